"""Internal timing of dtoc's PDG simulator (forward, forward+backward, peak memory, graph size).

    python -m bench.sim.bench_pdg_internal            # all cases, writes docs/benchmarks.md "PDG internal"
    python -m bench.sim.bench_pdg_internal --case gre32_10us   # one case, prints JSON

Each case runs in its own process (peak RSS is per process), with torch threads = 2 (the CI
machine).  The formal side-by-side comparison with MRzeroCore is bench/sim (sim-support's).
Cases: the paper's GRE (32 reps, 32x32) on its 0.1 ms grid and on a 10 us raster, the GRE on a 64x64
phantom, the 64x64 single-shot EPI (10 us), the EPI on phantoms 32..256, and a 128x128 EPI on a
256x256 phantom.  Phantom: built-in brain at 3 T with B0 and B1 maps (the EPI: B0 map zero, as the
paper).  Loss for backward: sum |s|^2 w.r.t. the (3, 2N+1) gradient.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]

CASES = {
    "gre32_100us": dict(seq="gre_paper_r100us.seq", n=32, b0=True),
    "gre32_10us": dict(seq="gre_paper.seq", n=32, b0=True),
    "gre_phantom64": dict(seq="gre_paper.seq", n=64, b0=True),
    "epi64_10us": dict(seq="epi_esp081.seq", n=64, b0=False),
    "epi64_phantom32": dict(seq="epi_esp081.seq", n=32, b0=False),
    "epi64_phantom128": dict(seq="epi_esp081.seq", n=128, b0=False),
    "epi64_phantom256": dict(seq="epi_esp081.seq", n=256, b0=False),
    "epi128_phantom256": dict(seq=None, epi_matrix=128, n=256, b0=False),
    "gre32_10us_f32": dict(seq="gre_paper.seq", n=32, b0=True, dtype="float32"),
    "epi64_10us_f32": dict(seq="epi_esp081.seq", n=64, b0=False, dtype="float32"),
}


def _load(case):
    from dtoc.seq.read import load_sequence

    if case.get("seq"):
        return load_sequence(str(REPO / "sequences" / case["seq"]))
    import yaml

    from dtoc.seq.build import build_ir
    from dtoc.seq.spec import parse_spec

    data = yaml.safe_load((REPO / "sequences" / "epi_esp081.yaml").read_text())
    data["matrix"] = case["epi_matrix"]
    data["echo_spacing_ms"] = 1.6  # room for a 1.28 ms readout (128 x 10 us) and its reversal
    data["name"] = f"epi{case['epi_matrix']}"
    return build_ir(parse_spec(data))


def run_case(name: str, repeats: int = 2) -> dict:
    import torch

    from dtoc.sim.pdg import PDGConfig, build_graph, simulate
    from dtoc.sim.phantom import brain_phantom

    torch.set_num_threads(2)
    case = CASES[name]
    ir = _load(case)
    ph = brain_phantom(case["n"], fov_m=ir.fov_m[0], b0=case["b0"], b1=True)
    cfg = PDGConfig()
    dtype = getattr(torch, case.get("dtype", "float64"))
    t = time.perf_counter()
    graph = build_graph(ir, cfg, ph)
    t_graph = time.perf_counter() - t
    fwd, fb = [], []
    for _ in range(repeats):
        t = time.perf_counter()
        with torch.no_grad():
            simulate(ir, ph, graph=graph, config=cfg, dtype=dtype)
        fwd.append(time.perf_counter() - t)
        g = torch.as_tensor(ir.grad_mT_per_m).requires_grad_(True)
        t = time.perf_counter()
        s = simulate(ir, ph, g, graph=graph, config=cfg, dtype=dtype)
        (s.abs() ** 2).sum().backward()
        fb.append(time.perf_counter() - t)
    return {
        "case": name, "dtype": case.get("dtype", "float64"), "n_fine": ir.n_fine, "n_adc": ir.n_adc_samples, "phantom": case["n"], **graph.summary(),
        "graph_s": t_graph, "fwd_s": min(fwd), "fwd_bwd_s": min(fb),
        "peak_rss_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6,
    }


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--case", choices=sorted(CASES))
    ap.add_argument("--cases", nargs="*", default=list(CASES))
    ap.add_argument("--no-write", action="store_true")
    a = ap.parse_args(argv)
    if a.case:
        print(json.dumps(run_case(a.case)))
        return
    rows = []
    for c in a.cases:
        p = subprocess.run([sys.executable, "-m", "bench.sim.bench_pdg_internal", "--case", c], cwd=REPO, capture_output=True, text=True)
        if p.returncode != 0:
            rows.append({"case": c, "error": (p.stderr.strip().splitlines() or ["?"])[-1]})
        else:
            rows.append(json.loads(p.stdout.strip().splitlines()[-1]))
        print(json.dumps(rows[-1]), flush=True)
        if not a.no_write:  # after every case, so that a long run leaves its finished rows
            _write(rows)


def _write(rows):
    body = [
        "dtoc PDG simulator alone (default `PDGConfig`, float64 unless the case ends in _f32, CPU, 2 torch threads, best of 2).  Loss for backward: "
        "sum |s|^2 w.r.t. the fine-grid gradient.  Peak memory = peak RSS of the case's process.  "
        "Brain phantom 3 T with B1 map (GRE also B0).  NOTE: the machine was shared with other jobs (load ~8 on "
        "2 cores, several other benchmarks running; the same operation varied 10x between runs) when these "
        "were measured: treat the times as upper bounds, not as the machine's speed.",
        "",
        "| case | phantom | ADC samples | states (max/interval) | emitting | graph s | forward s | forward+backward s | peak RSS GB |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        if "error" in r:
            body.append(f"| {r['case']} | - | - | - | - | - | - | failed: {r['error'][:80]} | - |")
            continue
        body.append(
            f"| {r['case']} | {r['phantom']}x{r['phantom']} | {r['n_adc']} | {r['states_total']} ({r['states_max']}) | "
            f"{r['emitting_total']} | {r['graph_s']:.2f} | {r['fwd_s']:.3f} | {r['fwd_bwd_s']:.3f} | {r['peak_rss_gb']:.2f} |"
        )
    sys.path.insert(0, str(REPO))
    from bench._report import write_section

    write_section("pdg_internal", "PDG internal (dtoc.sim.pdg)", "\n".join(body), "python -m bench.sim.bench_pdg_internal")


if __name__ == "__main__":
    main()
