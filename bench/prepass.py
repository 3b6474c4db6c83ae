"""PDG pre-pass benchmark: the graph build (:func:`dtoc.sim.pdg.build_graph`) per case, ms, median of N.

    python -m bench.prepass [--repeats 7] [--cases a,b] [--json]

Cases: the bench.sim cases (their sequence and phantom, ``PDGConfig()`` and ``PDGConfig.fast()``), and the three
graphs one ``dtoc optimize`` of the Fig-5 GRE builds (sequences/gre_paper_fig5.yaml with the optimizer's phantom:
the main preset, the 300-cycle dummy train at the steady-state thresholds, the loop's fast preset).  Per case:
the first call of the process (cold), then the median and the minimum of ``--repeats`` further calls, wall and
CPU time (one process, one thread; under load the CPU time is the steadier figure), and the graph's states.

To compare two trees at the same load, run this same file with each tree's ``dtoc`` first on the path (the file
imports only public names that every tree has), e.g. ``PYTHONPATH=/path/to/other/tree python bench/prepass.py``
and ``python -m bench.prepass`` here, one after the other; it prints which ``dtoc`` it timed and the load.  The
graphs are the same bit for bit (tests/test_prepass_golden.py, tests/test_prepass_equivalence.py).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _cases() -> dict:
    """name -> callable building the graph once (returns the graph)."""
    from bench.sim.run import CASES
    from dtoc.constants import default_dummies
    from dtoc.seq.load import load_sequence
    from dtoc.seq.spec import load_spec, parse_spec
    from dtoc.sim import pdg
    from dtoc.sim.pdg_dummies import detect_rf_spoiling, dummy_train
    from dtoc.sim.pdg_graph import build_graph
    from dtoc.sim.phantom import brain_phantom

    out: dict = {}
    for case, (spec, n, fov) in ((c, v[:3]) for c, v in CASES.items()):
        sp = load_spec(REPO / "sequences" / spec) if isinstance(spec, str) else parse_spec(dict(spec))
        ir = load_sequence(sp)
        ph = brain_phantom(n, field_T=3.0, fov_m=fov)
        for cname, cfg in (("default", pdg.PDGConfig()), ("fast", pdg.PDGConfig.fast())):
            out[f"sim:{case}/{cname}"] = lambda ir=ir, cfg=cfg, ph=ph: pdg.build_graph(ir, cfg, ph)
    from dtoc.optimize.config import OptimizeConfig
    from dtoc.optimize.run import make_phantoms

    ir = load_sequence(REPO / "sequences" / "gre_paper_fig5.yaml")
    ph = make_phantoms(ir, OptimizeConfig())[0]
    train = dummy_train(ir, default_dummies("gre"), None, detect_rf_spoiling(ir))
    steady = pdg.PDGConfig(min_latent_signal=1e-6, min_emitted_signal=1e-6, min_magnitude=1e-7)
    out["fig5:main"] = lambda: pdg.build_graph(ir, pdg.PDGConfig(), ph)
    out["fig5:dummies300"] = lambda: build_graph(train, steady, ph, final_z_readout=True)
    out["fig5:fast"] = lambda: pdg.build_graph(ir, pdg.PDGConfig.fast(), ph)
    return out


def _commit(path: Path) -> str:
    try:
        r = subprocess.run(["git", "-C", str(path), "rev-parse", "--short", "HEAD"], capture_output=True, text=True)
        dirty = subprocess.run(["git", "-C", str(path), "status", "--porcelain", "--", "dtoc"], capture_output=True)
        return r.stdout.strip() + ("+dirty" if dirty.stdout.strip() else "")
    except OSError:
        return "?"


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--cases", default="", help="comma-separated case names or prefixes (default: all)")
    ap.add_argument("--json", action="store_true", help="one JSON line per case instead of the table")
    a = ap.parse_args(argv)
    import torch

    torch.set_num_threads(1)
    import dtoc

    tree = Path(dtoc.__file__).resolve().parents[1]
    cases = _cases()
    want = [c for c in a.cases.split(",") if c]
    names = [n for n in cases if not want or any(n.startswith(w) for w in want)]
    load = os.getloadavg()
    print(
        f"# dtoc from {tree} ({_commit(tree)}), {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, "
        f"load {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}, {os.cpu_count()} CPUs, repeats {a.repeats}",
        flush=True,
    )
    if not a.json:
        print("| case | states | first call ms | wall median ms | wall min ms | CPU median ms |")
        print("|---|---|---|---|---|---|")
    for name in names:
        fn = cases[name]
        t0 = time.perf_counter()
        g = fn()
        first = time.perf_counter() - t0
        wall, cpu = [], []
        for _ in range(a.repeats):
            t0, c0 = time.perf_counter(), time.process_time()
            fn()
            wall.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
        row = {
            "case": name,
            "states": g.n_states_total,
            "first_ms": 1e3 * first,
            "wall_median_ms": 1e3 * statistics.median(wall),
            "wall_min_ms": 1e3 * min(wall),
            "cpu_median_ms": 1e3 * statistics.median(cpu),
        }
        if a.json:
            print(json.dumps(row), flush=True)
        else:
            print(
                f"| {name} | {row['states']} | {row['first_ms']:.1f} | {row['wall_median_ms']:.1f} | "
                f"{row['wall_min_ms']:.1f} | {row['cpu_median_ms']:.1f} |",
                flush=True,
            )
    load = os.getloadavg()
    print(f"# load at the end {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}")


if __name__ == "__main__":
    sys.path.append(str(REPO))  # after PYTHONPATH: the tree named there is the one timed
    main()
