"""The CLI's allocator setting (dtoc.util.allocator): the same commands with glibc's defaults
(``DTOC_MALLOC_TUNING=0``) and with freed memory kept for reuse (the default), side by side.

    python -m bench.allocator [--no-epi256] [--no-write]   -> docs/benchmarks.md "Allocator"

Each command runs as its own process, the two modes interleaved (off, on) per scenario; wall time, user and
system CPU, minor page faults and peak RSS come from the kernel's accounting of that child (wait4).  Every
output file of the two runs is compared byte for byte.  Scenarios: the README's EPI job, the paper's GRE
(300 dummy cycles), a 3D MPRAGE-like file written by pypulseq (tests/foreign/writers.py ``mprage(n=16,
nz=4, tr_shot=0.5)``) optimized with the image term on the built-in 3D head, ``dtoc simulate`` of the GRE
with 300 dummies, and the 256x256 single-shot EPI of "256x256 EPI memory" (the memory-heavy case).
"""

from __future__ import annotations

import argparse
import hashlib
import os
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]
GIRF = str(REPO / "girf" / "example_7T.npz")


def _scenarios(d: Path, with_epi256: bool) -> list[tuple[str, list[str]]]:
    sys.path.insert(0, str(REPO / "tests"))
    from foreign.writers import mprage

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        (d / "mprage.seq").write_bytes(mprage(n=16, nz=4, tr_shot=0.5))
    out = [
        ("optimize EPI 64 (README job)", ["optimize", str(REPO / "sequences/epi_esp081.seq"), "--girf", GIRF, "--b0", "7"]),
        ("optimize paper GRE (300 dummies)", ["optimize", str(REPO / "sequences/gre_paper.seq"), "--girf", GIRF]),
        ("optimize 3D MPRAGE-like + image term (brain3d)",
         ["optimize", str(d / "mprage.seq"), "--girf", GIRF, "--phantom", "brain3d", "--gmax", "32", "--smax", "130"]),
        ("simulate paper GRE --dummies 300", ["simulate", str(REPO / "sequences/gre_paper.seq"), "--girf", GIRF,
                                              "--dummies", "300", "--png", "{out}/sim.png"]),
    ]  # fmt: skip
    if with_epi256:
        data = yaml.safe_load((REPO / "sequences" / "epi_esp081.yaml").read_text())
        data.update(matrix=256, echo_spacing_ms=3.0, name="epi256")
        (d / "epi256.yaml").write_text(yaml.safe_dump(data))
        out.append(("optimize EPI 256x256", ["optimize", str(d / "epi256.yaml"), "--girf", GIRF, "--b0", "7"]))
    return out


def _run(args: list[str], out_dir: Path, tuning: str) -> dict:
    out_dir.mkdir(parents=True, exist_ok=True)
    argv = [sys.executable, "-m", "dtoc", *(a.replace("{out}", str(out_dir)) for a in args)]
    argv += ["--json", str(out_dir / "metrics.json"), "-q"]
    if args[0] == "optimize":
        argv += ["--out", str(out_dir / "out.seq")]
    env = dict(os.environ, DTOC_MALLOC_TUNING=tuning)
    with tempfile.TemporaryFile("w+") as log:
        t = time.perf_counter()
        p = subprocess.Popen(argv, stdout=log, stderr=subprocess.STDOUT, text=True, cwd=REPO, env=env)
        _, status, ru = os.wait4(p.pid, 0)
        wall = time.perf_counter() - t
        log.seek(0)
        tail = log.read()[-300:]
    files = sorted(f for f in out_dir.iterdir() if f.name != "metrics.json")
    digest = hashlib.sha256(b"".join(f.name.encode() + f.read_bytes() for f in files)).hexdigest()
    return {
        "ok": os.waitstatus_to_exitcode(status) == 0,
        "wall_s": wall,
        "user_s": ru.ru_utime,
        "sys_s": ru.ru_stime,
        "minflt": ru.ru_minflt,
        "peak_gb": ru.ru_maxrss / 1e6,
        "digest": digest,
        "n_files": len(files),
        "tail": tail,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--no-epi256", action="store_true", help="skip the 256x256 EPI (2 x ~2 min)")
    ap.add_argument("--no-write", action="store_true")
    a = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as td:
        d = Path(td)
        for i, (name, args) in enumerate(_scenarios(d, not a.no_epi256)):
            off = _run(args, d / f"s{i}_off", "0")
            on = _run(args, d / f"s{i}_on", "1")
            rows.append((name, off, on))
            print(name, {k: v for k, v in off.items() if k != "tail"}, {k: v for k, v in on.items() if k != "tail"},
                  flush=True)  # fmt: skip
    lines = [
        "| command | wall off -> on (s) | system CPU off -> on (s) | minor faults off -> on | peak RSS off -> on (GB) "
        "| wall off / on | outputs identical |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, off, on in rows:
        ok = off["ok"] and on["ok"]
        same = "yes" if ok and off["digest"] == on["digest"] and off["n_files"] else "NO"
        lines.append(
            f"| {name} | {off['wall_s']:.1f} -> {on['wall_s']:.1f} | {off['sys_s']:.1f} -> {on['sys_s']:.1f} | "
            f"{off['minflt'] / 1e6:.2f}M -> {on['minflt'] / 1e6:.2f}M | {off['peak_gb']:.2f} -> {on['peak_gb']:.2f} | "
            f"{off['wall_s'] / on['wall_s']:.2f}x | {same if ok else 'run failed'} |"
        )
    text = "\n".join(lines) + (
        "\n\noff = `DTOC_MALLOC_TUNING=0` (glibc's defaults), on = the CLI's default (`dtoc.util.allocator`: mmap and "
        "trim thresholds at 2 GiB, freed blocks stay in the process for reuse). One process per run, the two modes "
        "interleaved; CPU, faults and peak RSS of that child (wait4). Outputs: every file the command wrote (the "
        ".seq, its trajectory .npz, the simulate PNG), compared byte for byte; the --json metrics file is left out (it holds "
        "timings).\n"
    )
    print(text)
    if not a.no_write:
        from bench._report import write_section

        write_section("allocator", "Allocator", text, "python -m bench.allocator")


if __name__ == "__main__":
    main()
