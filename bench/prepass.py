"""PDG pre-pass benchmark: the graph build (:func:`dtoc.sim.pdg.build_graph`) per case, ms, median of N.

    python -m bench.prepass [--repeats 7] [--cases a,b] [--json] [--no-write]

Cases: the bench.sim cases (their sequence and phantom, ``PDGConfig()`` and ``PDGConfig.fast()``), and the three
graphs one ``dtoc optimize`` of the Fig-5 GRE builds (sequences/gre_paper_fig5.yaml with the optimizer's phantom:
the main preset, the 300-cycle dummy train at the steady-state thresholds, the loop's fast preset).  Per case and
pre-pass formulation -- the numpy one and, where it was built at install, the compiled core
(``dtoc/sim/_pdg_split.c``), alternated call by call in one process so both see the same load: the first call of
the process (cold, the formulation that runs by default), then the median and the minimum of ``--repeats`` further
calls, wall and CPU time (one process, one thread; under load the CPU time is the steadier figure), and the
graph's states (the two formulations build the same graph bit for bit: tests/test_prepass_native.py).  Without
``--no-write`` (and without ``--cases``) the table goes to docs/benchmarks.md (section "prepass").

To compare two trees at the same load, run this same file with each tree's ``dtoc`` first on the path (the file
imports only public names that every tree has; a tree without the compiled core times its numpy formulation
only), e.g. ``PYTHONPATH=/path/to/other/tree python bench/prepass.py --no-write`` and ``python -m bench.prepass
--no-write`` here, one after the other; it prints which ``dtoc`` it timed and the load.  The graphs are the same
bit for bit (tests/test_prepass_golden.py, tests/test_prepass_equivalence.py).
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


def _backends() -> list:
    """(label, context manager factory) of the formulations this tree has: numpy, then the compiled core."""
    import contextlib

    try:
        from dtoc.sim.pdg_graph_step import native_available, prepass_backend
    except ImportError:  # a tree before the compiled core: its only formulation
        return [("numpy", contextlib.nullcontext)]
    out = [("numpy", lambda: prepass_backend("numpy"))]
    if native_available():
        out.append(("compiled", lambda: prepass_backend("native")))
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--cases", default="", help="comma-separated case names or prefixes (default: all)")
    ap.add_argument("--json", action="store_true", help="one JSON line per case instead of the table")
    ap.add_argument("--no-write", action="store_true", help="print only; do not update docs/benchmarks.md")
    a = ap.parse_args(argv)
    import torch

    torch.set_num_threads(1)
    import dtoc

    tree = Path(dtoc.__file__).resolve().parents[1]
    cases = _cases()
    backends = _backends()
    want = [c for c in a.cases.split(",") if c]
    names = [n for n in cases if not want or any(n.startswith(w) for w in want)]
    load0 = os.getloadavg()
    head = (
        f"dtoc from {tree} ({_commit(tree)}), {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, "
        f"load {load0[0]:.2f} {load0[1]:.2f} {load0[2]:.2f}, {os.cpu_count()} CPUs, repeats {a.repeats}"
    )
    print("# " + head, flush=True)
    cols = " | ".join(f"{b} CPU median ms | {b} wall median ms | {b} wall min ms" for b, _ in backends)
    lines = [
        f"| case | states | first call ms | {cols} |" + (" CPU speed-up |" if len(backends) > 1 else ""),
        "|---|---|---|" + "---|---|---|" * len(backends) + ("---|" if len(backends) > 1 else ""),
    ]
    if not a.json:
        print("\n".join(lines), flush=True)
    for name in names:
        fn = cases[name]
        t0 = time.perf_counter()
        g = fn()  # the formulation that runs by default
        first = time.perf_counter() - t0
        wall: dict = {b: [] for b, _ in backends}
        cpu: dict = {b: [] for b, _ in backends}
        for _ in range(a.repeats):
            for b, ctx in backends:
                with ctx():
                    t0, c0 = time.perf_counter(), time.process_time()
                    fn()
                    wall[b].append(time.perf_counter() - t0)
                    cpu[b].append(time.process_time() - c0)
        row: dict = {"case": name, "states": g.n_states_total, "first_ms": 1e3 * first}
        for b, _ in backends:
            row[b] = {
                "cpu_median_ms": 1e3 * statistics.median(cpu[b]),
                "wall_median_ms": 1e3 * statistics.median(wall[b]),
                "wall_min_ms": 1e3 * min(wall[b]),
            }
        cells = " | ".join(
            f"{row[b]['cpu_median_ms']:.1f} | {row[b]['wall_median_ms']:.1f} | {row[b]['wall_min_ms']:.1f}"
            for b, _ in backends
        )
        line = f"| {name} | {row['states']} | {row['first_ms']:.1f} | {cells} |"
        if len(backends) > 1:
            line += f" {row['numpy']['cpu_median_ms'] / row['compiled']['cpu_median_ms']:.1f}x |"
        lines.append(line)
        print(json.dumps(row) if a.json else line, flush=True)
    load1 = os.getloadavg()
    print(f"# load at the end {load1[0]:.2f} {load1[1]:.2f} {load1[2]:.2f}")
    if not a.no_write and not want:
        from bench._report import write_section

        stamp = (
            f"dtoc {_commit(tree)}, {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, load {load0[0]:.2f} "
            f"{load0[1]:.2f} {load0[2]:.2f}, repeats {a.repeats}"
        )
        body = (
            f"{stamp}; load at the end {load1[0]:.2f} {load1[1]:.2f} {load1[2]:.2f}.  CPU time of this process (the "
            "steadier figure on a shared machine), the formulations alternated call by call; first call = the "
            "case's first build in the process, with the formulation that runs by default (compiled where built).  "
            "The graphs are the same bit for bit (tests/test_prepass_native.py, tests/test_prepass_golden.py, "
            "tests/test_prepass_equivalence.py).\n\n" + "\n".join(lines)
        )
        print(f"wrote {write_section('prepass', 'PDG pre-pass (graph build)', body, 'python -m bench.prepass')}")


if __name__ == "__main__":
    sys.path.append(str(REPO))  # after PYTHONPATH: the tree named there is the one timed
    main()
