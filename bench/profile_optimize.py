"""Where `dtoc optimize` spends its time: import, pre-pass, steady state, forward simulation, hardware twin,
backward, projection, export and checks -- exclusive times per stage, one process per scenario.

    python -m bench.profile_optimize [--only NAME ...] [--no-write]   -> docs/benchmarks.md "dtoc optimize profile"

Stages: import (torch, dtoc), reading the base .seq (with pypulseq's import), pre-pass, steady state, forward
simulation, hardware twin, backward (every autograd gradient: Tensor.backward and torch.autograd.grad),
projection onto the limits, export and checks. Scenarios: the README's EPI job (sequences/epi_esp081.seq, bundled example 7 T GIRF, --b0 7) with the line-aware
signal on and off (`PDGConfig.line_aware`: the before/after of issue 21 item 3), and the paper's GRE
(sequences/gre_paper.seq, same GIRF, default settings: 300 dummy cycles, 300 warm-start iterations).
Each child times its imports, then runs the `dtoc optimize` command in-process with timing wrappers on the stage functions: a
stage's time excludes the stages called inside it (the backward of every autograd graph -- simulation, twin
and loss -- is one stage). 'other' is the rest of the run (loss terms, optimizer bookkeeping, manifest).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

SCENARIOS = {
    "epi_line_aware": ("sequences/epi_esp081.seq", True),
    "epi_per_sample": ("sequences/epi_esp081.seq", False),
    "gre_paper": ("sequences/gre_paper.seq", True),
}

STAGES = (
    "import",
    "read .seq (incl. pypulseq import)",
    "pre-pass (PDG graph)",
    "steady state (dummies)",
    "forward simulation",
    "hardware twin",
    "backward (autograd)",
    "projection (limits)",
    "export + checks",
    "other",
)

_CHILD = r"""
import json, sys, time
t0 = time.perf_counter()
import torch
import dtoc.optimize.run as run
import dtoc.sim.imager as imager
import dtoc.sim.pdg as pdg
from dtoc.optimize.limits import EdgeProjector
from dtoc.optimize.twin import EdgeTwin
t_import = time.perf_counter() - t0
acc, stack = {}, []

def wrap(label, fn):
    def w(*a, **k):
        now = time.perf_counter()
        if stack:
            acc[stack[-1][0]] = acc.get(stack[-1][0], 0.0) + now - stack[-1][1]
        stack.append([label, now])
        try:
            return fn(*a, **k)
        finally:
            now = time.perf_counter()
            lab, ts = stack.pop()
            acc[lab] = acc.get(lab, 0.0) + now - ts
            if stack:
                stack[-1][1] = now
    return w

for mod in (imager, pdg):
    if hasattr(mod, "build_graph"):
        mod.build_graph = wrap("pre-pass (PDG graph)", mod.build_graph)
imager.steady_state_mz = wrap("steady state (dummies)", imager.steady_state_mz)
imager.simulate = wrap("forward simulation", imager.simulate)
EdgeTwin.forward_edges = wrap("hardware twin", EdgeTwin.forward_edges)
EdgeTwin.export_fine = wrap("hardware twin", EdgeTwin.export_fine)
EdgeProjector.project = wrap("projection (limits)", EdgeProjector.project)
torch.Tensor.backward = wrap("backward (autograd)", torch.Tensor.backward)
torch.autograd.grad = wrap("backward (autograd)", torch.autograd.grad)
import dtoc.seq.load as seqload
seqload.read_seq = wrap("read .seq (incl. pypulseq import)", seqload.read_seq)
run._write_outputs = wrap("export + checks", run._write_outputs)
run.write_checked = wrap("export + checks", run.write_checked)
if not json.loads(sys.argv[3]):
    from dtoc.sim import pdg_config
    orig_init = pdg_config.PDGConfig.__init__
    def init(self, *a, **k):
        orig_init(self, *a, **k)
        self.line_aware = False
    pdg_config.PDGConfig.__init__ = init
from dtoc.cli.main import run as cli
t1 = time.perf_counter()
try:
    cli(["optimize", sys.argv[1], "--girf", "girf/example_7T.npz", "--b0", "7", "-o", sys.argv[2],
         "--json", sys.argv[2] + ".json", "--force", "-q"])
except SystemExit as e:
    if e.code:
        raise
total = time.perf_counter() - t1
acc["import"] = t_import
acc["other"] = total - sum(v for k, v in acc.items() if k != "import")
m = json.loads(open(sys.argv[2] + ".json").read())
print("RESULT", json.dumps({"stages": acc, "total": total + t_import,
      "nrmse": [m["before"]["nrmse_percent"], m["after"]["nrmse_percent"]]}))
"""


def run_one(name: str) -> dict:
    import tempfile

    seq, line_aware = SCENARIOS[name]
    with tempfile.TemporaryDirectory() as td:
        p = subprocess.run(
            [sys.executable, "-c", _CHILD, seq, str(Path(td) / "o.seq"), json.dumps(line_aware)],
            capture_output=True,
            text=True,
            cwd=REPO,
        )
    for ln in p.stdout.splitlines():
        if ln.startswith("RESULT "):
            return json.loads(ln[7:])
    raise SystemExit(f"{name}: no result\n{p.stdout[-2000:]}\n{p.stderr[-2000:]}")


def render(rows: dict) -> str:
    names = list(rows)
    head = "| stage | " + " | ".join(names) + " |"
    lines = [head, "|---|" + "---|" * len(names)]
    for st in STAGES:
        cells = []
        for n in names:
            v = rows[n]["stages"].get(st, 0.0)
            cells.append(f"{v:.2f} s ({100 * v / rows[n]['total']:.0f} %)")
        lines.append(f"| {st} | " + " | ".join(cells) + " |")
    lines.append("| **total** | " + " | ".join(f"**{rows[n]['total']:.2f} s**" for n in names) + " |")
    lines.append(
        "| NRMSE before -> after | "
        + " | ".join(f"{a:.3g} % -> {b:.3g} %" for a, b in (rows[n]["nrmse"] for n in names))
        + " |"
    )
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", nargs="*", default=None)
    ap.add_argument("--no-write", action="store_true")
    a = ap.parse_args()
    rows = {}
    for name in SCENARIOS:
        if a.only and name not in a.only:
            continue
        rows[name] = run_one(name)
        print(name, json.dumps(rows[name]), flush=True)
    text = render(rows)
    text += (
        "\nWall seconds of one process per scenario (the CLI command in-process; imports of torch and dtoc "
        "in 'import'); exclusive times: a stage called inside another counts only for itself. 'epi_per_sample' is "
        "the same EPI job with `PDGConfig.line_aware = False` (before issue 21 item 3), 'epi_line_aware' after.\n"
    )
    print(text)
    if not a.no_write:
        from bench._report import write_section

        write_section("optimize_profile", "dtoc optimize profile (issue 21)", text, "python -m bench.profile_optimize")


if __name__ == "__main__":
    main()
