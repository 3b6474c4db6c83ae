"""Peak memory of the 256x256 single-shot EPI: simulator forward + backward and a whole `dtoc optimize`.

    python -m bench.sim.epi256_memory [--no-optimize] [--no-write]   -> docs/benchmarks.md "256x256 EPI memory"

The spec: sequences/epi_esp081.yaml at matrix 256 and 3.0 ms echo spacing (65536 ADC samples), the built-in
brain at 256 x 256. Each measurement is its own process; peak RSS from the kernel's accounting of that child
(wait4). Simulator: float32, `PDGConfig.fast()`, loss sum |s|^2 w.r.t. the gradient, 1 thread, with the
nominal gradient and with the one realized by the bundled example 7 T GIRF, line-aware path on; the per-sample
path is run under a 20 GB address-space cap (`ulimit -v`). Optimize: the README's command on this spec
(`--girf girf/example_7T.npz --b0 7`), default settings.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]

_CHILD = r"""
import sys, time, torch, yaml
from pathlib import Path
from dtoc.seq.build import build_ir
from dtoc.seq.spec import parse_spec
from dtoc.sim.pdg import PDGConfig, build_graph, simulate
from dtoc.sim.phantom import brain_phantom
import dtoc
torch.set_num_threads(1)
ir = build_ir(parse_spec(yaml.safe_load(Path(sys.argv[1]).read_text())))
ph = brain_phantom(256, fov_m=ir.fov_m[:2])
g = build_graph(ir, PDGConfig.fast(), ph)
G0 = torch.as_tensor(ir.grad_mT_per_m)
if sys.argv[2] == "girf":
    G0 = dtoc.Twin(ir, dtoc.load_model(girf=sys.argv[4])).forward().realized_grad_mT_per_m.detach()
G = G0.clone().to(torch.float32).requires_grad_(True)
t = time.perf_counter()
s = simulate(ir, ph, graph=g, grad_mT_per_m=G, config=PDGConfig.fast(line_aware=sys.argv[3] == "1"), dtype=torch.float32)
(s.abs() ** 2).sum().backward()
print("SECONDS", time.perf_counter() - t)
"""


def _spec(d: Path) -> Path:
    import yaml

    data = yaml.safe_load((REPO / "sequences" / "epi_esp081.yaml").read_text())
    data.update(matrix=256, echo_spacing_ms=3.0, name="epi256")
    p = d / "epi256.yaml"
    p.write_text(yaml.safe_dump(data))
    return p


def _run(argv: list[str], cap_kb: int | None = None) -> dict:
    """Run a child: its wall time, its own peak RSS (GB, from wait4) and whether it finished."""
    import resource

    def cap() -> None:
        if cap_kb:
            resource.setrlimit(resource.RLIMIT_AS, (cap_kb * 1024, cap_kb * 1024))

    with tempfile.TemporaryFile("w+") as log:
        t = time.perf_counter()
        p = subprocess.Popen(argv, stdout=log, stderr=subprocess.STDOUT, text=True, preexec_fn=cap, cwd=REPO)
        _, status, ru = os.wait4(p.pid, 0)
        wall = time.perf_counter() - t
        log.seek(0)
        out = log.read()
    sec = [float(ln.split()[1]) for ln in out.splitlines() if ln.startswith("SECONDS")]
    return {
        "ok": os.waitstatus_to_exitcode(status) == 0,
        "wall_s": wall,
        "peak_gb": ru.ru_maxrss / 1e6,
        "fwd_bwd_s": sec[0] if sec else None,
        "tail": out[-300:],
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--no-optimize", action="store_true")
    ap.add_argument("--no-write", action="store_true")
    a = ap.parse_args()
    girf = str(REPO / "girf" / "example_7T.npz")
    rows = []
    with tempfile.TemporaryDirectory() as td:
        spec = _spec(Path(td))
        runs = [
            (
                "simulate fwd+bwd, nominal gradient, line-aware",
                [sys.executable, "-c", _CHILD, str(spec), "nominal", "1", girf],
                None,
            ),
            (
                "simulate fwd+bwd, 7 T GIRF gradient, line-aware",
                [sys.executable, "-c", _CHILD, str(spec), "girf", "1", girf],
                None,
            ),
        ]
        if not a.no_optimize:
            runs.append(
                (
                    "dtoc optimize (README command on this spec)",
                    [sys.executable, "-m", "dtoc", "optimize", str(spec), "--girf", girf, "--b0", "7", "-o",
                     str(Path(td) / "o.seq"), "--json", str(Path(td) / "m.json"), "-q"],
                    None,
                )
            )  # fmt: skip
        runs.append(
            ("simulate fwd+bwd, nominal gradient, per-sample path (20 GB cap)",
             [sys.executable, "-c", _CHILD, str(spec), "nominal", "0", girf], 20_000_000)
        )  # fmt: skip
        for name, argv, cap in runs:
            r = _run(argv, cap)
            r["name"] = name
            rows.append(r)
            print(name, {k: v for k, v in r.items() if k != "tail"}, flush=True)
    lines = ["| run | finished | wall (s) | fwd+bwd (s) | peak RSS (GB) |", "|---|---|---|---|---|"]
    for r in rows:
        fb = "-" if r["fwd_bwd_s"] is None else f"{r['fwd_bwd_s']:.1f}"
        lines.append(f"| {r['name']} | {'yes' if r['ok'] else 'NO'} | {r['wall_s']:.1f} | {fb} | {r['peak_gb']:.2f} |")
    text = "\n".join(lines) + (
        "\n\nPeak RSS: each child's own (wait4), the whole process. A run that does not finish under the "
        "address-space cap ended with an allocation error.\n"
    )
    print(text)
    if not a.no_write:
        from bench._report import write_section

        write_section("epi256", "256x256 EPI memory (issue 21)", text, "python -m bench.sim.epi256_memory")


if __name__ == "__main__":
    main()
