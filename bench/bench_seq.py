"""Sequence I/O benchmark: time of build / read / write / check, and the round-trip precision.

Run: ``python -m bench.bench_seq`` (writes its section of docs/benchmarks.md).
"""

from __future__ import annotations

import os
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def _t(fn, n=3):
    ts = []
    out = None
    for _ in range(n):
        t0 = time.perf_counter()
        out = fn()
        ts.append(time.perf_counter() - t0)
    return min(ts), float(np.median(ts)), out


def main() -> None:
    from bench._report import write_section
    from dtoc.seq.build import SpecLimitWarning, build, seq_bytes
    from dtoc.seq.check import check_file
    from dtoc.seq.ir import edges_to_fine
    from dtoc.seq.read import quiet, read_seq
    from dtoc.seq.spec import load_spec
    from dtoc.seq.write import write_seq

    warnings.simplefilter("ignore", SpecLimitWarning)
    rows = []
    prec = []
    load = os.getloadavg()[0]
    for name in ("epi_esp081", "gre_paper"):
        spec = load_spec(REPO / "sequences" / f"{name}.yaml")
        path = REPO / "sequences" / f"{name}.seq"
        tb = _t(lambda spec=spec: seq_bytes(build(spec)))
        tr = _t(lambda path=path: read_seq(path))
        ir = tr[2]
        rng = np.random.default_rng(0)
        n = ir.edge_grad_mT_per_m.shape[1]
        tt = np.arange(n) / n
        p = sum(rng.normal() * np.sin(2 * np.pi * rng.uniform(1, 200) * tt + rng.uniform(0, 6.3)) for _ in range(6))
        pert = np.stack([p, np.roll(p, 17), np.roll(p, 31)]) * (2.0 / np.abs(p).max()) * ir.free_mask[:, ::2]
        new = ir.with_grad(edges_to_fine(ir.edge_grad_mT_per_m + pert))
        with tempfile.TemporaryDirectory() as d:
            out = Path(d) / "o.seq"
            tw = _t(lambda new=new, out=out: write_seq(new, out, force=True))
            tc = _t(lambda out=out: check_file(out))
            back = read_seq(out)
        err = np.abs(back.grad_mT_per_m - new.grad_mT_per_m).max()
        kerr = (
            np.abs(back.kspace_rad_per_m().numpy() - new.kspace_rad_per_m().numpy())[:2] / new.dk_rad_per_m[:2, None]
        ).max()
        with quiet():
            k_pp = ir.source.calculate_kspace()[0]
        kpp = (np.abs(k_pp - ir.nominal_kspace_rad_per_m() / (2 * np.pi))[:2] * np.array(ir.fov_m[:2])[:, None]).max()
        for what, t in (
            ("build (spec -> bytes)", tb),
            ("read_seq", tr),
            ("write_seq (all free blocks changed)", tw),
            ("check_file", tc),
        ):
            rows.append(f"| {name} | {what} | {t[0] * 1e3:.0f} | {t[1] * 1e3:.0f} |")
        prec.append(f"| {name} | {len(ir.block_edges_s) - 1} | {err:.2e} | {kerr:.2e} | {kpp:.2e} |")
    body = (
        f"Min and median of 3 runs (load average at start {load:.1f}: the CPU was shared).\n\n"
        "| sequence | step | min (ms) | median (ms) |\n|---|---|---|---|\n" + "\n".join(rows) + "\n\n"
        "Round trip with a random smooth perturbation (6 sinusoids, peak 2 mT/m) of every free sample, "
        "written and read back; unmodified k-space vs pypulseq `calculate_kspace`:\n\n"
        "| sequence | blocks | max waveform error (mT/m) | max k error (dk) | unmodified k vs pypulseq (dk) |\n"
        "|---|---|---|---|---|\n" + "\n".join(prec) + "\n"
    )
    print(body)
    write_section("seq", "Sequence I/O (dtoc build / read / write / check)", body, "python -m bench.bench_seq")


if __name__ == "__main__":
    main()
