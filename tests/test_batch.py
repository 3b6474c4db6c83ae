"""`dtoc batch` (docs/batch.md): a 6-job plan (2 sequences x 3 hardware models) on the local engine and on a Dask
LocalCluster; every job byte-identical to the `dtoc optimize` it stands for; a re-run is all cache hits; a
changed model file re-runs exactly its jobs; an interrupted batch keeps what finished and a re-run does the rest."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from dtoc.batch.plan import OUT_MANIFEST, OUT_PNG, OUT_SEQ, expand, load_plan
from dtoc.batch.run import run_batch
from tests.cli_helpers import run_cli

ROOT = Path(__file__).resolve().parents[1]
SIDE = "optimized.traj.npz"
#: the manifest keys that hold wall-clock times (the only bytes two identical runs differ in)
VOLATILE = ("run_time_s", "stage_times_s")


def _model(path: Path, alpha: float) -> Path:
    m = json.loads((ROOT / "girf" / "paper_eddy_both.json").read_text())
    m["effects"][0]["params"]["alpha"] = [alpha, 0.05]
    path.write_text(json.dumps(m, indent=1))
    return path


def _plan(tmp: Path, png: bool = True, rows: list[tuple[str, str]] | None = None) -> Path:
    _model(tmp / "eddyA.json", 0.10)
    _model(tmp / "eddyB.json", 0.05)
    p = tmp / "plan.yaml"
    p.write_text(
        f"""# 2 sequences x 3 hardware models, one orientation, one option set = 6 jobs
sequences:
  gre: {ROOT / "sequences" / "gre_small.seq"}
  epi: {ROOT / "sequences" / "epi_small.seq"}
hardware:
  ex7T: {{girf: {ROOT / "girf" / "example_7T.npz"}}}
  eddyA: {{model: eddyA.json}}
  eddyB: {{model: eddyB.json, gmax: 70, smax: 178}}
orientations: [sag]
options:
  quick: {{iters: 2, warm_iters: 8}}
png: {str(png).lower()}
"""
        + (
            ""
            if rows is None
            else "rows:\n"
            + "".join(f"  - {{sequence: {a}, hardware: {b}, orientation: sag, options: quick}}\n" for a, b in rows)
        )
    )
    return p


def _manifest(p: Path) -> dict:
    m = json.loads(p.read_text())
    for k in VOLATILE:
        m.pop(k)
    return m


@pytest.fixture(scope="module")
def local_run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("batch")
    plan = _plan(tmp)
    rep = run_batch(plan, tmp / "out", workers=2)
    return tmp, plan, rep


def test_plan_expands_to_the_product_with_content_keys(local_run):
    tmp, plan, rep = local_run
    jobs = expand(load_plan(plan), plan.parent)
    assert [j.name for j in jobs] == [
        f"{s}__{h}__sag__quick" for s in ("gre", "epi") for h in ("ex7T", "eddyA", "eddyB")
    ]
    assert len({j.key for j in jobs}) == 6
    assert rep["n_jobs"] == 6 and rep["n_ran"] == 6 and rep["n_failed"] == 0, rep
    # relative model paths resolve against the plan's folder; the limits of a hardware entry reach the job
    eddyB = next(j for j in jobs if j.name == "gre__eddyB__sag__quick")
    assert eddyB.request.model == (tmp / "eddyB.json").resolve() and eddyB.request.gmax == 70
    rec = next(r for r in rep["jobs"] if r["name"] == "gre__eddyB__sag__quick")
    assert rec["figures"]["limits"] == {"gmax_mT_per_m": 70.0, "smax_T_per_m_per_s": 178.0}
    assert rec["figures"]["limit_violations"] == 0


def test_each_job_is_byte_identical_to_its_dtoc_optimize(local_run, tmp_path, capsys, monkeypatch):
    """The same library call: .seq, side-car and PNG byte for byte; the manifest equal but for its wall times."""
    tmp, plan, rep = local_run
    monkeypatch.chdir(tmp_path)
    for job in expand(load_plan(plan), plan.parent):
        r = job.request
        hw = ["--girf", r.girf] if r.girf else ["--model", r.model]
        lim = [] if r.gmax is None else ["--gmax", r.gmax, "--smax", r.smax]
        d = tmp_path / job.name
        d.mkdir()
        monkeypatch.chdir(d)
        code, _, err = run_cli(
            capsys, "optimize", r.base, *hw, *lim, "-o", OUT_SEQ, "--json", OUT_MANIFEST, "--png", OUT_PNG,
            "--orientation", "sag", "--iters", 2, "--warm-iters", 8, "-q",
        )  # fmt: skip
        assert code == 0, err
        got = tmp / "out" / job.name
        for f in (OUT_SEQ, SIDE, OUT_PNG):
            assert (d / f).read_bytes() == (got / f).read_bytes(), (job.name, f)
        assert _manifest(d / OUT_MANIFEST) == _manifest(got / OUT_MANIFEST), job.name


def test_rerun_is_all_cache_hits_and_a_changed_model_reruns_exactly_its_jobs(local_run):
    tmp, plan, first = local_run
    seq_bytes = {r["name"]: (tmp / "out" / r["name"] / OUT_SEQ).read_bytes() for r in first["jobs"]}
    again = run_batch(plan, tmp / "out", workers=2)
    assert again["n_cached"] == 6 and again["n_ran"] == 0 and again["workers"] == 0
    os.utime(tmp / "eddyA.json")  # a touch changes no byte: still all cached (the key is the content)
    assert run_batch(plan, tmp / "out", workers=2)["n_cached"] == 6
    _model(tmp / "eddyA.json", 0.12)  # a re-measured model
    third = run_batch(plan, tmp / "out", workers=2)
    ran = sorted(r["name"] for r in third["jobs"] if r["status"] == "ran")
    assert ran == ["epi__eddyA__sag__quick", "gre__eddyA__sag__quick"]
    assert third["n_cached"] == 4
    for name in ran:  # the new result differs from the old one; the old folder is kept, the link moved
        assert (tmp / "out" / name / OUT_SEQ).read_bytes() != seq_bytes[name]
    keys = {r["key"][:20] for r in first["jobs"]} | {r["key"][:20] for r in third["jobs"]}
    assert sorted(p.name for p in (tmp / "out" / "jobs").iterdir()) == sorted(keys)
    assert not (tmp / "out" / ".staging").exists()


def test_a_damaged_cached_job_runs_again(local_run):
    tmp, plan, _ = local_run
    victim = tmp / "out" / "epi__ex7T__sag__quick" / OUT_SEQ
    good = victim.read_bytes()
    victim.write_bytes(good[:-10])  # a half-written file (e.g. copied by hand)
    rep = run_batch(plan, tmp / "out", workers=1)
    assert [r["name"] for r in rep["jobs"] if r["status"] == "ran"] == ["epi__ex7T__sag__quick"]
    assert (tmp / "out" / "epi__ex7T__sag__quick" / OUT_SEQ).read_bytes() == good


@pytest.mark.slow  # (22 s; the process pool's bytes are tested in the default job)
def test_dask_local_cluster_gives_the_same_bytes(local_run, tmp_path):
    pytest.importorskip("distributed")
    tmp, plan, _ = local_run
    rep = run_batch(plan, tmp_path / "out", engine="dask", workers=2)
    assert rep["engine"] == "dask" and rep["n_ran"] == 6 and rep["n_failed"] == 0, rep
    for r in rep["jobs"]:
        for f in (OUT_SEQ, SIDE, OUT_PNG):
            assert (tmp_path / "out" / r["name"] / f).read_bytes() == (tmp / "out" / r["name"] / f).read_bytes()


def test_a_failing_job_does_not_stop_the_others(tmp_path, capsys):
    plan = _plan(tmp_path, png=False, rows=[("epi", "eddyB"), ("epi", "ex7T"), ("gre", "eddyB")])
    (tmp_path / "eddyB.json").write_text(
        '{"effects": [{"kind": "exp_eddy", "params": {"alpha": [3.0], "tau_s": [0.001]}}]}'
    )
    code, out, err = run_cli(capsys, "batch", plan, "--out", tmp_path / "out", "--workers", 2, "--json", "-", "-q")
    assert code == 1, err
    rep = json.loads(out)
    failed = sorted(r["name"] for r in rep["jobs"] if r["status"] == "failed")
    assert failed == ["epi__eddyB__sag__quick", "gre__eddyB__sag__quick"]
    assert rep["n_ran"] == 1
    for r in rep["jobs"]:
        if r["status"] == "failed":
            assert r["error"] and "\n" not in r["error"] and "Traceback" not in r["error"]
            assert not (tmp_path / "out" / r["name"]).exists()
    assert "Traceback" not in err


def test_sigint_mid_batch_keeps_the_finished_jobs_and_a_rerun_finishes(tmp_path):
    """SIGINT to the whole process group (a terminal's Ctrl-C) after the first finished job: exit 130, the
    finished job kept, no worker left, nothing half-written; the same command then runs only the rest."""
    plan = _plan(tmp_path, png=False, rows=[("epi", "ex7T"), ("epi", "eddyA"), ("epi", "eddyB")])
    cmd = [sys.executable, "-m", "dtoc", "batch", str(plan), "--out", str(tmp_path / "out"), "--workers", "2"]
    env = {**os.environ, "DTOC_FAULT_SIGNAL": "batch_job:SIGINT"}  # the batch signals itself after job 1
    p = subprocess.run(
        cmd + ["--json", str(tmp_path / "r1.json"), "-q"], env=env, capture_output=True, text=True, timeout=600
    )
    assert p.returncode == 130, p.stderr
    assert "Traceback" not in p.stderr and p.stderr.count("interrupted by SIGINT") == 1, p.stderr
    r1 = json.loads((tmp_path / "r1.json").read_text())
    kept = [r["name"] for r in r1["jobs"] if r["status"] == "ran"]
    assert r1["interrupted"] and 1 <= len(kept) < 3
    assert not (tmp_path / "out" / ".staging").exists()
    p2 = subprocess.run(cmd + ["--json", "-", "-q"], capture_output=True, text=True, timeout=600)
    assert p2.returncode == 0, p2.stderr
    r2 = json.loads(p2.stdout)
    assert sorted(r["name"] for r in r2["jobs"] if r["status"] == "cached") == sorted(kept)
    assert r2["n_ran"] == 3 - len(kept)


def test_sigint_to_the_process_group_while_jobs_run(tmp_path):
    """A real Ctrl-C: the signal reaches the batch and its workers together (workers ignore it; the batch
    stops them)."""
    plan = _plan(tmp_path, png=False, rows=[("epi", "ex7T"), ("epi", "eddyA"), ("gre", "eddyB")])
    p = subprocess.Popen(
        [sys.executable, "-m", "dtoc", "batch", str(plan), "--out", str(tmp_path / "out"), "--workers", "2"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )
    # wait until a worker is inside a job (its private folder exists), then Ctrl-C the group
    staging = tmp_path / "out" / ".staging"
    t0 = time.monotonic()
    while not (staging.is_dir() and any(staging.iterdir())):
        assert p.poll() is None and time.monotonic() - t0 < 120, "no job started"
        time.sleep(0.05)
    os.killpg(p.pid, signal.SIGINT)
    _, err = p.communicate(timeout=120)
    assert p.returncode == 130, err
    assert "Traceback" not in err and "KeyboardInterrupt" not in err and "panicked" not in err, err
    assert err.count("interrupted by SIGINT") == 1, err
    assert not (tmp_path / "out" / ".staging").exists()
    t0 = time.monotonic()  # no worker outlives the batch: the process group empties
    with pytest.raises(ProcessLookupError):
        while time.monotonic() - t0 < 10:
            os.killpg(p.pid, 0)
            time.sleep(0.1)


def test_bad_plans_are_one_line(tmp_path, capsys):
    plan = _plan(tmp_path, png=False)
    cases = {
        "sequences: {}\nhardware: {a: {ideal: true}}\n": "sequences",
        "sequences: {a: x.seq}\nhardware: {a: {ideal: true, girf: g.npz}}\n": "exactly one",
        "sequences: {a: x.seq}\nhardware: {a: {ideal: true}}\noptions: {o: {out: x.seq}}\n": "not allowed",
        "sequences: {a: x.seq}\nhardware: {a: {ideal: true}}\n": "not found",
        "sequences: {'a b': x.seq}\nhardware: {a: {ideal: true}}\n": "letters",
        "- 1\n": "mapping",
    }
    for text, want in cases.items():
        plan.write_text(text)
        code, _, err = run_cli(capsys, "batch", plan, "--out", tmp_path / "o")
        assert code == 2 and want in err and len(err.strip().splitlines()) == 1, (text, err)
    # the report never overwrites an input, even with --force
    seq = tmp_path / "mine.seq"
    seq.write_bytes((ROOT / "sequences" / "epi_small.seq").read_bytes())
    plan.write_text(f"sequences: {{a: {seq}}}\nhardware: {{a: {{ideal: true}}}}\n")
    code, _, err = run_cli(capsys, "batch", plan, "--out", tmp_path / "o2", "--json", seq, "--force")
    assert code == 2 and "--json" in err and len(err.strip().splitlines()) == 1, err
    assert seq.read_bytes() == (ROOT / "sequences" / "epi_small.seq").read_bytes()
    assert not (tmp_path / "o2").exists()
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "keep.txt").write_text("mine")
    plan.write_text(_plan(tmp_path, png=False).read_text())
    code, _, err = run_cli(capsys, "batch", plan, "--out", tmp_path / "full")
    assert code == 2 and "not a dtoc batch folder" in err
    assert (tmp_path / "full" / "keep.txt").read_text() == "mine"
