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


BUDGETS = {"read": 120.0, "other": 120.0, "optimize": 300.0}


def test_merge_replaces_only_the_rerun_files_rows_and_recounts(tmp_path, monkeypatch):
    """--merge: a rerun file's row replaces its own (same folder and name), a new file is appended, every other
    row stays, and the section's counts, classes, commits and dates are rendered again over the merged table;
    the page outside the section's markers (hand-written notes) is untouched."""
    from bench import public_corpus as pc

    rows = [_row("a", "one.seq", "timed out after 300 s", "aaa1111"), _row("b", "two.seq", "optimized", "bbb2222")]
    doc = tmp_path / "foreign.md"
    sec = pc.render(rows, "KCL 7 T", BUDGETS, "?", when="2026-11-26 10:00")
    doc.write_text("# page\n\n" + sec + "\nnotes by hand\n")
    monkeypatch.setattr(pc, "DOC", doc)
    assert "**2 files from 1 writers (pypulseq): 1 optimized, 0 refused with one line, 1 stopped by the bench" in sec
    new = [_row("a", "one.seq", "optimized", "ccc3333"), _row("c", "three.seq", "refused: no ADC", "ccc3333")]
    pc.write_section(pc.merge_section(new, "ccc3333", None, BUDGETS, when="2026-11-27 09:00"))
    out = doc.read_text()
    lines = [ln for ln in out.splitlines() if ln.startswith("| ") and not ln.startswith("| source")]
    assert [ln.split(" | ")[1] for ln in lines] == ["one.seq", "two.seq", "three.seq"]
    assert "optimized" in lines[0] and lines[0].endswith("| ccc3333 |") and lines[1].endswith("| bbb2222 |")
    assert "**3 files from 1 writers (pypulseq): 2 optimized, 1 refused with one line, 0 stopped by the bench" in out
    assert "- optimized: 2 (a/one.seq, b/two.seq)" in out and "timed out" not in out.split("| source |")[0]
    assert "commits ccc3333 (2 rows), bbb2222 (1 row)." in out and "Rows ran 2026-11-26 to 2026-11-27 (UTC)" in out
    assert "GIRF: KCL 7 T." in out  # kept from the section merged into when not given
    assert out.startswith("# page") and out.endswith("notes by hand\n") and out.count(pc.BEGIN) == 1


def test_a_refusal_is_rendered_whole_without_the_machines_available_memory(tmp_path, monkeypatch):
    """The result cell holds the whole refusal (its way out is at its end), and none of the machine's available
    memory (it changes between runs: the same file would get another cell); a merged old row is cleaned too."""
    from bench import public_corpus as pc

    refusal = (
        "refused: x.seq: optimize: estimate (whole solve of 37451885 fine and 34 ADC samples): ~109 min and 84 GiB "
        "peak memory; 19.8 GiB available on this machine (rough: docs/cli.md, Cost estimates): needs about 84 GiB of "
        "memory (estimate, before any work), more than 75% of the 19.8 GiB available here: refused; a shorter file "
        "(it cannot be solved period by period: the sequence has no excitation to cut it at)"
    )
    r = _row("cest", "x.seq", refusal, "ddd4444")
    r["optimize_s"], r["optimize_cpu_s"] = 9.4, 4.2
    line = pc.row_line(dict(r), "?")
    cell = pc._cells(line)[pc.C_RESULT]
    assert cell.endswith(
        "a shorter file (it cannot be solved period by period: the sequence has no excitation to cut it at)"
    )
    assert "GiB available" not in cell and "more than 75% of the memory available: refused" in cell
    assert "~109 min and 84 GiB peak memory (rough" in cell and pc._cells(line)[13] == "1 (9 / 4 CPU)"
    assert pc.outcome(cell) == "refused by the run's cost estimate (memory), before any work"
    assert pc.outcome("refused: internal error: ModuleNotFoundError: x") == "internal error"  # (the reader's)
    # an old row of the page, cut and with the memory in it, merged: cleaned, and its class counted
    doc = tmp_path / "foreign.md"
    monkeypatch.setattr(pc, "DOC", doc)
    old = line.replace(cell, pc._cell(refusal[:220]))
    doc.write_text(pc.render([_row("b", "two.seq", "optimized", "bbb2222")], "G", BUDGETS, "?") + "\n")
    doc.write_text(doc.read_text().replace(pc.END, old + "\n" + pc.END))
    out = pc.merge_section([], "?", None, BUDGETS)
    assert (
        "GiB available" not in out
        and "- refused by the run's cost estimate (memory), before any work: 1 (cest/x.seq)" in out
    )
