"""Internal timing of dtoc's PDG simulator (forward, forward+backward, peak memory, graph size).

    python -m bench.sim.bench_pdg_internal            # all cases, writes docs/benchmarks.md "PDG internal"
    python -m bench.sim.bench_pdg_internal --case gre32_10us   # one case, prints JSON
    python -m bench.sim.bench_pdg_internal --cases gre32_100us gre32_10us gre_phantom64 epi64_10us \
        --presets default fast --dtypes float64 float32 --threads 1 [--baseline before.jsonl]

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
    from dtoc.seq.load import load_sequence

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


def run_case(
    name: str, repeats: int = 2, preset: str = "default", threads: int = 2, dtype_name: str | None = None
) -> dict:
    """Time one case: graph build, forward (no grad), forward+backward; wall and process CPU seconds (best of ``repeats``)."""
    import torch

    from dtoc.sim.pdg import PDGConfig, build_graph, simulate
    from dtoc.sim.phantom import brain_phantom

    torch.set_num_threads(threads)
    case = CASES[name]
    ir = _load(case)
    ph = brain_phantom(case["n"], fov_m=ir.fov_m[0], b0=case["b0"], b1=True)
    cfg = PDGConfig() if preset == "default" else getattr(PDGConfig, preset)()
    dname = dtype_name or case.get("dtype", "float64")
    dtype = getattr(torch, dname)
    t = time.perf_counter()
    graph = build_graph(ir, cfg, ph)
    t_graph = time.perf_counter() - t
    fwd, fb, fwd_cpu, fb_cpu = [], [], [], []
    for _ in range(repeats):
        t, c = time.perf_counter(), time.process_time()
        with torch.no_grad():
            simulate(ir, ph, graph=graph, config=cfg, dtype=dtype)
        fwd.append(time.perf_counter() - t)
        fwd_cpu.append(time.process_time() - c)
        g = torch.as_tensor(ir.grad_mT_per_m).requires_grad_(True)
        t, c = time.perf_counter(), time.process_time()
        s = simulate(ir, ph, g, graph=graph, config=cfg, dtype=dtype)
        (s.abs() ** 2).sum().backward()
        fb.append(time.perf_counter() - t)
        fb_cpu.append(time.process_time() - c)
    return {
        "case": name,
        "preset": preset,
        "dtype": dname,
        "threads": threads,
        "n_fine": ir.n_fine,
        "n_adc": ir.n_adc_samples,
        "phantom": case["n"],
        **graph.summary(),
        "graph_s": t_graph,
        "fwd_s": min(fwd),
        "fwd_bwd_s": min(fb),
        "fwd_cpu_s": min(fwd_cpu),
        "fwd_bwd_cpu_s": min(fb_cpu),
        "peak_rss_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6,
    }


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--case", choices=sorted(CASES))
    ap.add_argument("--cases", nargs="*", default=list(CASES))
    ap.add_argument("--presets", nargs="*", default=["default"], help="PDGConfig presets: default, fast, strict")
    ap.add_argument("--dtypes", nargs="*", default=[None], help="override the case dtype (float32/float64)")
    ap.add_argument(
        "--threads",
        type=int,
        default=2,
        help="torch intra-op threads (1 on a loaded machine: OpenMP spin-waits inflate CPU time)",
    )
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--baseline", help="JSON-lines file of an earlier run (same cases) shown as 'before' columns")
    ap.add_argument("--no-write", action="store_true")
    a = ap.parse_args(argv)
    if a.case:
        print(json.dumps(run_case(a.case, a.repeats, a.presets[0], a.threads, a.dtypes[0])))
        return
    base = {}
    if a.baseline:
        for line in Path(a.baseline).read_text().splitlines():
            r = json.loads(line)
            if "error" not in r:
                base[(r["case"], r.get("preset", "default"), r.get("dtype"))] = r
    rows = []
    for c in a.cases:
        for preset in a.presets:
            for dt in a.dtypes:
                cmd = [
                    sys.executable,
                    "-m",
                    "bench.sim.bench_pdg_internal",
                    "--case",
                    c,
                    "--presets",
                    preset,
                    "--threads",
                    str(a.threads),
                    "--repeats",
                    str(a.repeats),
                ] + (["--dtypes", dt] if dt else [])
                p = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True)
                if p.returncode != 0:
                    rows.append({"case": c, "preset": preset, "error": (p.stderr.strip().splitlines() or ["?"])[-1]})
                else:
                    rows.append(json.loads(p.stdout.strip().splitlines()[-1]))
                print(json.dumps(rows[-1]), flush=True)
                if not a.no_write:  # after every case, so that a long run leaves its finished rows
                    _write(rows, base, a.threads)


def _write(rows, base=None, threads=2):
    import platform

    import torch

    base = base or {}
    body = [
        f"dtoc PDG simulator alone, CPU ({platform.processor() or platform.machine()}, {__import__('os').cpu_count()} cores, torch "
        f"{torch.__version__}, {threads} torch thread(s), best of the repeats; {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}).  "
        "Loss for backward: sum |s|^2 w.r.t. the fine-grid gradient.  Peak memory = peak RSS of the case's process.  "
        "Brain phantom 3 T with B1 map (GRE also B0).  Presets: `default` = `PDGConfig()` (thresholds 1e-5), `fast` = "
        "`PDGConfig.fast()` (1e-4).  CPU s = process CPU time (user+sys), the figure to compare on a shared machine; "
        "wall s depends on the load (another job kept one of the 2 cores busy).  'before' = the same case, preset and dtype with "
        "the simulator of the previous commit (issue-4 speed work not applied), measured on the same machine in the same session shortly "
        "before this table (`--baseline`; a checkout of the previous commit).",
        "",
        "| case | preset | dtype | phantom | ADC samples | states (max/interval) | emitting | forward CPU s | fwd+bwd CPU s | forward wall s | fwd+bwd wall s | before: fwd / fwd+bwd CPU s | peak RSS GB |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        if "error" in r:
            body.append(
                f"| {r['case']} | {r.get('preset', '-')} | - | - | - | - | - | - | failed: {r['error'][:80]} | - | - | - | - |"
            )
            continue
        b = base.get((r["case"], r.get("preset", "default"), r["dtype"]))
        bs = f"{b['fwd_cpu_s']:.3f} / {b['fwd_bwd_cpu_s']:.3f}" if b and "fwd_cpu_s" in b else "-"
        body.append(
            f"| {r['case']} | {r.get('preset', 'default')} | {r['dtype']} | {r['phantom']}x{r['phantom']} | {r['n_adc']} | {r['states_total']} ({r['states_max']}) | "
            f"{r['emitting_total']} | {r['fwd_cpu_s']:.3f} | {r['fwd_bwd_cpu_s']:.3f} | {r['fwd_s']:.3f} | {r['fwd_bwd_s']:.3f} | {bs} | {r['peak_rss_gb']:.2f} |"
        )
    sys.path.insert(0, str(REPO))
    from bench._report import write_section

    torch.set_num_threads(threads)  # the section header reports this process's thread count

    write_section(
        "pdg_internal", "PDG internal (dtoc.sim.pdg)", "\n".join(body), "python -m bench.sim.bench_pdg_internal"
    )


if __name__ == "__main__":
    main()
