"""`dtoc identify` on PUBLIC REAL measurements: held-out error before -> after, effects, what stays unexplained.

    python -m bench.identify_public --data DIR [--write-docs]

Data (never committed; fetch them into DIR yourself):

- ``girfos``: the example thin-slice GIRF measurement of the open-source GIRFOS toolbox
  (github.com/ZemaTimoteo/GIRFOS_tool, ``Matlab_basedCode/Example/test64_GIRF_..._RFoff-50mm_tPulTotal-10ms``):
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


CASES = {
    "girfos": (
        "GIRFOS toolbox example: thin-slice (3 mm, 50 mm off-centre) k(t) of 12 triangles x 3 repeats on x and "
        "on y, 999 x 10 us (Siemens scanner, Pulseq)",
        load_girfos,
    ),
}


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


def run_case(name: str, data: IdentData) -> dict:
    t0 = time.perf_counter()
    r = identify(data, None)
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
        "| data set | held-out / noise: ideal -> updated | adopted (± stderr) | not adopted | what stays unexplained | s |",
        "|---|---|---|---|---|---|",
    ]
    for x in rows:
        out.append(
            f"| {x['name']}: {CASES[x['name']][0]} | {x['channel']}: {x['before']:.2f} -> {x['after']:.2f} "
            f"(noise {x['noise']:.3g}) | {x['adopted']} | {x['rejected']} | {' / '.join(x['notes']) or 'nothing'} "
            f"| {x['seconds']:.0f} |"
        )
    return "\n".join(out)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", type=Path, required=True, help="folder holding the fetched data sets (see docstring)")
    p.add_argument("--write-docs", action="store_true")
    a = p.parse_args(argv)
    rows = []
    for name, (_, loader) in CASES.items():
        folder = a.data / name
        if not folder.is_dir():
            print(f"{name}: skipped ({folder} absent)")
            continue
        data = loader(folder)
        x = run_case(name, data)
        rows.append(x)
        print(
            f"{name}: held-out {x['channel']} {x['before']:.2f} -> {x['after']:.2f} x noise; adopted {x['adopted']}; "
            f"not adopted {x['rejected']}; {x['seconds']:.1f} s"
        )
        for n in x["notes"]:
            print(f"  - {n}")
        for n in x["rejected_reasons"]:
            print(f"  - not adopted: {n}")
    if a.write_docs and rows:
        from bench._report import DOC, write_section

        write_section(
            "identify_public",
            "Public real measurements",
            "Declared model: ideal hardware; identify with its defaults (see the module docstring of "
            "`bench/identify_public.py` for the data and their conversion).\n\n" + table(rows) + "\n",
            "python -m bench.identify_public --data DIR --write-docs",
            doc=DOC.parent / "identify.md",
        )


if __name__ == "__main__":
    main()
