"""Progress on stderr for long commands, also when stderr is not a terminal (scripts, CI logs); -q silences it."""

import io
import re
from pathlib import Path

from cli_helpers import run_cli

from dtoc.cli.progress import ProgressReporter

REPO = Path(__file__).resolve().parents[1]
LINE = re.compile(r"^dtoc optimize: warm \d+/\d+ \(\d+ %\), loss \S+, elapsed [\d.]+ s, ETA ([\d.]+ s|-)$")


def test_plain_lines_with_elapsed_and_eta_are_throttled():
    s = io.StringIO()
    rep = ProgressReporter("dtoc optimize", stream=s, tty=False, every_s=3600)
    for it in range(1, 101):
        rep.update("warm", it, 100, 1.0 / it)
    rep.step("discard")
    lines = s.getvalue().splitlines()
    assert len(lines) == 3  # first report, last iteration, the named stage: throttled in between
    assert lines[0].startswith("dtoc optimize: warm 1/100 (1 %), loss 1,") and lines[0].endswith("ETA -")
    assert lines[1].startswith("dtoc optimize: warm 100/100 (100 %), loss 0.01,") and lines[1].endswith("ETA 0.0 s")
    assert lines[2].startswith("dtoc optimize: discard (elapsed ")


def test_quiet_prints_nothing():
    s = io.StringIO()
    rep = ProgressReporter("dtoc optimize", stream=s, tty=False, quiet=True)
    rep.update("warm", 1, 2, 0.5)
    rep.step("x")
    assert s.getvalue() == ""


def test_optimize_reports_progress_when_stderr_is_not_a_terminal(capsys, tmp_path):
    args = ["optimize", REPO / "sequences" / "epi_small.seq", "--girf", REPO / "girf" / "example_7T.npz"]
    fast = ["--warm-iters", "8", "--iters", "0"]
    code, out, err = run_cli(capsys, *args, "-o", tmp_path / "a.seq", *fast)
    assert code == 0, err
    progress = [x for x in err.splitlines() if x.startswith("dtoc optimize: warm")]
    assert progress and all(LINE.match(x) for x in progress), err
    code, out, err = run_cli(capsys, *args, "-o", tmp_path / "b.seq", *fast, "-q")
    assert code == 0 and not [x for x in err.splitlines() if x.startswith("dtoc optimize: warm")]


def test_simulate_reports_its_stages(capsys):
    code, out, err = run_cli(
        capsys, "simulate", REPO / "sequences" / "epi_small.seq", "--girf", REPO / "girf" / "example_7T.npz"
    )
    assert code == 0, err
    assert "dtoc simulate: simulating: hardware model, realized simulation (elapsed" in err
