"""Benchmark of the hardware twin: forward + backward time of the chains used by the optimizer.

Run: ``python -m bench.bench_hardware`` (writes the "Hardware twin" section of docs/benchmarks.md).
Cases: the paper's 64x64 EPI (echo spacing 0.73 ms) and the 32-repetition GRE, both on the 10 us
gradient raster, i.e. the IR's 5 us fine grid, through (a) the full 3x3 GIRF with B0 row
(girf/example_7T.npz, 10 us taps, 20 ms kernel -> resampled to 5 us), (b) the published KCL 2024 3x3
GIRF (5000 taps at 10 us) when ../shared/data is present, (c) the paper's two-term exponential eddy
model on all axes.  Time = min and median of repeated (forward, sum, backward w.r.t. the demanded waveform).
"""

from __future__ import annotations

import os
import statistics
import sys
import time
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench._report import write_section  # noqa: E402
from dtoc.hardware import HardwareModel, build_effect, model_from_girf  # noqa: E402
from dtoc.seq.load import load_sequence  # noqa: E402


def _time(model, g, dt, dtype, reps=7):
    x = torch.as_tensor(g, dtype=dtype).clone().requires_grad_(True)
    model.requires_grad_(False)

    def once():
        G, b0 = model(x, dt)
        (G.sum() + b0.sum()).backward()
        x.grad = None

    once()  # warm-up (kernel resampling plans are cached)
    ts = []
    for _ in range(reps):
        t0 = time.perf_counter()
        once()
        ts.append(time.perf_counter() - t0)
    return min(ts), statistics.median(ts)


def main():
    # one intra-op thread: on the shared 2-core CI machine two OpenMP threads competing with other jobs
    # made every FFT 10-100x slower (spin-waiting); set DTOC_BENCH_THREADS to override
    torch.set_num_threads(int(os.environ.get("DTOC_BENCH_THREADS", "1")))
    load0 = os.getloadavg()[0]
    models = {"3x3 GIRF + B0 (example_7T, 2048 taps)": model_from_girf(REPO / "girf" / "example_7T.npz")}
    shared = REPO.parent / "shared" / "data" / "girf" / "kcl_7T_terra_2024" / "7T_GIRF.mat"
    if shared.exists():
        from dtoc.hardware.girf_import import import_girf
        from dtoc.hardware.model import girf_effect

        models["3x3 GIRF (KCL 2024, 5000 taps)"] = HardwareModel([girf_effect(import_girf([shared]))])
    models["exp_eddy 2 terms (1 ms, 100 ms), all axes"] = HardwareModel(
        [build_effect("exp_eddy", {"alpha": [0.1, 0.1], "tau_s": [1e-3, 0.1]})]
    )
    seqs = {
        "EPI 64x64 esp 0.73 ms": REPO / "sequences" / "epi_esp073.seq",
        "GRE 32x32, 32 reps": REPO / "sequences" / "gre_paper.seq",
    }
    rows = []
    for sname, sp in seqs.items():
        ir = load_sequence(sp)
        for mname, m in models.items():
            for dtype in (torch.float32, torch.float64):
                tmin, tmed = _time(m, ir.grad_mT_per_m, ir.dt_fine_s, dtype)
                rows.append(
                    f"| {sname} | {ir.n_fine} | {mname} | {str(dtype).split('.')[-1]} | {tmin * 1e3:.1f} | {tmed * 1e3:.1f} |"
                )
                print(rows[-1], flush=True)
    body = (
        "Forward + backward (w.r.t. the demanded waveform) of the hardware model on the IR's fine grid "
        "(dt = 5 us), batch 1, 3 axes, model frozen (as in the optimizer); min and median of 7 after one warm-up "
        f"(load average at start {load0:.1f}: other jobs shared the CPU, so the median is noisy).\n\n"
        "| sequence | samples per axis | model | dtype | min (ms) | median (ms) |\n|---|---|---|---|---|---|\n"
        + "\n".join(rows)
    )
    write_section("hardware", "Hardware twin", body, "python -m bench.bench_hardware")


if __name__ == "__main__":
    main()
