"""CLI start-up benchmark: wall and CPU time of short dtoc commands, as a ratio to ``python -c pass``.

Run: ``python -m bench.startup [--baseline DIR] [--repeat N]`` (writes its section of docs/benchmarks.md).
``--baseline DIR``: another checkout of dtoc (e.g. ``git worktree add /tmp/base <rev>``) timed in the same
run, interleaved command by command, so that the two columns share the machine's load.
Each command runs in a fresh process (``python -m dtoc ...`` from the checkout's folder); the table gives
the median over ``--repeat`` runs and which of torch / pypulseq the command imported.
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

PROBE = (
    "import runpy, sys\n"
    "sys.argv = ['dtoc'] + sys.argv[1:]\n"
    "try:\n"
    "    runpy.run_module('dtoc', run_name='__main__')\n"
    "except SystemExit:\n"
    "    pass\n"
    "sys.stderr.write('IMPORTED ' + ','.join(m for m in ('torch', 'pypulseq', 'matplotlib') if m in sys.modules) + '\\n')\n"
)


def _commands(tmp: Path) -> list[tuple[str, list[str]]]:
    return [
        ("python -c pass", []),
        ("dtoc --help", ["--help"]),
        ("dtoc check epi_small.seq", ["check", "sequences/epi_small.seq"]),
        ("dtoc diff epi_small.seq gre_small.seq", ["diff", "sequences/epi_small.seq", "sequences/gre_small.seq"]),
        ("dtoc build epi_small.yaml", ["build", "sequences/epi_small.yaml", "-o", str(tmp / "b.seq"), "--force"]),
        (
            "dtoc optimize epi_small.yaml, 1 + 1 iterations (fixed cost of an optimize)",
            [
                "optimize",
                "sequences/epi_small.yaml",
                "--girf",
                "girf/example_7T.npz",
                "--b0",
                "7",
                "-o",
                str(tmp / "o.seq"),
                "--warm-iters",
                "1",
                "--iters",
                "1",
                "--threads",
                "1",
                "--force",
                "-q",
            ],
        ),
    ]


def _run_once(root: Path, argv: list[str]) -> tuple[float, float, str]:
    """Wall s, CPU s (user+sys of the child) and the heavy modules it imported."""
    code = "pass" if not argv else PROBE
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-c", code, *argv], cwd=root, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    imported = ""
    for line in r.stderr.splitlines():
        if line.startswith("IMPORTED "):
            imported = line[len("IMPORTED ") :].strip()
    return wall, cpu, imported


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--baseline", type=Path, default=None, help="another dtoc checkout timed side by side")
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--no-write", action="store_true", help="print only; do not update docs/benchmarks.md")
    a = ap.parse_args()
    roots = [("this", REPO)] + ([("baseline", a.baseline.resolve())] if a.baseline else [])
    with tempfile.TemporaryDirectory() as d:
        cmds = _commands(Path(d))
        res: dict[tuple[str, str], list[tuple[float, float, str]]] = {}
        for name, argv in cmds:
            _run_once(REPO, argv)  # warm the file cache
            for _ in range(a.repeat):
                for tag, root in roots:  # interleaved: both trees see the same load
                    res.setdefault((tag, name), []).append(_run_once(root, argv))
    base = {tag: statistics.median(w for w, _, _ in res[(tag, "python -c pass")]) for tag, _ in roots}
    head = "| command | wall (s) | CPU (s) | wall / `python -c pass` | imports torch / pypulseq |"
    sep = "|---|---|---|---|---|"
    if a.baseline:
        head += " baseline wall (s) | baseline imports | this / baseline |"
        sep += "---|---|---|"
    lines = [head, sep]
    for name, _ in cmds:
        w = statistics.median(x[0] for x in res[("this", name)])
        c = statistics.median(x[1] for x in res[("this", name)])
        imp = res[("this", name)][-1][2]
        row = f"| `{name}` | {w:.2f} | {c:.2f} | {w / base['this']:.1f} | {_yn(imp)} |"
        if a.baseline:
            wb = statistics.median(x[0] for x in res[("baseline", name)])
            row += f" {wb:.2f} | {_yn(res[('baseline', name)][-1][2])} | {w / wb:.2f} |"
        lines.append(row)
    load = os.getloadavg()[0]
    body = (
        f"Median of {a.repeat} fresh processes per command (`python -c <probe> ARGS` running the `dtoc` module from "
        f"the checkout's folder, file cache warm); 1-min load average at the end {load:.1f}. "
        "Target of docs/cli.md: `--help`, `check`, `diff` and `build` never import torch; `dtoc check` on a small "
        "file under 1.5 s.\n\n" + "\n".join(lines) + "\n"
    )
    if a.baseline:
        rev = subprocess.run(
            ["git", "-C", str(a.baseline), "rev-parse", "--short", "HEAD"], capture_output=True, text=True
        )
        body += (
            f"\nBaseline: commit `{rev.stdout.strip() or '?'}` (the tree before this change), same run, interleaved.\n"
        )
    print(body)
    if not a.no_write:
        from bench._report import write_section

        write_section(
            "startup", "CLI start-up", body, "python -m bench.startup" + (" --baseline DIR" if a.baseline else "")
        )


def _yn(imported: str) -> str:
    s = set(imported.split(",")) if imported else set()
    return f"{'yes' if 'torch' in s else 'no'} / {'yes' if 'pypulseq' in s else 'no'}"


if __name__ == "__main__":
    main()
