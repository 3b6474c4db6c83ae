"""Non-Cartesian image operator: which NUFFT library, by measurement.

Run: ``python -m bench.nufft [--no-write]`` (writes its section of docs/benchmarks.md).  The operator is
:mod:`dtoc.sim.ndft`'s ``I = E^H W s`` (density weights W fixed, computed once) on multi-shot spiral
trajectories; each candidate computes the image and the gradient of ``sum |I|^2`` w.r.t. ``s`` (what the
optimizer's image term needs), float64, one thread, against the exact sum (dense matrix, chunked):

* the exact dense operator (``dtoc.sim.ndft``, what dtoc uses up to 2e7 entries);
* finufft (``dtoc.sim.nufft``: type 1 forward, type 2 backward, tolerance 1e-10);
* torchkbnufft (``KbNufftAdjoint``, pure torch autograd; default table interpolation and its exact
  ``Toeplitz``-free sparse-matrix mode where it fits).

Times: median of 5 repeats after one warm-up (plans / interpolation tables built outside the timing, as
both are cached per trajectory in use).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]


def _spiral(m: int, kmax: float, shots: int) -> np.ndarray:
    t = np.linspace(0, 1, m // shots)
    k = np.concatenate(
        [kmax * t * np.exp(1j * (2 * np.pi * 16 * np.sqrt(t) + 2 * np.pi * s / shots)) for s in range(shots)]
    )
    return np.stack([k.real, k.imag])


def _exact(k, shape, fov, w, s) -> np.ndarray:
    """The exact image, chunked over pixels (no dense matrix in memory)."""
    ny, nx = shape
    x = (np.arange(nx) - nx // 2) * fov[0] / nx
    y = (np.arange(ny) - ny // 2) * fov[1] / ny
    X, Y = np.meshgrid(x, y)
    r = np.stack([X.ravel(), Y.ravel()])
    out = np.empty(r.shape[1], dtype=np.complex128)
    ws = w * s
    for i in range(0, r.shape[1], 256):
        out[i : i + 256] = np.exp(1j * (r[:, i : i + 256].T @ k)) @ ws
    return out.reshape(ny, nx)


def _time(fn, reps: int = 5) -> float:
    fn()
    ts = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts)


def run_case(m: int, n: int, shots: int) -> list[dict]:
    from dtoc.sim import nufft
    from dtoc.sim.ndft import EXACT_MAX_ENTRIES

    fov = (0.22, 0.22)
    k = _spiral(m, np.pi * n / fov[0] * 0.98, shots)
    m = k.shape[1]
    keep = np.ones(m, dtype=bool)
    p = nufft.plan(k, k.tobytes(), (n, n), fov, keep, torch.float64)
    w = p.w
    rng = np.random.default_rng(0)
    s_np = rng.standard_normal(m) + 1j * rng.standard_normal(m)
    ref = _exact(k, (n, n), fov, w, s_np)
    scale = np.abs(ref).max()
    rows = []

    def record(name, fn):
        s = torch.as_tensor(s_np).requires_grad_(True)

        def fb():
            s.grad = None
            img = fn(s)
            (img.abs() ** 2).sum().backward()
            return img

        img = fb()
        err = float(np.abs(img.detach().numpy() - ref).max() / scale)
        rows.append({"M": m, "N": n, "operator": name, "fwd_bwd_s": _time(fb), "max_rel_error": err})

    if m * n * n <= 4 * EXACT_MAX_ENTRIES:
        x = (np.arange(n) - n // 2) * fov[0] / n
        X, Y = np.meshgrid(x, x)
        EH = torch.as_tensor(np.exp(1j * (np.stack([X.ravel(), Y.ravel()]).T @ k)) * w)  # (P, M), dtoc.sim.ndft's

        def dense(s):
            return (s @ EH.T).reshape(n, n)

        record("exact dense (dtoc.sim.ndft)", dense)
    record("finufft 1e-10 (dtoc.sim.nufft)", lambda s: nufft.nufft_image(s, p))
    try:
        import torchkbnufft as tkbn
    except ImportError:
        return rows
    adj = tkbn.KbNufftAdjoint(im_size=(n, n), dtype=torch.float64)
    # torchkbnufft's omega is k in radians per pixel, one row per image dimension (rows: y, columns: x)
    om = torch.as_tensor(np.stack([k[1] * fov[1] / n, k[0] * fov[0] / n]))
    wt = torch.as_tensor(w)
    record("torchkbnufft table (default)", lambda s: adj((s * wt)[None, None], om)[0, 0])
    if m * n * n <= 4 * EXACT_MAX_ENTRIES:
        sp = tkbn.calc_tensor_spmatrix(om, im_size=(n, n))
        record("torchkbnufft sparse matrix", lambda s: adj((s * wt)[None, None], om, interp_mats=sp)[0, 0])
    return rows


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--no-write", action="store_true")
    a = ap.parse_args(argv)
    sys.path.insert(0, str(REPO))
    torch.set_num_threads(1)
    rows = []
    for m, n, shots in ((20868, 50, 3), (65536, 128, 8), (262144, 256, 16)):
        rows += run_case(m, n, shots)
        print(rows[-1], flush=True)
    text = render(rows)
    print(text)
    if not a.no_write:
        from bench._report import write_section

        write_section(
            "nufft", "Non-Cartesian image operator: NUFFT library by measurement", text, "python -m bench.nufft"
        )


def render(rows: list[dict]) -> str:
    import finufft

    try:
        import torchkbnufft

        tk = torchkbnufft.__version__
    except ImportError:
        tk = "absent"
    head = (
        "Spiral trajectories (M samples, N x N image), float64, 1 thread; "
        f"finufft {finufft.__version__}, torchkbnufft {tk}. Image E^H W s and the gradient of sum |I|^2 w.r.t. s "
        "(median of 5 after a warm-up; plans and tables built before). Error: max |I - I_exact| / max |I_exact|, "
        "I_exact by the chunked exact sum.\n\n"
        "| M | N | operator | image + gradient (s) | max relative error |\n|---|---|---|---|---|\n"
    )
    lines = [
        f"| {r['M']} | {r['N']} | {r['operator']} | {r['fwd_bwd_s']:.4g} | {r['max_rel_error']:.2e} |" for r in rows
    ]
    ratios = []
    for m in sorted({r["M"] for r in rows}):
        t = {r["operator"].split(" (")[0]: r["fwd_bwd_s"] for r in rows if r["M"] == m}
        fi = t.get("finufft 1e-10")
        if fi and "torchkbnufft table" in t:
            ratios.append(f"{t['torchkbnufft table'] / fi:.1f}x (M = {m})")
    tail = (
        f"\nfinufft against torchkbnufft's default: {', '.join(ratios)} faster, at ~1e-10 instead of ~1e-3 error; "
        "dtoc uses finufft above the exact operator's size (docs/metrics.md).\n"
        if ratios
        else ""
    )
    return head + "\n".join(lines) + "\n" + tail


if __name__ == "__main__":
    main()
