"""Line-aware 'separable' EPI signal against the per-sample windows, side by side in one process.

    python -m bench.sim.line_aware [--repeats 5] [--no-write]   -> docs/benchmarks.md "Line-aware EPI signal"

Cases: the 64x64 single-shot EPI (sequences/epi_esp081.seq) on 64, 128 and 256 phantoms and a 128x128 EPI on a
256 phantom, each with the nominal gradient and with the gradient realized by the bundled example 7 T GIRF (its
blip tails make the phase moment drift along every line: the Jacobi-Anger series of the line path). float32 (the
optimizer's inner loop) and float64, 1 torch thread, graph built once per case; forward and forward + backward
(loss sum |s|^2 w.r.t. the (3, 2N+1) gradient) timed interleaved (old, new, old, new, ...), minimum of the
repeats; the GEMM peak of this machine (one complex64 matrix product, 1 thread) for the achieved rate.  The
difference column: max |s_new - s_old| / max |s_old|.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[2]


def _ir(case):
    from dtoc.seq.load import load_sequence

    if case["epi"] == 64:
        return load_sequence(str(REPO / "sequences" / "epi_esp081.seq"))
    import yaml

    from dtoc.seq.build import build_ir
    from dtoc.seq.spec import parse_spec

    data = yaml.safe_load((REPO / "sequences" / "epi_esp081.yaml").read_text())
    data["matrix"] = case["epi"]
    data["echo_spacing_ms"] = 1.6
    data["name"] = f"epi{case['epi']}"
    return build_ir(parse_spec(data))


def gemm_peak_gflops(dtype=torch.complex64) -> float:
    """Achieved complex GEMM rate of this machine, 1 thread (8 real flops per complex multiply-add)."""
    a = torch.randn(512, 512, dtype=dtype)
    b = torch.randn(512, 512, dtype=dtype)
    a @ b
    best = np.inf
    for _ in range(5):
        t = time.perf_counter()
        a @ b
        best = min(best, time.perf_counter() - t)
    return 8 * 512**3 / best / 1e9


def run(repeats: int) -> list[dict]:
    import dtoc
    import dtoc.sim.pdg_signal as S
    from dtoc.sim.pdg import PDGConfig, build_graph, simulate
    from dtoc.sim.phantom import brain_phantom

    torch.set_num_threads(1)
    h = dtoc.load_model(girf=str(REPO / "girf" / "example_7T.npz"))
    rows = []
    for case in (dict(epi=64, n=64), dict(epi=64, n=128), dict(epi=64, n=256), dict(epi=128, n=256)):
        ir = _ir(case)
        ph = brain_phantom(case["n"], fov_m=ir.fov_m[:2])
        g = build_graph(ir, PDGConfig(), ph)
        G_real = dtoc.Twin(ir, h).forward().realized_grad_mT_per_m.detach()
        for wave, G0 in (("nominal", torch.as_tensor(ir.grad_mT_per_m)), ("7 T GIRF", G_real)):
            for dname, dt in (("float32", torch.float32), ("float64", torch.float64)):
                res = {False: {"fwd": np.inf, "fb": np.inf}, True: {"fwd": np.inf, "fb": np.inf}}
                sig = {}
                S.LINE_MACS = []
                with torch.no_grad():  # the line path's operation count of one forward
                    simulate(ir, ph, graph=g, grad_mT_per_m=G0, config=PDGConfig(signal_method="separable"), dtype=dt)
                macs = sum(S.LINE_MACS)
                S.LINE_MACS = None
                for _ in range(repeats):
                    for la in (False, True):
                        cfg = PDGConfig(signal_method="separable", line_aware=la)
                        t = time.perf_counter()
                        with torch.no_grad():
                            s = simulate(ir, ph, graph=g, grad_mT_per_m=G0, config=cfg, dtype=dt)
                        res[la]["fwd"] = min(res[la]["fwd"], time.perf_counter() - t)
                        sig[la] = s
                        G = G0.clone().requires_grad_(True)
                        t = time.perf_counter()
                        s2 = simulate(ir, ph, graph=g, grad_mT_per_m=G, config=cfg, dtype=dt)
                        (s2.abs() ** 2).sum().backward()
                        res[la]["fb"] = min(res[la]["fb"], time.perf_counter() - t)
                diff = float((sig[True] - sig[False]).abs().max() / sig[False].abs().max())
                rows.append(
                    dict(
                        case=f"EPI {case['epi']}x{case['epi']}, {case['n']}x{case['n']} phantom",
                        wave=wave,
                        dtype=dname,
                        old=res[False],
                        new=res[True],
                        diff=diff,
                        n_adc=int(ir.n_adc_samples),
                        voxels=int((ph.pd > 0).sum()),
                        macs=macs,
                    )
                )
                print(rows[-1], flush=True)
    return rows


def _ms(x: float) -> str:
    return f"{1e3 * x:.0f} ms" if x < 10 else f"{x:.1f} s"


def render(rows: list[dict], peak: float) -> str:
    lines = [
        "| case | gradient | dtype | per-sample windows fwd / fwd+bwd | line-aware fwd / fwd+bwd | speed-up fwd / "
        "fwd+bwd | max difference (rel.) | line path GFLOP/s fwd (share of GEMM peak) | GEMM floor fwd |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        o, n = r["old"], r["new"]
        lines.append(
            f"| {r['case']} | {r['wave']} | {r['dtype']} | {_ms(o['fwd'])} / {_ms(o['fb'])} | {_ms(n['fwd'])} / "
            f"{_ms(n['fb'])} | **{o['fwd'] / n['fwd']:.1f}x** / **{o['fb'] / n['fb']:.1f}x** | {r['diff']:.1e} | "
            + (
                f"{8e-9 * r['macs'] / n['fwd']:.1f} ({100 * 8e-9 * r['macs'] / n['fwd'] / peak[r['dtype']]:.0f} %) | "
                f"{_ms(8e-9 * r['macs'] / peak[r['dtype']])} |"
                if r["macs"]
                else "- (per-sample path) | - |"
            )
        )
    return (
        "\n".join(lines)
        + f"\n\nWhole `simulate` calls (graph prebuilt; the 3 emitting states of a single-shot EPI). This machine's "
        f"complex GEMM, 1 thread: {peak['float32']:.1f} GFLOP/s (complex64), {peak['float64']:.1f} GFLOP/s "
        "(complex128). GFLOP/s: 8 x the line path's complex multiply-adds (its two products, counted by "
        "`dtoc.sim.pdg_signal.LINE_MACS`) over the whole forward time; 'GEMM floor': those operations at the GEMM "
        "peak -- the distance of the whole call (PDG propagation, factors, gathers included) to the limit of this "
        "algorithm. The per-sample path contracts the readout axis for every "
        "sample (T x V x terms complex multiply-adds as matrix products); the line path contracts the phase-encoded "
        "axis once per line and the readout axis per sample (n_lines x V x terms + T x n_ro x terms), the realized "
        "phase drift along a line by a Jacobi-Anger series whose length sets the gain (docs/simulator.md, "
        "'Signal evaluation'); where it would be too long (4 S > min(n_pe, samples per line)) the per-sample "
        "path runs. fwd+bwd: S + 2 terms, so the nominal lines' gain is smaller with a gradient than without.\n"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--no-write", action="store_true")
    a = ap.parse_args()
    torch.set_num_threads(1)
    peak = {"float32": gemm_peak_gflops(torch.complex64), "float64": gemm_peak_gflops(torch.complex128)}
    rows = run(a.repeats)
    text = render(rows, peak)
    print(text)
    if not a.no_write:
        from bench._report import write_section

        write_section("line_aware", "Line-aware EPI signal (issue 21)", text, "python -m bench.sim.line_aware")


if __name__ == "__main__":
    main()
