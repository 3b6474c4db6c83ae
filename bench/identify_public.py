"""`dtoc identify` on PUBLIC REAL measurements: held-out error before -> after, effects, what stays unexplained.

    python -m bench.identify_public --data DIR [--write-docs] [--only NAME,...] [--save-rows F.json]
    python -m bench.identify_public --rows F.json [F.json ...] --write-docs     # compose saved rows
    python -m bench.identify_public --data DIR --only NAME --without KIND,...     # diagnostic, no docs

Data (never committed; fetch them into DIR yourself; neither repository has a licence file, so the data are
read locally and never redistributed):

- ``girfos``: the example thin-slice GIRF measurement of the open-source GIRFOS toolbox
  (github.com/ZemaTimoteo/GIRFOS_tool, commit b6562cb7d1be,
  ``Matlab_basedCode/Example/test64_GIRF_..._RFoff-50mm_tPulTotal-10ms``):
  ``Results/Data_test64.mat`` (coil-combined ADC signals of a 3 mm slice 50 mm off isocentre, with and
  without the test gradient, 12 triangles x 3 repeats per axis, x and y) and the ``.seq`` file that played them
  (Pulseq 1.2: 12 negative triangles of 115 T/m/s, 100-320 us long, peak 5.75-18.4 mT/m, in the middle of a
  999-sample ADC of 10 us).  Copy them as ``DIR/girfos/Data_test64.mat`` and ``DIR/girfos/test64.seq``.

Conversion (this module, no code of the toolbox): the demanded gradient of each acquisition is the ``.seq``
arbitrary gradient (amplitude x the decoded shape, Hz/m -> mT/m), sampled at the ADC times (Pulseq: shape
point i at (i + 1/2) x 10 us, ADC sample j at 10 us + (j + 1/2) x 10 us: shape point j + 1); the measured k
is the thin-slice phase (unwrapped phase with the gradient minus without, per acquisition) divided by the
slice offset 0.05 m, with its mean over the first 400 samples (before any gradient) removed.  The three
repeats are kept as repeated waveforms (noise floor from their scatter; folds keep repeats together).  The
driven axis alone is measured (``axes_measured``).  A slice offset that is not exactly 50 mm scales the
measured k like a gain of the driven axis: identify cannot tell the two apart from these data.
Check of this time axis (issue 37): the toolbox itself pairs input sample i with the output difference
k[i+1] - k[i] and keeps only |H| (``get_GIRF.m``: ``H.Hx_w = abs(...)``), so it fixes no time origin; on
the converted data the first moment of the measured gradient (t_end k_end - integral of k, over k_end; the
low-frequency group delay of any linear chain) lies +0.64 us (x) and +0.07 us (y) after the demand's, the
same for all 12 durations and 3 repeats (``centroid_shift``).  A timing offset in the conversion would
shift it by the offset (half a raster = 5 us for the other Pulseq sample convention): there is none beyond
what the data measure.

- ``bruker_girf``: the 7 T preclinical (Bruker, ParaVision 6.0.1) trajectory measurements of
  github.com/ju-kloiber/Bruker-GIRF (commit 694dd0792dd1, ``resources/exp7/result_*.jcamp``; copy them as
  ``DIR/bruker_girf/result_<N>.jcamp``): ParaVision's trajectory adjustment (``PVM_TrajKx/Ky/Kz``, 5028
  samples of 2 us, k in 1/mm) for 13 triangles of 48.6 x m mT/m (m = 1..13, files result_7 ... result_94)
  at 6075 T/m/s, as the repository's ``examples/girf.jl`` states them (its ``construct_nominal_G``: the
  triangle starts at the first sample, t_j = j x 2 us).  The final k of every file matches the nominal
  triangle's area to < 0.1 % on every axis, which checks the amplitudes.  Conversion: g = that triangle
  (rise 4m samples: the stated 8.00001 us x m snapped to the 2 us raster), k = 2 pi x 1000 x PVM_TrajK (rad/m).
  *Assumed*: each axis was measured with its triangle alone (one waveform per file and axis, only that axis
  measured); the files hold a separate B0 term per axis (``PVM_TrajBx/By/Bz``, unit not stated, not used).
  Had the three axes played together, the cross terms would not be separable from the self terms
  (identical waveforms), which identify refuses to label anyway, so nothing identifiable is dropped.

Each case is identified against ideal hardware with the defaults.  ``--write-docs`` writes the section
``identify_public`` of docs/identify.md.  A data set missing under DIR is skipped with a line.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from dtoc.identify.data import IdentData
from dtoc.identify.search import identify

GAMMA_BAR_HZ_PER_T = 42.576e6
DT = 10e-6


def _parse_seq(path: Path):
    """(blocks, gradients {id: (amplitude Hz/m, shape id, delay us)}, shapes {id: (n, compressed samples)}) of
    a Pulseq 1.2 file (only what the GIRFOS file uses)."""
    sec = None
    blocks, grads, shapes = [], {}, {}
    cur = 0
    for line in path.read_text().splitlines():
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        if s.startswith("["):
            sec = s
            continue
        if sec == "[BLOCKS]":
            blocks.append([int(x) for x in s.split()])
        elif sec == "[GRADIENTS]":
            a = s.split()
            grads[int(a[0])] = (float(a[1]), int(a[2]), float(a[3]))
        elif sec == "[SHAPES]":
            if s.startswith("shape_id"):
                cur = int(s.split()[1])
            elif s.startswith("num_samples"):
                shapes[cur] = (int(s.split()[1]), [])
            else:
                shapes[cur][1].append(float(s))
    return blocks, grads, shapes


def _decode(n: int, d: list) -> np.ndarray:
    """Pulseq shape decompression: run-length coded derivative ("a a k": a repeated k + 2 times), summed."""
    out: list[float] = []
    j = 0
    while j < len(d):
        out.append(d[j])
        if j + 1 < len(d) and d[j + 1] == d[j]:
            out += [d[j]] * (1 + int(round(d[j + 2])))
            j += 3
        else:
            j += 1
    w = np.cumsum(out)
    if w.size != n:
        raise ValueError(f"shape decodes to {w.size} samples, expected {n}")
    return np.where(np.abs(w) < 1e-6, 0.0, w)


def load_girfos(folder: Path) -> IdentData:
    """The GIRFOS thin-slice example as a docs/contracts.md §1 measurement (module docstring)."""
    import scipy.io as sio

    blocks, grads, shapes = _parse_seq(folder / "test64.seq")
    mat = sio.loadmat(folder / "Data_test64.mat")
    gs, ks, meas = [], [], []
    for ax, key, col in ((0, "kx", 3), (1, "ky", 4)):
        ids = [b[col] for b in blocks if b[6] == 1 and b[col] not in (0, 3)]  # gradient id 3: amplitude 0
        sig_g = mat[f"{key}_cc_grad"][:, 0, :]
        sig_0 = mat[f"{key}_cc_noGrad"][:, 0, :]
        n = sig_g.shape[0]
        phase = np.unwrap(np.angle(sig_g), axis=0) - np.unwrap(np.angle(sig_0), axis=0)
        phase -= phase[:400].mean(axis=0)
        k = phase / 0.05  # rad/m: phase = k x slice offset
        for m, gid in enumerate(ids):
            amp, shape_id, _ = grads[gid]
            w = amp * _decode(*shapes[shape_id]) / GAMMA_BAR_HZ_PER_T * 1e3  # mT/m on the 10 us raster
            g = np.zeros((3, n))
            g[ax] = w[1 : n + 1]
            kk = np.zeros((3, n))
            kk[ax] = k[:, m]
            am = np.zeros(3, dtype=bool)
            am[ax] = True
            gs.append(g)
            ks.append(kk)
            meas.append(am)
    labels = [f"{'xy'[i // 36]} triangle {(i % 36) // 3 + 1} repeat {i % 3 + 1}" for i in range(len(gs))]
    return IdentData(dt_s=DT, g=np.stack(gs), k=np.stack(ks), sigma={}, labels=labels, axes_measured=np.stack(meas))


BRUKER_FILES = (7, 14, 21, 29, 36, 43, 50, 58, 65, 72, 80, 87, 94)  # result_N.jcamp, in the order of BRUKER_AMP x 1..13
BRUKER_AMP = 48.601  # mT/m: peak of the first triangle; triangle m (1-based) peaks at m x BRUKER_AMP
BRUKER_SLEW = 6075.067308  # T/m/s, every triangle
BRUKER_DT = 2e-6  # s, ADC dwell
BRUKER_N = 5028  # samples per axis and file


def _jcamp_arrays(path: Path) -> dict[str, np.ndarray]:
    """The ``##$PVM_Traj<name>=( n )`` arrays of a ParaVision trajectory-adjustment result (JCAMP-DX)."""
    import re

    text = path.read_text()
    out = {}
    for m in re.finditer(r"##\$PVM_Traj(\w+)=\( (\d+) \)\n(.*?)(?=##)", text, re.S):
        v = np.array(m.group(3).split(), dtype=float)
        if v.size != int(m.group(2)):
            raise ValueError(f"{path.name}: PVM_Traj{m.group(1)} holds {v.size} values, header says {m.group(2)}")
        out[m.group(1)] = v
    return out


def load_bruker(folder: Path) -> IdentData:
    """The Bruker-GIRF 7 T preclinical triangles (``exp7``) as a docs/contracts.md §1 measurement (docstring)."""
    t = np.arange(BRUKER_N) * BRUKER_DT
    gs, ks, meas, labels = [], [], [], []
    for m, num in enumerate(BRUKER_FILES, start=1):
        arr = _jcamp_arrays(folder / f"result_{num}.jcamp")
        amp = m * BRUKER_AMP
        rise = round(amp / BRUKER_SLEW * 1e-3 / BRUKER_DT) * BRUKER_DT  # 8.00001 us x m, snapped to 4m samples
        tri = amp * np.clip(1.0 - np.abs(t - rise) / rise, 0.0, None)
        for ax, name in enumerate("xyz"):
            kk = arr[f"K{name}"]
            if kk.size != BRUKER_N:
                raise ValueError(f"result_{num}.jcamp: PVM_TrajK{name} has {kk.size} samples, expected {BRUKER_N}")
            g = np.zeros((3, BRUKER_N))
            g[ax] = tri
            k = np.zeros((3, BRUKER_N))
            k[ax] = 2 * np.pi * 1e3 * kk  # 1/mm -> rad/m
            am = np.zeros(3, dtype=bool)
            am[ax] = True
            gs.append(g)
            ks.append(k)
            meas.append(am)
            labels.append(f"{name} triangle {amp:.1f} mT/m")
    return IdentData(
        dt_s=BRUKER_DT, g=np.stack(gs), k=np.stack(ks), sigma={}, labels=labels, axes_measured=np.stack(meas)
    )


CASES = {
    "girfos": (
        "GIRFOS toolbox example: thin-slice (3 mm, 50 mm off-centre) k(t) of 12 triangles x 3 repeats on x and "
        "on y, 999 x 10 us (Siemens scanner, Pulseq)",
        load_girfos,
    ),
    "bruker_girf": (
        "Bruker-GIRF exp7: ParaVision trajectory adjustment k(t) of 13 triangles (48.6-632 mT/m, 6075 T/m/s), "
        "each axis alone, 5028 x 2 us (7 T preclinical Bruker, ParaVision 6.0.1)",
        load_bruker,
    ),
}


def centroid_shift(data: IdentData) -> np.ndarray:
    """(M,) seconds: first moment of the measured gradient minus that of the demand, per waveform, on its
    measured axis over the demanded pulse +-30/40 samples, from k (G = dk/dt / gamma: the first moment is
    (t_b k_b - t_a k_a - integral k) / (k_b - k_a), no differentiation of noisy k).  For a linear chain it is
    the group delay at low frequency; a timing offset of the data adds to it one to one."""
    gamma = 2 * np.pi * 42.577478e6 * 1e-3  # rad/m per (mT/m s)
    t = np.arange(data.g.shape[-1]) * data.dt_s
    out = np.full(data.g.shape[0], np.nan)
    for m in range(data.g.shape[0]):
        ax = int(np.flatnonzero(data.axes_measured[m])[0]) if data.axes_measured is not None else 0
        g = data.g[m, ax]
        nz = np.flatnonzero(g)
        if nz.size == 0 or data.k is None:
            continue
        a, b = max(nz[0] - 30, 0), min(nz[-1] + 40, g.size - 1)
        kp = gamma * np.concatenate([[0.0], np.cumsum(0.5 * (g[1:] + g[:-1]) * data.dt_s)])
        out[m] = _first_moment(data.k[m, ax], t, a, b) - _first_moment(kp, t, a, b)
    return out


def _first_moment(k: np.ndarray, t: np.ndarray, a: int, b: int) -> float:
    """First moment in time of G = dk/dt / gamma on [t_a, t_b], from k alone (integration by parts)."""
    integral = np.trapezoid(k[a : b + 1], t[a : b + 1])
    return float((t[b] * k[b] - t[a] * k[a] - integral) / (k[b] - k[a]))


def _fmt_effect(f) -> str:
    from dtoc.identify.candidates import lti_features, lti_physical_text
    from dtoc.identify.kinds import effect_name

    e = f.effect
    if e.kind == "lti":
        ft = lti_features(e.taps.detach().numpy().reshape(-1), int(round(e.t0_s / e.dt_s)), e.dt_s)
        return f"{effect_name(e)} ({lti_physical_text(ft)})"
    ps = []
    for k, v in e.params_dict().items():
        if isinstance(v, float):
            se = f.stderr.get(k)
            ps.append(f"{k} {v:.4g}" + (f" ± {se:.2g}" if isinstance(se, float) else ""))
    return f"{effect_name(e)} ({', '.join(ps)})"


def run_case(name: str, data: IdentData, without: frozenset = frozenset()) -> dict:
    from dtoc.identify.kinds import CANDIDATE_KINDS

    t0 = time.perf_counter()
    r = identify(data, None, kinds=[k for k in CANDIDATE_KINDS if k not in without] if without else None)
    secs = time.perf_counter() - t0
    c = "k" if data.G is None else "G"
    s = r.noise[c].sigma
    return {
        "name": name,
        "channel": c,
        "before": r.heldout_before[c] / s,
        "after": r.heldout_after[c] / s,
        "noise": s,
        "noise_method": r.noise[c].method,
        "adopted": "; ".join(_fmt_effect(f) for f in r.twin.found) or "none",
        "rejected": "; ".join(x["effect"] for x in r.rejected) or "none",
        "rejected_reasons": [" / ".join(x["reasons"]) for x in r.rejected],
        "notes": [n for n in r.remaining if not n.startswith("not adopted")],
        "explained": r.explained,
        "seconds": secs,
    }


def table(rows: list[dict]) -> str:
    out = [
        "| data set | held-out / noise: ideal -> updated | adopted (± stderr) | not adopted | what stays unexplained "
        "| s (load avg) |",
        "|---|---|---|---|---|---|",
    ]
    for x in rows:
        window = f"the first {x['window_ms']:.3g} ms" if x.get("window_ms") else "the whole records"
        out.append(
            f"| {x['name']}: {CASES[x['name']][0]}; identified on {window} "
            f"| {x['channel']}: {x['before']:.2f} -> {x['after']:.2f} "
            f"(noise {x['noise']:.3g}) | {x['adopted']} | {x['rejected']} | {' / '.join(x['notes']) or 'nothing'} "
            f"| {x['seconds']:.0f} ({x['load'][0]:.1f}-{x['load'][1]:.1f}, {x['date']}) |"
        )
    return "\n".join(out)


def main(argv=None) -> None:
    import datetime
    import json
    import os

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", type=Path, help="folder holding the fetched data sets (see docstring)")
    p.add_argument("--write-docs", action="store_true")
    p.add_argument("--only", default=None, help="comma-separated data set names (default: all)")
    p.add_argument("--without", default="", help="comma-separated candidate kinds left out (a diagnostic run)")
    p.add_argument("--save-rows", type=Path, help="write this run's rows as JSON (to compose a table later)")
    p.add_argument("--rows", type=Path, nargs="+", help="compose the table from saved rows instead of running")
    p.add_argument("--max-ms", type=float, help="use only the first MAX_MS ms of every record (stated in the row)")
    a = p.parse_args(argv)
    without = frozenset(x for x in a.without.split(",") if x)
    if a.write_docs and without:
        p.error("--without is a diagnostic: the docs table is written with the full library only")
    if (a.data is None) == (a.rows is None):
        p.error("give --data DIR (run) or --rows FILE... (compose saved rows)")
    only = set(a.only.split(",")) if a.only else set(CASES)
    if only - set(CASES):
        p.error(f"unknown data set(s): {', '.join(sorted(only - set(CASES)))}; known: {', '.join(CASES)}")
    rows = []
    if a.rows:
        saved = {}
        for f in a.rows:
            for x in json.loads(f.read_text()):
                saved[x["name"]] = x
        rows = [saved[n] for n in CASES if n in saved and n in only]
    for name, (_, loader) in CASES.items():
        if a.rows or name not in only:
            continue
        folder = a.data / name
        if not folder.is_dir():
            print(f"{name}: skipped ({folder} absent)")
            continue
        data = loader(folder)
        if a.max_ms:
            n = int(round(a.max_ms * 1e-3 / data.dt_s))
            data = IdentData(
                dt_s=data.dt_s,
                g=data.g[:, :, :n],
                k=None if data.k is None else data.k[:, :, :n],
                G=None if data.G is None else data.G[:, :, :n],
                sigma=data.sigma,
                labels=data.labels,
                axes_measured=data.axes_measured,
            )
        load0 = os.getloadavg()[0]
        x = run_case(name, data, without)
        x["window_ms"] = data.g.shape[-1] * data.dt_s * 1e3 if a.max_ms else None
        x["load"] = (load0, os.getloadavg()[0])
        x["date"] = datetime.date.today().isoformat()
        rows.append(x)
        print(
            f"{name}: held-out {x['channel']} {x['before']:.2f} -> {x['after']:.2f} x noise; adopted {x['adopted']}; "
            f"not adopted {x['rejected']}; {x['seconds']:.1f} s (load {x['load'][0]:.1f} -> {x['load'][1]:.1f})"
        )
        for n in x["notes"]:
            print(f"  - {n}")
        for n in x["rejected_reasons"]:
            print(f"  - not adopted: {n}")
    if a.save_rows and rows and not a.rows:
        tmp = a.save_rows.with_suffix(".tmp")
        tmp.write_text(json.dumps(rows, indent=1))
        os.replace(tmp, a.save_rows)
    if a.write_docs and rows:
        from bench._report import DOC, write_section

        write_section(
            "identify_public",
            "Public real measurements",
            "Declared model: ideal hardware; identify with its defaults (see the module docstring of "
            "`bench/identify_public.py` for the data and their conversion). Last column: wall seconds of "
            "the identification, the machine's load average at its start and end, and the date of the run "
            "(the rows may come from separate runs: `--save-rows`, `--rows`); identify runs with 1 torch thread "
            "(its default), whatever the line above says of the process that wrote this section.\n\n"
            + table(rows)
            + "\n",
            "python -m bench.identify_public --data DIR --write-docs` (or per data set `--only NAME --save-rows "
            "F.json`, then `--rows F.json ... --write-docs",
            doc=DOC.parent / "identify.md",
        )


if __name__ == "__main__":
    main()
