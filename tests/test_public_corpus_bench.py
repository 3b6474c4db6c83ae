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


def _row(folder: str, name: str, result: str, commit: str) -> dict:
    return {
        "file": f"/x/{folder}/{name}", "writer_line": "Created by PyPulseq", "version": "1.5.0", "size_kb": 1.0,
        "limits": {"gmax": 40.0, "smax": 170.0, "source": "assumed"}, "check": "ok", "predict": "-",
        "simulate": "-", "result": result, "time_s": 1.0, "peak_mb": 1.0, "commit": commit,
    }  # fmt: skip


def test_merge_replaces_only_the_rerun_files_rows_and_recounts(tmp_path, monkeypatch):
    """--merge: a rerun file's row replaces its own (same folder and name), a new file is appended, every other
    line (rows, prose) stays, and the summary line and the commit list are recounted over the merged table."""
    from bench import public_corpus as pc

    rows = [_row("a", "one.seq", "timed out after 300 s", "aaa1111"), _row("b", "two.seq", "optimized", "bbb2222")]
    head = [
        pc.BEGIN,
        "Written by `python -m bench.public_corpus DIR --girf ...`; run then on commits aaa1111 (1 row), bbb2222 (1 row), "
        "Some CPU, 2 cores.",
        "",
        "2 files from 1 writers (pypulseq): **1 optimized**, 0 refused with one line, 1 timed out, stopped at the "
        "memory cap or killed by a signal ('exit -9'), 0 internal errors of optimize (0 files with an internal error "
        "in any step). The files are not committed.",
        "A paragraph someone wrote by hand.",
        "",
        "| source | file | writer | version | kind | size (kB) | limits (mT/m, T/m/s) | check | predict k (dk) "
        "| simulate NRMSE (%) | result | k before -> after (dk) | NRMSE before -> after (%) | time (s) | peak (MB) "
        "| RF use | commit |",
        "|" + "---|" * 17,
    ]
    doc = tmp_path / "foreign.md"
    doc.write_text("# page\n\n" + "\n".join(head + [pc.row_line(r, "?") for r in rows]) + "\n" + pc.END + "\n\nrest\n")
    monkeypatch.setattr(pc, "DOC", doc)
    new = [_row("a", "one.seq", "optimized", "ccc3333"), _row("c", "three.seq", "refused: no ADC", "ccc3333")]
    text = pc.merge_section(new, "ccc3333")
    pc.write_section(text + pc.END + "\n")
    out = doc.read_text()
    lines = [ln for ln in out.splitlines() if ln.startswith("| ") and not ln.startswith("| source")]
    assert [ln.split(" | ")[1] for ln in lines] == ["one.seq", "two.seq", "three.seq"]
    assert "optimized" in lines[0] and lines[0].endswith("| ccc3333 |") and lines[1].endswith("| bbb2222 |")
    assert "3 files from 1 writers (pypulseq): **2 optimized**, 1 refused with one line, 0 timed out" in out
    assert "on commits ccc3333 (2 rows), bbb2222 (1 row), Some CPU" in out
    assert "A paragraph someone wrote by hand." in out and out.startswith("# page") and out.endswith("rest\n")
