"""bench/public_corpus.py: every file of a folder gets a row, optimized or refused in one line, never an internal
error; figures come from the commands' own JSON, and the table replaces only its marked section."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


@pytest.mark.slow  # seven subprocesses (15-50 s)
def test_a_folder_of_files_gives_one_row_each_optimized_or_refused(tmp_path):
    d = tmp_path / "corpus" / "mine"
    d.mkdir(parents=True)
    shutil.copyfile(REPO / "sequences" / "epi_small.seq", d / "epi_small.seq")
    (d / "truncated.seq").write_bytes((REPO / "sequences" / "epi_small.seq").read_bytes()[:1500])
    rows_file = tmp_path / "rows.jsonl"
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
    argv = [sys.executable, "-m", "bench.public_corpus", str(tmp_path / "corpus"), "--girf"]
    argv += [str(REPO / "girf" / "example_7T.npz"), "--no-write", "--rows", str(rows_file)]
    p = subprocess.run(argv, cwd=REPO, env=env, capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr
    rows = {Path(r["file"]).name: r for r in map(json.loads, rows_file.read_text().splitlines())}
    assert set(rows) == {"epi_small.seq", "truncated.seq"}
    ok = rows["epi_small.seq"]
    assert ok["result"] == "optimized" and ok["limits"]["source"] == "file"  # dtoc's own limit definitions
    assert ok["k_after_dk"] < ok["k_before_dk"] and ok["nrmse_after_pct"] < ok["nrmse_before_pct"]
    assert ok["peak_mb"] > 50 and ok["probe"]["kind"] == "epi"
    bad = rows["truncated.seq"]
    assert bad["result"].startswith("refused: ") and "internal error" not in bad["result"]
    assert "\n" not in bad["result"] and str(tmp_path) not in bad["result"]  # one line, no folder path
    # the rendered section: one table row per file between the markers
    table = p.stdout[p.stdout.index("<!-- public-corpus:begin -->") :]
    assert table.count("| mine | ") == 2 and "1 optimized" in table.replace("*", "")


def test_a_step_over_the_memory_cap_is_stopped_and_said_so():
    """The machine is shared: a step whose resident memory passes the cap is killed by the bench (not by the
    kernel's OOM killer, which may pick a neighbour), and its row says so; a step under the cap runs."""
    from bench.public_corpus import _stopped, run_step

    env = {**os.environ, "PYTHONPATH": str(REPO)}
    grow = "import time; b = bytearray(400 * 2**20); b[::4096] = b'x' * len(b[::4096]); time.sleep(30)"
    r = run_step([sys.executable, "-c", grow], 60.0, env, mem_cap_mb=150.0)
    assert r["mem_capped"] and not r["timed_out"] and r["wall_s"] < 25
    assert _stopped(r, 60.0).startswith("stopped at the bench's memory cap")
    r = run_step([sys.executable, "-c", "print(1)"], 60.0, env, mem_cap_mb=150.0)
    assert not r["mem_capped"] and r["rc"] == 0 and _stopped(r, 60.0) is None
