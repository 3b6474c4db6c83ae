"""Sequences dtoc did not write, end to end: the corpus of tests/foreign/writers.py through check, simulate,
predict and optimize with a real measured GIRF at explicit limits, every output verified independently.

Run: ``python -m bench.foreign [--girf H.npz] [--only NAME ...] [--no-write]`` -> docs/foreign.md (table,
date, machine).  Default GIRF: the KCL 7 T Terra 2024 3x3 GIRF imported from ``../shared/data`` (skipped
cleanly when absent).  Verification of every output, none of it by dtoc's writer:
(1) pypulseq reads it and ``check_timing`` passes; (2) ``dtoc check`` at the same limits; (3) the peak slew
from pypulseq's own decoding of the gradient shapes (``waveforms_and_times``); (4) the realized k of the
re-read output against the base's nominal k, in dk; (5) ``dtoc diff`` base vs output lists gradient
differences only.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
SHARED_GIRF = REPO.parent / "shared" / "data" / "girf" / "kcl_7T_terra_2024" / "7T_GIRF.mat"
GMAX, SMAX = 32.0, 130.0

CORPUS = [  # name, description, writer call
    ("gre", "2D spoiled GRE 32x32, RF use undefined", "gre()"),
    ("epi", "2D single-shot EPI 32x32, flat-top sampling", "epi()"),
    ("se_epi", "spin-echo EPI 32x32 (180 'refocusing')", "se_epi()"),
    ("se_epi_ramp", "spin-echo EPI, ramp sampling", "se_epi(ramp_sampling=True)"),
    ("tse", "TSE, 4 shots x ETL 8, CPMG", "tse()"),
    ("haste", "HASTE-like single-shot TSE, half Fourier", "tse(single_shot=True)"),
    ("radial", "2D radial GRE, 32 spokes x 64", "radial()"),
    ("spiral_1", "2D spiral, single shot", "spiral(1, n=16)"),
    ("spiral_3", "2D spiral, 3 interleaves", "spiral(3)"),
    ("ute", "2D UTE-like centre-out half spokes", "ute()"),
    ("gre3d", "3D GRE 16x16x8 (slab), image term on the built-in 3D head", "gre3d()"),
    ("multislice_labels", "3-slice GRE 16x16, LIN/SLC labels, soft delay", "gre_multislice_labels()"),
    ("mprage", "3D MPRAGE-like 32x32x8, inversion + TI, 8 shots of 1 s (windowed)", "mprage(nz=8)"),
]
#: members too long for the default test job (tests/test_foreign_corpus.py marks them slow): 49-63 s each on
#: 2 cores (radial, gre3d, ute; non-Cartesian and 3D paths keep fast tests in test_ndft.py and test_sim_3d.py)
SLOW = {"mprage", "radial", "gre3d", "ute", "se_epi", "se_epi_ramp", "spiral_3"}  # (17-24 s each on a 2-core AMD EPYC)
#: extra optimize/simulate options per member (an image term on a 3D phantom is asked for, never assumed)
EXTRA = {"gre3d": ("--phantom", "brain3d")}


def write_corpus(d: Path, only) -> list[tuple[str, str, Path]]:
    sys.path.insert(0, str(REPO / "tests"))
    from foreign import writers as W  # noqa: F401  (used by eval)

    out = []
    for name, desc, call in CORPUS:
        if only and name not in only:
            continue
        p = d / f"{name}.seq"
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            p.write_bytes(eval("W." + call))  # noqa: S307  (calls of our own writers)
        out.append((name, desc, p))
    return out


def corpus_girf(d: Path, given: Path | None) -> Path | None:
    if given is not None:
        return given
    if not SHARED_GIRF.exists():
        return None
    from dtoc.hardware.girf_import import import_girf
    from dtoc.hardware.girf_io import save_girf

    p = d / "kcl2024.npz"
    save_girf(import_girf([SHARED_GIRF]), p)
    return p


def _cli(*argv) -> tuple[int, str, str]:
    import contextlib
    import io

    from dtoc.cli.main import run

    o, e = io.StringIO(), io.StringIO()
    code = 0
    with contextlib.redirect_stdout(o), contextlib.redirect_stderr(e):
        try:
            run([str(a) for a in argv])
        except SystemExit as ex:
            code = ex.code or 0
    return code, o.getvalue(), e.getvalue()


def pypulseq_checks(path: Path) -> tuple[bool, float]:
    """pypulseq read + check_timing, and the peak slew (T/m/s) from pypulseq's own shape decoding."""
    import pypulseq as pp

    from dtoc.constants import GAMMA_HZ_PER_T
    from dtoc.seq.pulseq import quiet

    s = pp.Sequence()
    with quiet():
        s.read(str(path))
        ok, _ = s.check_timing()
        wave = s.waveforms_and_times()[0]
    worst = 0.0
    for w in wave:
        if w.shape[1] < 2:
            continue
        dt = np.diff(w[0])
        m = dt > 1e-9
        worst = max(worst, float(np.max(np.abs(np.diff(w[1])[m] / dt[m]))) / GAMMA_HZ_PER_T)
    return bool(ok), worst


#: the official Pulseq C++ reader (``ExternalSequence``) as a program: a path given by this variable (docs/foreign.md,
#: "The official C++ reader"); unset: the column says "-"
CPP_READER_ENV = "DTOC_PULSEQ_CPP_READER"


def cpp_reader_check(path: Path) -> dict | None:
    """Load ``path`` once with the official Pulseq C++ reader: SeqEyes (which compiles Pulseq's ExternalSequence
    class) run as ``--exit-after-load``; it parses every section, checks the signature and decodes every block.
    Returns {ok, blocks, duration_s, messages} (ok: exit 0 and no ERROR/WARNING line), or None when no reader is
    configured."""
    import re
    import subprocess

    exe = os.environ.get(CPP_READER_ENV)
    if not exe:
        return None
    env = {**os.environ, "QT_QPA_PLATFORM": "offscreen"}
    p = subprocess.run([exe, "--exit-after-load", str(path)], capture_output=True, text=True, env=env, timeout=600)
    text = p.stdout + p.stderr
    bad = [ln.strip() for ln in text.splitlines() if "ERROR" in ln or "WARNING" in ln]
    nb = re.search(r"(\d+) blocks detected", text)
    du = re.search(r"total duration: ([0-9.eE+-]+) seconds", text)
    return {
        "ok": p.returncode == 0 and not bad,
        "blocks": int(nb.group(1)) if nb else None,
        "duration_s": float(du.group(1)) if du else None,
        "messages": bad[:3],
    }


def _pypulseq_blocks_duration(path: Path) -> tuple[int, float]:
    import pypulseq as pp

    from dtoc.seq.pulseq import quiet

    s = pp.Sequence()
    with quiet():
        s.read(str(path))
    return len(s.block_events), float(s.duration()[0])


def _realized_error_dk(base: Path, out: Path, girf: Path, dk) -> float:
    """max |k_realized(output re-read) - k_nominal(base)| / dk over the encoded axes."""
    import dtoc
    from dtoc.seq.load import load_sequence

    h = dtoc.load_model(girf=str(girf))
    b, o = load_sequence(base), load_sequence(out)
    k0 = b.nominal_kspace_rad_per_m()
    k = dtoc.Twin(o, h).forward().kspace_rad_per_m.detach().numpy()
    dk = np.asarray(dk, dtype=float)
    fin = np.isfinite(dk)
    return float(np.max(np.abs(k[fin] - k0[fin]) / dk[fin, None]))


def run_one(name: str, desc: str, seq: Path, girf: Path, d: Path) -> dict:
    row: dict = {"name": name, "what": desc}
    code, out, err = _cli("check", seq, "--gmax", GMAX, "--smax", SMAX, "--json", "-")
    row["base_check_ok"] = code == 0
    code, out, err = _cli("predict", seq, "--girf", girf, "--json", "-")
    row["predict_ok"] = code == 0
    t0 = time.perf_counter()
    o, m = d / f"{name}_opt.seq", d / f"{name}_opt.json"
    extra = EXTRA.get(name, ())
    code, _, err = _cli(
        "optimize", seq, "--girf", girf, "--gmax", GMAX, "--smax", SMAX, "-o", o, "--json", m, "-q", *extra
    )
    row["optimize_s"] = time.perf_counter() - t0
    if code != 0:
        row["error"] = err.strip().splitlines()[-1] if err.strip() else f"exit {code}"
        return row
    man = json.loads(m.read_text())
    row["kind"] = man["sequence"].get("kind") if "kind" in man["sequence"] else None
    row["grid"] = bool(man["sequence"]["image_term"])
    row["k_before_dk"] = man["before"]["kspace_max_error_dk"]
    row["k_after_dk"] = man["after"]["kspace_max_error_dk"]
    row["nrmse_before_pct"] = man["before"]["nrmse_percent"]
    row["nrmse_after_pct"] = man["after"]["nrmse_percent"]
    row["n_adc"] = man["sequence"]["n_adc_samples"]
    dks = [x for x in man["sequence"]["dk_rad_per_m"] if x is not None and math.isfinite(x)]
    row["dk_rad_per_m"] = min(dks) if dks else None
    row["dk_from_fov"] = man["sequence"]["dk_source"].startswith("grid")
    row["discarded"] = man["n_samples_discarded"]
    u = (man.get("solver") or {}).get("unreachable") or {}
    # the solve was bound by the limits: samples above the tolerance, every one named at an active limit
    row["limits_bound"] = bool(u.get("n_samples")) and u.get("n_limits") == u.get("n_samples")
    code, _, _ = _cli("check", o, "--gmax", GMAX, "--smax", SMAX)
    row["check_ok"] = code == 0
    row["pypulseq_timing_ok"], row["slew_independent"] = pypulseq_checks(o)
    row["k_after_reread_dk"] = _realized_error_dk(seq, o, girf, man["sequence"]["dk_rad_per_m"])
    cpp = cpp_reader_check(o)
    if cpp is not None:
        nb, du = _pypulseq_blocks_duration(o)
        cpp["agrees_with_pypulseq"] = (
            cpp["blocks"] == nb and cpp["duration_s"] is not None and abs(cpp["duration_s"] - du) < 1e-6
        )
    row["cpp_reader"] = cpp
    code, out, _ = _cli("diff", seq, o, "--json", "-")
    whats = {x["what"] for x in json.loads(out)["differences"]}
    row["only_gradients_changed"] = all(w.startswith(("grad", "definition", "shape")) for w in whats)
    if row["grid"]:
        code, out, _ = _cli("simulate", seq, "--girf", girf, "--json", "-", "-q", *extra)
        row["simulate_ok"] = code == 0
    return row


def _fmt(v, nd=3):
    if v is None:
        return "-"
    if isinstance(v, bool):
        return "yes" if v else "NO"
    return f"{v:.{nd}g}"


def _cpp_cell(c: dict | None) -> str:
    if c is None:
        return "-"
    if c["ok"] and c.get("agrees_with_pypulseq"):
        return f"yes ({c['blocks']} blocks, {c['duration_s']:.6g} s)"
    return "NO: " + ("; ".join(c["messages"]) or f"{c['blocks']} blocks, {c['duration_s']} s (pypulseq differs)")


def render(rows: list[dict], girf_name: str) -> str:
    import torch

    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    import datetime as dt

    head = (
        "# Foreign sequences: files dtoc did not write\n\n"
        "Written by `python -m bench.foreign`; run "
        f"{dt.date.today().isoformat()} on {cpu}, {os.cpu_count()} cores, Python {platform.python_version()}, "
        f"torch {torch.__version__}.\n\n"
        "The corpus: `tests/foreign/writers.py`, pypulseq scripts of our own in the style users start from: no "
        "FOV/matrix or limit definitions, RF with the writers' default use (undefined; refocusing pulses marked "
        "'refocusing' as users do), the usual pypulseq k-space layouts. Each file: `dtoc check` and `dtoc predict`, "
        f"then `dtoc optimize --girf {girf_name} --gmax {GMAX:g} --smax {SMAX:g}` (default settings), and the output "
        "verified without dtoc's writer: pypulseq reads it and `check_timing` passes; `dtoc check` at the same limits; "
        "the peak slew from pypulseq's own decoding of the shapes; the realized k of the *re-read* output against "
        "the base's nominal k; `dtoc diff` shows gradient changes only; the official Pulseq C++ reader loads it "
        "(below, \"The official C++ reader\"; '-' where none was configured).\n\n"
        "k errors are the max over ADC samples and encoded axes, in dk: 2 pi / FOV where a Cartesian grid is "
        "inferred from the ADC k positions or the file's FOV, else the readouts' sampling step (marked *). NRMSE: "
        "image of the built-in phantom where the file has an image term (iFFT or non-uniform DFT).\n\n"
    )
    cols = (
        "| file | what | image | k before (dk) | k after (dk) | k after, re-read output (dk) | NRMSE before -> after (%) "
        "| check 32/130 | pypulseq timing | Pulseq C++ reader | peak slew, pypulseq decoding (T/m/s) | gradients only "
        "| dk (rad/m) | time (s) |"
    )
    lines = [cols, "|" + "---|" * 14]
    for r in rows:
        if "error" in r:
            lines.append(
                f"| {r['name']} | {r['what']} | | | | | | | | | | | | {r['optimize_s']:.1f} (error: {r['error']}) |"
            )
            continue
        star = "" if r.get("dk_from_fov", r["grid"]) else "*"
        nr = "-" if r["nrmse_before_pct"] is None else f"{r['nrmse_before_pct']:.3g} -> {r['nrmse_after_pct']:.3g}"
        lines.append(
            f"| {r['name']} | {r['what']} | {_fmt(r['grid'])} | {_fmt(r['k_before_dk'])}{star} | "
            f"{_fmt(r['k_after_dk'])}{star} | {_fmt(r['k_after_reread_dk'])}{star} | {nr} | {_fmt(r['check_ok'])} | "
            f"{_fmt(r['pypulseq_timing_ok'])} | {_cpp_cell(r.get('cpp_reader'))} | {r['slew_independent']:.1f} | {_fmt(r['only_gradients_changed'])} | "
            f"{_fmt(r['dk_rad_per_m'])} | {r['optimize_s']:.1f} |"
        )
    return head + "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--girf", type=Path, default=None, help="GIRF .npz (default: KCL 2024 from ../shared/data)")
    ap.add_argument("--only", nargs="*", default=None)
    ap.add_argument("--no-write", action="store_true")
    a = ap.parse_args()
    with tempfile.TemporaryDirectory() as td:
        d = Path(td)
        girf = corpus_girf(d, a.girf)
        if girf is None:
            print("no GIRF: ../shared/data absent and no --girf given; nothing to do")
            return
        rows = []
        for name, desc, seq in write_corpus(d, a.only):
            r = run_one(name, desc, seq, girf, d)
            print(json.dumps({k: (round(v, 4) if isinstance(v, float) else v) for k, v in r.items()}), flush=True)
            rows.append(r)
        text = render(rows, "KCL 7 T Terra 2024 3x3 (../shared/data, imported)" if a.girf is None else a.girf.name)
    if not a.no_write:
        doc = REPO / "docs" / "foreign.md"
        old = doc.read_text() if doc.exists() else ""
        keep = "<!-- public-corpus:begin -->"  # bench.public_corpus's section and what follows it are kept
        doc.write_text(text + _NOTES + ("\n" + old[old.index(keep) :] if keep in old else ""))
    print(text)
    bad = [
        r["name"]
        for r in rows
        if "error" in r
        or not (r.get("check_ok") and r.get("pypulseq_timing_ok"))
        or (r.get("cpp_reader") is not None and not _cpp_cell(r["cpp_reader"]).startswith("yes"))
    ]
    if bad:
        print("FAILED:", bad)
        raise SystemExit(1)
    _ = math


_NOTES = """
## RF use of files before format 1.5
Pulseq files before format 1.5.0 carry no RF `use`, and the k-space of a spin echo depends on it (a refocusing
pulse negates k, an excitation sets it to 0). dtoc decides it as Pulseq MATLAB's `read(..., 'detectRFuse')` and
pypulseq's `read(detect_rf_use=True)` (its default for such files) do, per event of the file's `[RF]` section, from
the pulse alone (`dtoc.seq.rfuse`): flip angle below 90.01 deg: excitation; otherwise a pulse longer than 6 ms at
-3.4 to -3.5 ppm: (fat) saturation; otherwise refocusing. One refinement that cannot change k at any ADC sample: a
refocusing-strength pulse followed by an excitation before any ADC sample is an inversion. The notes say, per
`[RF]` event, its flip, duration, count and use, and how it was decided; `--rf-use ID=use,...` (simulate,
predict, optimize) overrides any (ID: the event's number in `[RF]`; uses by name or initial), and the optimize
manifest records the table (`sequence.rf_use`). A 1.4.1 spin-echo EPI (tests/foreign/writers_truth.py) gets k
centred (the same trajectory as pypulseq's detection) and its 32 x 32 Cartesian grid; read with every pulse as
an excitation its readout ran from +670 to +1480 rad/m. Format 1.5 files state the use: kept; an explicit
`undefined` is taken as an excitation, as the reference tools' k-space calculations do, and said so.

## What dtoc check checks
Three kinds of rule, each violation naming its kind and where its rule or value came from (`kind`, `source` in
`--json`; columns "kind" and "from" of the table; the summary groups the failures by kind):

| kind | rules | from |
|---|---|---|
| `format` | what the file's format version requires: LF line endings, the md5 signature when there is one (the specification makes it optional: an unsigned file gets a warning), integer fields, the raster definitions format 1.4 requires, block durations and event times on the file's own declared rasters, events inside their blocks, gradients continuous between blocks and ending at zero | `Pulseq format 1.4.1` (the file's version) |
| `limits` | gradient amplitude and slew rate per axis and as vectors; PNS and acoustic bands when a profile has them | as given: `--gmax 32 --smax 130`, `--scanner NAME`, `--system FILE`, or the limits a dtoc-built file records |
| `convention` | a vendor's: RF dead time and ring-down, ADC dead time, the ADC sample count (a multiple of `adc_samples_divisor`, at most `adc_max_samples`; where the file declares `MaxAdcSegmentLength` the interpreter splits the ADC into segments of that length, and the segment obeys them, a whole number of segments ending on the gradient raster), the file's rasters against the scanner's (the gradient raster equal; the RF, ADC and block rasters whole multiples: a declared 10 us RF raster is legal on a 1 us scanner) | only `--scanner NAME` or `--system FILE`; the ADC sample rules only where the profile names them. Otherwise "not checked", never assumed |

So `dtoc check --gmax G --smax S` checks the format and the limits, and says that the vendor conventions were not
checked: Pulseq's MATLAB demos with their 20 us ring-down, files declaring `MaxAdcSegmentLength` with 12,000
samples per ADC and a 10 us RF raster pass; the same files with a profile naming a 30 us ring-down fail on that,
as `convention (--scanner NAME): 16 x rf_ringdown (worst 20 us vs 30 us)`. `dtoc optimize` checks its output for
the format and the limits (and PNS / acoustics of the profile); an output that fails any of them is never
reported as "0 violations": the summary names the failed rules with their values and the command exits 1.

## Figures for files dtoc did not write
Each printed figure is meaningful or replaced by a reason: no signal (RF flips below 1e-6 rad: "no signal: ...",
no NRMSE of 0 %); grid and FOV from the file's `FOV` and `MatrixSize`/`Matrix` definitions where it has them,
the notes comparing them with the grid of the ADC k positions (e.g. "the ADC positions step by 2 pi / 500 mm
along x (readout), not 2 pi / the defined 250 mm (oversampled 2x)"); ramp-sampled readouts take the file's FOV
(the readout's mean sampling step, the fallback without one, says nothing of the designed FOV when the ramps are
sampled too); phase lines -N/2+1 .. N/2 (encoded from the top, as JEMRIS writes them) are an N grid, not N+2; a
file whose samples are on no grid is told why (e.g. "k steps along z too ...: blocks whose z gradient area is not
rewound (e.g. field-camera sync blocks) accumulate kz"). simulate and optimize share one "before" (docs/metrics.md).

## Reading the table
- Column "image": whether the file gets an image term (and NRMSE): a Cartesian grid inferred from the ADC k
  positions (iFFT), or a 2D non-Cartesian trajectory with a known FOV -- radial with a constant step (FOV = 2 pi /
  step) or a FOV definition in the file, as the spiral writers set -- reconstructed by a non-uniform DFT with
  Pipe-Menon density weights on the nominal trajectory (`dtoc.sim.ndft`: exact up to 2e7 samples x pixels,
  above that the same operator by finufft to 1e-10, `dtoc.sim.nufft`; the 3-shot spiral, 20868 samples x 50^2
  pixels, and the UTE are the cases). Ramp-sampled readouts without a FOV definition: straight Cartesian lines
  (the ramp-sampled EPI) get FOV 2 pi / (the readout's mean step, the phase step) and N = samples per line x
  phase lines; straight radial spokes with ramps (the UTE) get FOV 2 pi / the flat-top step (the sampled,
  oversampled FOV); in both the non-uniform DFT regrids the ramp samples. 3D Cartesian files: the 3D grid is
  inferred from the ADC k positions (`dtoc.seq.geometry.infer_cartesian_grid_3d`; k in units of 2 pi / FOV per
  axis, dkz = 2 pi / the slab FOV); the image term is asked for with `--phantom brain3d` (the built-in 3D head,
  `dtoc.sim.phantom.brain_phantom_3d`, on that grid), reconstructed by a 3D iFFT (gre3d). Without it (mprage,
  windowed) k-space terms only.
- `*`: no image grid, so the k unit is the readouts' sampling step (column dk).
- The spirals are written close to the slew limit (127 of 130 T/m/s), which leaves the optimizer little room;
  that is physics, not a bug to tune away.
- The slice axis is held (`k` after excitation set by the file), except when k is encoded along it (3D): then it
  is optimized outside RF. Soft-delay blocks are never given gradients (their duration changes on the scanner).
- Multi-slice files: the representative is the slices' average. The slices share one in-plane encoding (only
  the RF frequency and the slice labels differ), so the grid is inferred over all slices together and the image
  term reconstructs one 2D object from every slice's samples, averaged per grid point: each slice's trajectory
  error enters the image with equal weight, and the k-space term scores every sample of every slice on its own.
  A per-slice image would need a per-slice object, which the built-in phantom does not have.
- The MPRAGE-like file (7.9 s) is longer than `window_auto_s` (4 s): it is solved one excitation period at a
  time (docs/optimize.md, "Long sequences"), k-space terms only; its k error is over the three encoded axes.

- The MPRAGE-like file with the image term (`--phantom brain3d`, so not windowed: the whole 7.9 s at once),
  measured once by hand on the example GIRF (2026-11-26, same machine): NRMSE 6.58 % -> 0.204 %, k 0.191 ->
  0.0046 dk, 0 violations at 32/130, 550 s wall, 2.2 GB peak RSS; the windowed k-space-only solve is the
  table's row.

## The official C++ reader
Column "Pulseq C++ reader": every output loaded once by Pulseq's own C++ reader, the `ExternalSequence` class
that scanners' interpreters compile. It was not built from the pulseq sources here: this workplace reaches
package indexes only, not GitHub. What was run instead is the same class as compiled into SeqEyes (the Pulseq
viewer, whose binary carries `ExternalSequence` and its messages), from the `pypulseqpp-seqeyes` wheel on PyPI
with Qt from `PySide6-Essentials`, both installed in a throw-away virtual environment outside the repository
and never committed:

    python3 -m venv /tmp/cpp && /tmp/cpp/bin/pip install PySide6-Essentials pypulseqpp-seqeyes
    DTOC_PULSEQ_CPP_READER=/tmp/cpp/bin/pypulseqpp-seqeyes python -m bench.foreign

`seqeyes --exit-after-load FILE` (offscreen) parses every section, checks the file's MD5 signature and decodes
every block's events (shape decompression included); "yes" = exit 0, no ERROR or WARNING line, and its block
count and total duration equal pypulseq's. It does reject what it should: a removed `[BLOCKS]` header ("***
ERROR: Required: [BLOCKS] section", exit 4) and a corrupted `num_samples` of a shape ("compressed shape format
error ... Decode SeqBlock failed", exit 4; plus the signature warning).
"""


if __name__ == "__main__":
    main()
