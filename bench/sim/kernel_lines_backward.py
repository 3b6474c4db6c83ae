"""The line-aware readout products' hand-written backward against torch's autograd of the same products, in one
process, interleaved.

    python -m bench.sim.kernel_lines_backward [--repeats 3] [--threads 1] [--dtype float32]

Case: the 128x128 single-shot EPI (sequences/epi_esp081.yaml at matrix 128, echo spacing 1.6 ms, the case
``epi128_10us_p256`` of bench.sim.run) on a 256x256 brain phantom, with the gradient realized by the bundled
example 7 T GIRF (its blip tails make the phase moment drift along every line: a 16-term drift series), graph
built once.  Timed: one ``simulate`` forward + ``backward`` of sum |s|^2 w.r.t. the (3, 2N+1) gradient, wall and
CPU seconds, with :func:`dtoc.sim.pdg_signal._line_products` as shipped (custom node) and with the batch products
left to torch's autograd ('autograd': :func:`_line_batch_products` per batch on slices of the readout tensors, as
before the node), alternating autograd, custom, autograd, ...  Both runs share the contiguous weights H.  Printed:
per repeat the seconds, the minimum, the gain, and the gradients' largest difference relative to the largest
entry.  Nothing is written.
"""

from __future__ import annotations

import argparse
import os
import time

import torch


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    import dtoc
    import dtoc.sim.pdg_signal as S
    from bench.sim.line_aware import REPO, _ir
    from dtoc.sim.pdg import PDGConfig, build_graph, simulate
    from dtoc.sim.phantom import brain_phantom

    dt = {"float32": torch.float32, "float64": torch.float64}[a.dtype]
    ir = _ir({"epi": 128})
    ph = brain_phantom(256, fov_m=ir.fov_m[:2])
    graph = build_graph(ir, PDGConfig(), ph)
    G0 = dtoc.Twin(ir, dtoc.load_model(girf=str(REPO / "girf" / "example_7T.npz"))).forward().realized_grad_mT_per_m
    G0 = G0.detach().to(dt)
    custom = S._line_products

    def plain(H, X, dq, dlp, batches, mrs):
        return torch.cat(
            [S._line_batch_products(F, H, X[b0:b1], dlp[b0:b1], dq[b0:b1], mrs)[0] for b0, b1, F in batches], 0
        )

    def fwd_bwd(kind: str) -> tuple[float, float, torch.Tensor]:
        S._line_products = custom if kind == "custom" else plain
        try:
            G = G0.clone().requires_grad_(True)
            t, c = time.perf_counter(), time.process_time()
            s = simulate(ir, ph, G, graph=graph, config=PDGConfig(), dtype=dt)
            (s.real**2 + s.imag**2).sum().backward()
            return time.perf_counter() - t, time.process_time() - c, G.grad
        finally:
            S._line_products = custom

    kinds = ("autograd", "custom")
    for k in kinds:  # warm-up (first simulate of the process)
        fwd_bwd(k)
    res: dict = {k: [] for k in kinds}
    grads = {}
    for _ in range(a.repeats):
        for k in kinds:
            wall, cpu, grads[k] = fwd_bwd(k)
            res[k].append((wall, cpu))
    print(f"EPI 128, 256 phantom, {a.dtype}, {a.threads} thread(s), load {os.getloadavg()[0]:.2f}")
    for k in kinds:
        print(f"  {k:8s} wall {[round(w, 3) for w, _ in res[k]]} cpu {[round(c, 3) for _, c in res[k]]}")
    best = {k: min(c for _, c in res[k]) for k in kinds}
    print(
        f"  min CPU s: autograd {best['autograd']:.3f}, custom {best['custom']:.3f}, "
        f"gain {100 * (1 - best['custom'] / best['autograd']):.1f} %"
    )
    ref = grads["autograd"]
    print(
        f"  gradient difference: {float((grads['custom'] - ref).abs().max() / ref.abs().max()):.2e} of the largest entry"
    )


if __name__ == "__main__":
    main()
