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
