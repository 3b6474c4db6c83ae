"""Run MRzeroCore 1.2.0 (the reference PDG simulator) on a dtoc phantom and a .seq file.

This script runs in a THROW-AWAY environment that has MRzeroCore (AGPL-3.0) installed, never in the
dtoc environment, and imports nothing from dtoc (it only calls MRzeroCore's public API):

    python3 -m venv /tmp/mrzero_env
    /tmp/mrzero_env/bin/pip install torch==2.13.0        # first, or pip pulls the CUDA wheels
    /tmp/mrzero_env/bin/pip install MRzeroCore==1.2.0 pypulseq==1.5.0.post1
    /tmp/mrzero_env/bin/python bench/sim/mrzero_reference.py reference --seq S.seq --phantom P.npz --out R.npz
    /tmp/mrzero_env/bin/python bench/sim/mrzero_reference.py bench --seq S.seq --phantom P.npz --out B.json

Only numbers leave this script (an .npz with the complex signal, a JSON with timings).

Alignment with dtoc (docs/metrics.md, "Agreement with MRzeroCore"):
* phantom: dtoc (ny, nx) maps -> MRzero (x, y, z=1) voxel grid (transposed), voxel size FOV/n,
  voxel centres (i - n//2) dx in both codes (identical for even n); D in 1e-9 m^2/s (MRzero's unit);
  'box' voxel shape in both (sinc(k dx) attenuation per in-plane axis); the z voxel extent is set
  to 1 um so that MRzero's z box attenuation is 1, as dtoc's 2D sheet (no z attenuation);
  background voxels (PD = 0) are masked out by MRzero's PD threshold (their inf relaxation times never
  reach it); B0 and B1 maps passed as they are (the fixtures use B0 = 0, B1 = 1).
* sequence: the same .seq file.  MRzero's pulseq-rs importer puts RF rotations at the pulse centre
  and ADC samples at the Pulseq times (delay + (i + 0.5) dwell), as dtoc.
* signal: MRzero returns PD-weighted sums over voxels with transverse magnitude sin(FA) after an
  excitation (same units as dtoc); its receiver phase convention differs by a constant factor, so
  comparisons are done on magnitude images (the paper's NRMSE) -- see tests/test_sim_mrzero.py.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import resource
import sys
import time

import numpy as np


@contextlib.contextmanager
def _quiet():
    """Silence Python-level prints; MRzero's Rust part writes to fd 1 directly, so redirect that too."""
    sys.stdout.flush()
    saved = os.dup(1)
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 1)
    try:
        with contextlib.redirect_stdout(io.StringIO()):
            yield
    finally:
        sys.stdout.flush()
        os.dup2(saved, 1)
        os.close(saved)
        os.close(devnull)


def load_mr0_phantom(path: str, mr0, torch):
    """dtoc phantom .npz -> MRzero SimData (box voxels)."""
    z = np.load(path, allow_pickle=False)
    pd = z["pd"]
    ny, nx = pd.shape
    fov = np.atleast_1d(z["fov_m"]).astype(float)
    if fov.size == 1:
        fov = np.repeat(fov, 2)

    def grid(a, fill=0.0):
        a = np.where(np.isfinite(a), a, fill).astype(np.float64)
        return torch.as_tensor(a.T[:, :, None].copy(), dtype=torch.float32)  # (x, y, z)

    get = lambda k, default: z[k] if k in z.files else np.full(pd.shape, default)  # noqa: E731
    big = 1e6  # stand-in for inf relaxation times (MRzero needs finite values); only in PD = 0 voxels here
    ph = mr0.VoxelGridPhantom(
        PD=grid(pd),
        T1=grid(z["t1_s"], big),
        T2=grid(z["t2_s"], big),
        T2dash=grid(get("t2dash_s", np.inf), big),
        D=grid(get("d_m2_per_s", 0.0) * 1e9),
        B0=grid(get("b0_hz", 0.0)),
        B1=grid(get("b1", 1.0))[None],
        coil_sens=torch.ones((1, nx, ny, 1), dtype=torch.complex64),
        affine=torch.tensor(
            [[fov[0] / nx * 1e3, 0, 0, 0], [0, fov[1] / ny * 1e3, 0, 0], [0, 0, 1e-3, 0], [0, 0, 0, 1]],
            dtype=torch.float32,
        ),
    )
    return ph.build(voxel_shape="box")


# MRzero settings, from its documented defaults to the strict reference.  'defaults' is exactly what
# MRzero users run (compute_graph with its voxel-Nyquist cut-off, which drops the box voxels' sinc
# tails); the intermediate levels and 'strict' use the same pre-pass with the cut-off disabled
# (compute_graph_ext, nyquist = inf), i.e. MRzero converging to its own strict answer.
LEVELS = {
    "defaults": (
        dict(max_state_count=200, min_state_mag=1e-4),
        dict(min_emitted_signal=1e-2, min_latent_signal=1e-2),
        False,
    ),
    "mid3": (
        dict(max_state_count=1000, min_state_mag=1e-5),
        dict(min_emitted_signal=1e-3, min_latent_signal=1e-3),
        True,
    ),
    "mid4": (
        dict(max_state_count=5000, min_state_mag=1e-6),
        dict(min_emitted_signal=1e-4, min_latent_signal=1e-4),
        True,
    ),
    "strict": (
        dict(max_state_count=100000, min_state_mag=1e-7),
        dict(min_emitted_signal=1e-7, min_latent_signal=1e-7),
        True,
    ),
}


def run(seq_path, phantom_path, strict: bool = True, repeats: int = 0, n_dummies: int = 0, level: str | None = None):
    import torch

    with _quiet():
        import MRzeroCore as mr0
    torch.manual_seed(0)
    t0 = time.perf_counter()
    data = load_mr0_phantom(phantom_path, mr0, torch)
    with _quiet():
        seq = mr0.Sequence.import_file(seq_path)
    t_import = time.perf_counter() - t0
    level = level or ("strict" if strict else "defaults")
    graph_kw, exec_kw, no_cutoff = LEVELS[level]
    t0 = time.perf_counter()
    with _quiet():
        if no_cutoff:
            # compute_graph() passes the voxel Nyquist frequency to the pre-pass, which then treats every state
            # beyond it as emitting nothing -- right for 'sinc' voxels, wrong for the 'box' voxels used here
            # (their sinc(k dx) tails are real signal; up to 30 % error on a single voxel).  Same pre-pass with
            # the Nyquist cut-off disabled:
            graph = mr0.compute_graph_ext(
                seq,
                float(data.T1.mean()),
                float(data.T2.mean()),
                float(data.T2dash.mean()),
                float(data.D.mean()),
                nyquist=(float("inf"),) * 3,
                size=tuple(float(v) for v in data.size),
                avg_b1_trig=data.avg_B1_trig,
                **graph_kw,
            )
        else:  # exactly what MRzero users run
            graph = mr0.compute_graph(seq, data, **graph_kw)
    t_graph = time.perf_counter() - t0

    def forward(requires_grad: bool):
        for rep in seq:
            rep.gradm.requires_grad_(requires_grad)
            if rep.gradm.grad is not None:
                rep.gradm.grad = None
        with _quiet():
            return mr0.execute_graph(graph, seq, data, print_progress=False, **exec_kw)

    # first call of the new sequence (cold: the first simulation of this process), gradient included
    t0 = time.perf_counter()
    signal = forward(True)
    (signal.real**2 + signal.imag**2).sum().backward()
    t_first = time.perf_counter() - t0
    out = {
        "signal": signal.detach().numpy().astype(np.complex128).T,  # (n_coils, N_adc)
        "t_import_s": t_import,
        "t_graph_s": t_graph,
        "t_first_fwd_bwd_s": t_first,
        "graph_kw": graph_kw,
        "exec_kw": exec_kw,
        "level": level,
        "mrzero_version": mr0.__version__,
        "torch_version": torch.__version__,
        "threads": torch.get_num_threads(),
    }
    if repeats:
        fw, fb = [], []
        for _ in range(repeats):
            t0 = time.perf_counter()
            with torch.no_grad():
                forward(False)
            fw.append(time.perf_counter() - t0)
            if fw[-1] > 20:
                break
        for _ in range(repeats):
            t0 = time.perf_counter()
            s = forward(True)
            loss = (s.real**2 + s.imag**2).sum()
            loss.backward()
            fb.append(time.perf_counter() - t0)
            if fb[-1] > 20:
                break
        grad_norm = float(sum(float(r.gradm.grad.norm() ** 2) for r in seq if r.gradm.grad is not None) ** 0.5)
        out.update({"t_fwd_s": min(fw), "t_fwd_bwd_s": min(fb), "grad_norm": grad_norm})
    out["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("mode", choices=["reference", "bench"])
    ap.add_argument("--seq", required=True)
    ap.add_argument("--phantom", required=True, help="dtoc phantom .npz (dtoc.sim.phantom.save_phantom)")
    ap.add_argument("--out", required=True, help="reference: .npz with the signal; bench: .json")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--defaults", action="store_true", help="bench with MRzero's default thresholds (else strict)")
    ap.add_argument(
        "--level", choices=sorted(LEVELS), default=None, help="bench at this MRzero setting (overrides --defaults)"
    )
    ap.add_argument("--threads", type=int, default=0)
    a = ap.parse_args(argv)
    if a.threads:
        import torch

        torch.set_num_threads(a.threads)
    if a.mode == "reference":
        r = run(a.seq, a.phantom, strict=True)
        np.savez_compressed(
            a.out,
            signal=r["signal"],
            mrzero_version=np.asarray(r["mrzero_version"]),
            thresholds=np.asarray(json.dumps({**r["graph_kw"], **r["exec_kw"]}, sort_keys=True)),
        )
    else:
        try:
            r = run(a.seq, a.phantom, strict=not a.defaults, repeats=a.repeats, level=a.level)
            sig = r.pop("signal")
            np.save(a.out + ".signal.npy", sig)
            r["ok"] = True
        except MemoryError as e:  # pragma: no cover - reported, not hidden
            r = {
                "ok": False,
                "error": f"MemoryError: {e}",
                "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
            }
        except RuntimeError as e:
            r = {
                "ok": False,
                "error": f"RuntimeError: {str(e)[:200]}",
                "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
            }
        with open(a.out, "w") as f:
            json.dump(r, f, indent=1, default=str)


if __name__ == "__main__":
    main()
