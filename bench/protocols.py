"""Real protocol sizes: `dtoc optimize` on clinical matrices, multi-slice EPI and minutes-long 3D, each on a
real measured GIRF.

Run: ``python -m bench.protocols [--rows NAME ...] [--timeout S] [--no-write]`` (writes its section of
docs/benchmarks.md).  Each row is built here (dtoc's own EPI spec, or pypulseq writers: this module's
multi-slice EPI, 3D FLASH at 1 mm and ADNI-like MPRAGE; the project's TSE writer of tests/foreign/writers.py),
then optimized by its own ``python -m dtoc optimize`` process with the default options (the user's command) and the KCL 7 T
Terra 2024 3x3 GIRF from ``../shared/data`` (docs: docs/optimize.md).  Per row: wall and CPU time, peak RSS
(``wait4``), the k error before -> after and the image NRMSE from the manifest, the solver's evaluations and stop
reason (or the windowed solve's windows).  A row that does not finish within ``--timeout`` is reported so, with
its peak RSS up to then: never a projected figure.
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from bench._proc import run_step

REPO = Path(__file__).resolve().parents[1]


def epi_multislice(
    n: int = 64,
    slices: int = 4,
    reps: int = 1,
    fov: float = 0.22,
    tr_slice: float = 0.08,
    ramp_sampling: bool = True,
    labels: bool = True,
) -> bytes:
    """Gradient-echo multi-slice EPI in the style of a pypulseq script: per repetition and slice a sinc
    excitation (slice offset by RF frequency), prephasers, ``n`` readouts (on the ramps too when
    ``ramp_sampling``) with blips, a spoiler and the fill to ``tr_slice``; labels SLC / REP / LIN."""
    import pypulseq as pp

    from tests.foreign.writers import _bytes, _fill, _sinc, _system

    sys_ = _system(pp)
    seq = pp.Sequence(sys_)
    thk, gap = 3e-3, 6e-3
    rf, gz, gzr = _sinc(pp, sys_, 70, thk, 2e-3)
    dk = 1 / fov
    if ramp_sampling:
        gx = pp.make_trapezoid("x", area=n * dk, system=sys_)
        dur = pp.calc_duration(gx)
        dwell = math.floor((dur - 2 * sys_.adc_dead_time) / n / 1e-7) * 1e-7
        adc = pp.make_adc(n, dwell=dwell, delay=math.floor((dur - n * dwell) / 2 / 1e-6) * 1e-6, system=sys_)
    else:
        gx = pp.make_trapezoid("x", flat_area=n * dk, flat_time=n * 8e-6 + 20e-6, system=sys_)
        adc = pp.make_adc(n, duration=n * 8e-6, delay=gx.rise_time + 10e-6, system=sys_)
    blip = pp.make_trapezoid("y", area=dk, system=sys_)
    gxpre = pp.make_trapezoid("x", area=-gx.area / 2, duration=1e-3, system=sys_)
    gypre = pp.make_trapezoid("y", area=-(n / 2) * dk, duration=1e-3, system=sys_)
    spoil = pp.make_trapezoid("z", area=4 / thk, system=sys_)
    t_train = n * pp.calc_duration(gx) + (n - 1) * pp.calc_duration(blip)
    fill = tr_slice - pp.calc_duration(rf, gz) - pp.calc_duration(gzr) - 1e-3 - t_train - pp.calc_duration(spoil)
    if fill < 0:
        raise ValueError("epi_multislice: tr_slice too short for the echo train")
    for r in range(reps):
        for s in range(slices):
            rf.freq_offset = gz.amplitude * (s - slices // 2) * gap
            seq.add_block(rf, gz)
            seq.add_block(gzr)
            seq.add_block(gxpre, gypre)
            g = gx
            for i in range(n):
                lab = [pp.make_label("LIN", "SET", i)]
                if labels and i == 0:
                    lab += [pp.make_label("SLC", "SET", s), pp.make_label("REP", "SET", r)]
                seq.add_block(g, adc, *lab)
                if i < n - 1:
                    seq.add_block(blip)
                g = pp.scale_grad(g, -1)
            seq.add_block(spoil)
            seq.add_block(_fill(pp, sys_, fill))
    return _bytes(seq)


def _gre_train_events(pp, sys_, nx: int, fov_x: float, bw_px_hz: float, prep_s: float, spoil_s: float):
    """The readout events of a Cartesian 3D GRE: an x readout of ``nx`` samples at ``bw_px_hz`` per pixel (dwell on
    the 100 ns ADC raster, the flat top on the 10 us gradient raster), its prephaser in ``prep_s`` and a spoiler of
    one cycle per pixel in ``spoil_s``."""
    dk = 1 / fov_x
    dwell = round(1 / (bw_px_hz * nx) / 1e-7) * 1e-7
    flat = math.ceil(nx * dwell / 1e-5 - 1e-9) * 1e-5
    gx = pp.make_trapezoid("x", flat_area=nx * dk, flat_time=flat, system=sys_)
    delay = gx.rise_time + round((flat - nx * dwell) / 2 / 1e-6) * 1e-6
    adc = pp.make_adc(nx, dwell=dwell, delay=delay, system=sys_)
    gxpre = pp.make_trapezoid("x", area=-gx.area / 2, duration=prep_s, system=sys_)
    spoil = pp.make_trapezoid("x", area=nx * dk, duration=spoil_s, system=sys_)
    return gx, adc, gxpre, spoil


def _encode(pp, sys_, ky: float, kz: float, dur_s: float) -> list:
    """The (y, z) phase-encode trapezoids of areas ``ky``, ``kz`` (1/m) in ``dur_s``; a zero area plays none."""
    return [pp.make_trapezoid(ax, area=a, duration=dur_s, system=sys_) for ax, a in (("y", ky), ("z", kz)) if a != 0]


def gre3d_1mm(
    nx: int = 256,
    ny: int = 192,
    nz: int = 96,
    tr: float = 6.5e-3,
    flip_deg: float = 10,
    bw_px_hz: float = 400,
    partitions: int | None = None,
) -> bytes:
    """3D spoiled GRE (FLASH-like) at 1 mm isotropic: FOV ``nx`` x ``ny`` x ``nz`` mm, a 1 ms slab-selective sinc over
    the ``nz`` mm slab, ``ny`` x ``nz`` TRs of ``tr`` (defaults: 256 x 192 x 96, TR 6.5 ms: 119.8 s), RF spoiling
    117 deg, readout on x at ``bw_px_hz`` Hz/pixel, phase on y (inner loop) and partition on z (outer); a
    T1-weighted 3D FLASH of about 2 minutes (protocol values assumed, typical of a 3 T T1w 3D GRE).  ``partitions``:
    only that many of the ``nz`` partitions, the central ones (a shorter cut of the same protocol: the same TRs and
    encoding amplitudes, fewer of them)."""
    import pypulseq as pp

    from tests.foreign.writers import _bytes, _fill, _sinc, _system

    sys_ = _system(pp)
    seq = pp.Sequence(sys_)
    fov = (nx * 1e-3, ny * 1e-3, nz * 1e-3)
    prep, spoil_s = 0.8e-3, 1.2e-3
    rf, gz, gzr = _sinc(pp, sys_, flip_deg, fov[2], 1e-3)
    gx, adc, gxpre, spoil = _gre_train_events(pp, sys_, nx, fov[0], bw_px_hz, prep, spoil_s)
    fill = tr - pp.calc_duration(rf, gz) - prep - spoil_s - pp.calc_duration(gx)
    if fill < 0:
        raise ValueError(f"gre3d_1mm: TR {tr * 1e3:g} ms is {-fill * 1e3:.2f} ms too short")
    dky, dkz = 1 / fov[1], 1 / fov[2]
    i = 0
    npar = nz if partitions is None else min(partitions, nz)
    for kz in (np.arange(nz // 2 - npar // 2, nz // 2 - npar // 2 + npar) - nz // 2) * dkz:
        for ky in (np.arange(ny) - ny // 2) * dky:
            phase = math.radians((117 * i * (i + 1) / 2) % 360)  # RF spoiling
            rf.phase_offset, adc.phase_offset, i = phase, phase, i + 1
            seq.add_block(rf, gz)
            seq.add_block(gxpre, *_encode(pp, sys_, ky, kz + gzr.area, prep))
            seq.add_block(gx, adc)
            seq.add_block(spoil, *_encode(pp, sys_, -ky, -kz, spoil_s))
            seq.add_block(_fill(pp, sys_, fill))
    return _bytes(seq)


#: the MPRAGE rows' timing, modelled on the ADNI 3 T protocol (values assumed from it, not a vendor's file): shot TR,
#: TI (to the train's centre) and echo spacing, s; flip of the train, deg; readout bandwidth, Hz per pixel
ADNI_LIKE = {"tr_shot": 2.3, "ti": 0.9, "esp": 7.0e-3, "flip_deg": 9.0, "bw_px_hz": 240.0}


def mprage_protocol(shots: int = 256, ky_step: int = 1, npar: int = 176, nx: int = 256) -> bytes:
    """MPRAGE at 1 mm isotropic, modelled on the ADNI 3 T protocol (:data:`ADNI_LIKE`: TR 2300 ms, TI 900 ms, flip
    9 deg, 256 x 256 x 176 at 1 mm): per shot a 10 ms inversion (block pulse, use 'inversion') and a spoiler,
    TI to the train's centre, a train of ``npar`` GRE readouts (the partition loop, linear: its centre at TI) at
    the echo spacing, then the recovery to the shot's TR.  ``shots`` ky lines,
    every ``ky_step``-th of 256 (2: every other line, as a 2x-undersampled acquisition without reference lines).
    256 shots: 9.8 min, 128 shots with ``ky_step`` 2: 4.9 min."""
    import pypulseq as pp

    from tests.foreign.writers import _bytes, _fill, _system

    sys_ = _system(pp)
    seq = pp.Sequence(sys_)
    fov = (nx * 1e-3, 0.256, npar * 1e-3)
    tr_shot, ti, esp = ADNI_LIKE["tr_shot"], ADNI_LIKE["ti"], ADNI_LIKE["esp"]
    prep, spoil_s = 0.8e-3, 1.2e-3
    inv = pp.make_block_pulse(flip_angle=math.pi, duration=10e-3, system=sys_, delay=sys_.rf_dead_time, use="inversion")
    inv_spoil = pp.make_trapezoid("z", area=4 / 1e-3, duration=4e-3, system=sys_)
    rf = pp.make_block_pulse(
        flip_angle=math.radians(ADNI_LIKE["flip_deg"]), duration=0.1e-3, system=sys_, delay=sys_.rf_dead_time
    )
    gx, adc, gxpre, spoil = _gre_train_events(pp, sys_, nx, fov[0], ADNI_LIKE["bw_px_hz"], prep, spoil_s)
    fill_es = esp - pp.calc_duration(rf) - prep - spoil_s - pp.calc_duration(gx)
    t_inv = pp.calc_duration(inv) + pp.calc_duration(inv_spoil)
    fill_ti = ti - t_inv - (npar // 2) * esp
    fill_shot = tr_shot - t_inv - fill_ti - npar * esp
    if min(fill_es, fill_ti, fill_shot) < 0:
        raise ValueError("mprage_protocol: timing does not fit (esp, ti or tr_shot too short)")
    dky, dkz = 1 / fov[1], 1 / fov[2]
    for s in range(shots):
        ky = (s * ky_step - 128) * dky
        seq.add_block(inv)
        seq.add_block(inv_spoil)
        seq.add_block(_fill(pp, sys_, fill_ti))
        for kz in (np.arange(npar) - npar // 2) * dkz:
            seq.add_block(rf)
            seq.add_block(gxpre, *_encode(pp, sys_, ky, kz, prep))
            seq.add_block(gx, adc)
            seq.add_block(spoil, *_encode(pp, sys_, -ky, -kz, spoil_s))
            seq.add_block(_fill(pp, sys_, fill_es))
        seq.add_block(_fill(pp, sys_, fill_shot))
    return _bytes(seq)


def _spec_epi(matrix: int, esp_ms: float) -> dict:
    import yaml

    d = yaml.safe_load((REPO / "sequences" / "epi_esp081.yaml").read_text())
    d.update(matrix=matrix, echo_spacing_ms=esp_ms, name=f"epi{matrix}")
    return d


#: pypulseq files carry no limits (dtoc never assumes them): the writers' system, 32 mT/m and 130 T/m/s
PYPULSEQ = ["--gmax", "32", "--smax", "130"]

#: name -> (description, how to make the base, extra dtoc optimize options)
ROWS: dict[str, tuple[str, str, list[str]]] = {
    "epi128": ("single-shot EPI 128, echo spacing 1.5 ms (dtoc spec)", "spec:128:1.5", []),
    "epi256": ("single-shot EPI 256, echo spacing 3.0 ms (dtoc spec)", "spec:256:3.0", []),
    "epi_ms4": ("4-slice ramp-sampled EPI 64, 10 repetitions (~3.2 s, pypulseq)", "epims:64:4:10", PYPULSEQ),
    "epi_labels": ("labelled EPI 64 with 8 repetitions (pypulseq, LIN/SLC/REP)", "epims:64:1:8", PYPULSEQ),
    "tse256": ("TSE 256, ETL 16 (pypulseq)", "tse:256:16", PYPULSEQ),
    "gre3d_1mm": ("3D FLASH 1 mm, 256 x 192 x 96, TR 6.5 ms (2.0 min, pypulseq)", "gre3d1mm:256:192:96", PYPULSEQ),
    "mprage5": (
        "MPRAGE 1 mm ADNI-like, 128 of 256 ky lines x 176 partitions (4.9 min, pypulseq)",
        "mprage:128:2",
        PYPULSEQ,
    ),
    "mprage10": ("MPRAGE 1 mm ADNI-like, 256 x 256 x 176 (9.8 min, pypulseq)", "mprage:256:1", PYPULSEQ),
}
#: the rows of earlier runs (one per name, the latest), rendered together: rows are run one session at a time
ROWS_FILE = Path(__file__).with_name("protocols_rows.json")


def make_base(how: str, d: Path) -> Path:
    """Write the row's base sequence into ``d``; returns its path."""
    kind, *a = how.split(":")
    p = d / "base.seq"
    if kind == "spec":
        import yaml

        spec = d / "spec.yaml"
        spec.write_text(yaml.safe_dump(_spec_epi(int(a[0]), float(a[1]))))
        r = subprocess.run([sys.executable, "-m", "dtoc", "build", str(spec), "-o", str(p), "--force"], cwd=REPO)
        if r.returncode:
            raise SystemExit(f"dtoc build failed for {how}")
        return p
    sys.path.insert(0, str(REPO))
    from tests.foreign import writers as W

    if kind == "epims":
        data = epi_multislice(n=int(a[0]), slices=int(a[1]), reps=int(a[2]))
    elif kind == "tse":
        data = W.tse(n=int(a[0]), etl=int(a[1]))
    elif kind == "gre3d1mm":
        data = gre3d_1mm(nx=int(a[0]), ny=int(a[1]), nz=int(a[2]))
    elif kind == "mprage":
        data = mprage_protocol(shots=int(a[0]), ky_step=int(a[1]))
    else:
        raise ValueError(how)
    p.write_bytes(data)
    return p


def run_row(name: str, girf: Path, timeout_s: float, d: Path) -> dict:
    desc, how, extra = ROWS[name]
    base = make_base(how, d)
    out, man = d / "out.seq", d / "m.json"
    argv = [sys.executable, "-m", "dtoc", "optimize", str(base), "--girf", str(girf), "--b0", "7", "-o", str(out)]
    argv += ["--json", str(man), "--force", "-q", "--no-trajectory", *extra]
    r = run_step(argv, timeout_s)
    rc, timed_out, err = r["rc"], r["timed_out"], r["err"]
    row = {
        "name": name,
        "desc": desc,
        "wall_s": r["wall_s"],
        "cpu_s": r["cpu_s"],
        "rss_gb": r["peak_mb"] * 1024 / 1e6,
        "timed_out": timed_out,
        "rc": rc,
    }
    if rc != 0 and not timed_out:
        last = err.strip().splitlines()[-1].replace(str(base), base.name) if err.strip() else f"exit {rc}"
        row["error"] = last[:300]  # no machine path (the base lies in a temporary folder)
    if man.exists():
        m = json.loads(man.read_text())
        sv = m.get("solver") or {}
        w = m.get("windowed") or {}
        row.update(
            duration_s=m["sequence"]["duration_s"],
            n_adc=m["sequence"]["n_adc_samples"],
            k_before=m["before"]["kspace_max_error_dk"],
            k_after=m["after"]["kspace_max_error_dk"],
            nrmse_before=m["before"].get("nrmse_percent"),
            nrmse_after=m["after"].get("nrmse_percent"),
            evaluations=sv.get("evaluations"),
            stop=sv.get("stop_reason") or ("windowed" if w else "fixed count"),
            windows=w.get("windows"),
            reused=w.get("windows_reusing_a_solve"),
            unreachable=(sv.get("unreachable") or {}).get("n_samples"),
            minimax=sv.get("minimax"),
        )
    return row


def render(rows: list[dict]) -> str:
    def f(v, fmt="{:.3g}"):
        return "-" if v is None else fmt.format(v)

    lines = [
        "| row | duration | ADC samples | wall / CPU | peak RSS | k before -> after (dk) | NRMSE before -> after "
        "| evaluations / windows | stop reason |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        if r.get("timed_out"):
            res = f"did not finish in {r['wall_s']:.0f} s"
            lines.append(
                f"| {r['desc']} | - | - | {res} (CPU {r['cpu_s']:.0f} s) | {r['rss_gb']:.2f} GB so far | - | - | - | - |"
            )
            continue
        if "k_after" not in r:
            lines.append(
                f"| {r['desc']} | - | - | failed: {r.get('error', '?')} | {r['rss_gb']:.2f} GB | - | - | - | - |"
            )
            continue
        ev = (
            f(r["evaluations"], "{}")
            if r["evaluations"] is not None
            else f"{r['windows']} windows ({r['reused']} reused)"
        )
        stop = r["stop"] + (f", {r['unreachable']} samples named" if r.get("unreachable") else "")
        mm = r.get("minimax")
        if mm:  # the warm start's minimax rounds (docs/optimize.md, "Solver", 4.)
            stop += f"; minimax rounds {mm['rounds']} ({mm['max_before_dk']:.3g} -> {mm['max_after_dk']:.3g} dk, {mm['stop_reason']})"
        lines.append(
            f"| {r['desc']} | {r['duration_s']:.3g} s | {r['n_adc']} | {r['wall_s']:.0f} s / {r['cpu_s']:.0f} s "
            f"| {r['rss_gb']:.2f} GB | {f(r['k_before'])} -> {f(r['k_after'])} "
            f"| {f(r['nrmse_before'], '{:.3g} %')} -> {f(r['nrmse_after'], '{:.3g} %')} | {ev} | {stop} |"
        )
    return "\n".join(lines)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(prog="python -m bench.protocols", description=__doc__.splitlines()[0])
    ap.add_argument("--rows", nargs="*", default=list(ROWS), choices=list(ROWS))
    ap.add_argument("--timeout", type=float, default=600.0, help="per row, s")
    ap.add_argument("--no-write", action="store_true")
    ap.add_argument("--girf", type=Path, default=None, help="a GIRF .npz instead of the KCL 2024 one")
    a = ap.parse_args(argv)
    from bench.foreign import SHARED_GIRF, corpus_girf

    rows = []
    with tempfile.TemporaryDirectory() as td:
        girf = corpus_girf(Path(td), a.girf)
        if girf is None:
            raise SystemExit(f"the measured GIRF is absent ({SHARED_GIRF})")
        for name in a.rows:
            with tempfile.TemporaryDirectory() as d:
                r = run_row(name, girf, a.timeout, Path(d))
            r["date"] = time.strftime("%Y-%m-%d")
            rows.append(r)
            print(json.dumps(r), flush=True)
    if not a.no_write:
        old = json.loads(ROWS_FILE.read_text()) if ROWS_FILE.exists() else []
        keep = {r["name"]: r for r in old}
        keep.update({r["name"]: r for r in rows})
        rows = [keep[n] for n in ROWS if n in keep]
        ROWS_FILE.write_text(json.dumps(rows, indent=1) + "\n")
    body = (
        "`dtoc optimize` with its defaults on each base, KCL 7 T Terra 2024 3x3 GIRF (measured), one process per "
        "row (peak RSS from wait4); rows from earlier runs of this command are kept (bench/protocols_rows.json, each "
        "with its date); rows not listed have not been run.\n\n" + render(rows)
    )
    if not a.no_write:
        from bench._report import write_section

        shown = " ".join(x if not x.endswith(".npz") else "GIRF.npz" for x in (argv or []))  # no machine paths
        write_section("protocols", "Real protocol sizes", body, "python -m bench.protocols " + shown)
    print(render(rows))


if __name__ == "__main__":
    main(sys.argv[1:])
