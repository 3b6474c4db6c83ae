"""The output convention of docs/cli.md on every command, and interrupts (SIGINT/SIGTERM) at each stage."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import run_cli

REPO = Path(__file__).resolve().parents[1]
EPI = REPO / "sequences" / "epi_small.seq"
GRE = REPO / "sequences" / "gre_small.seq"
GIRF = REPO / "girf" / "example_7T.npz"
FAST = ["--warm-iters", "20", "--iters", "2", "--threads", "1"]
#: unit suffixes a report key may end with (docs/cli.md); dimensionless figures are listed by name
UNIT = re.compile(r"(_percent|_dk|_rad_per_m|_mT_per_m|_T_per_m_per_s|_uT|_rad|_s|_hz|_T|_m)$")


def _commands(tmp: Path) -> dict[str, list]:
    meas = tmp / "meas.npz"
    rng = np.random.default_rng(0)
    g = rng.standard_normal((4, 3, 400)).cumsum(-1) * 0.1
    np.savez(meas, dt=np.array(1e-5), g=g, G=g)
    return {
        "check": ["check", EPI],
        "diff": ["diff", EPI, GRE],
        "predict": ["predict", EPI, "--girf", GIRF],
        "girf show": ["girf", "show", GIRF],
        "girf fit": ["girf", "fit", meas, "-o", tmp / "fit.npz"],
        "simulate": ["simulate", GRE],
        "optimize": ["optimize", EPI, "--girf", GIRF, "-o", tmp / "o.seq", *FAST],
    }


def test_json_dash_is_clean_json_on_stdout_and_the_table_moves_to_stderr(capsys, tmp_path):
    for name, argv in _commands(tmp_path).items():
        code, out, err = run_cli(capsys, *argv, "--json", "-")
        assert code in (0, 1), (name, err)
        json.loads(out)  # stdout is the report and nothing else
        assert "┃" in err or "│" in err or "OK" in err or "same" in err, (name, err[-300:])
        for p in tmp_path.glob("*"):
            if p.name != "meas.npz":
                p.unlink()


def test_json_path_writes_a_file_and_the_table_stays_on_stdout(capsys, tmp_path):
    for name, argv in _commands(tmp_path).items():
        j = tmp_path / "r.json"
        code, out, err = run_cli(capsys, *argv, "--json", j)
        assert code in (0, 1), (name, err)
        json.loads(j.read_text())
        assert out.strip(), name  # the human table is on stdout
        assert not out.lstrip().startswith("{"), name
        for p in tmp_path.glob("*"):
            if p.name != "meas.npz":
                p.unlink()


def test_identify_and_girf_import_follow_it_too(capsys, tmp_path, shared_data):
    from dtoc.hardware.girf_io import save_girf
    from dtoc.hardware.model import HardwareModel, build_effect, girf_effect
    from dtoc.identify.synth import lowpass_girf, probe_waveforms, save_measurement, simulate_measurement

    dt = 10e-6
    gd = lowpass_girf(dt)
    save_girf(gd, tmp_path / "declared.npz")
    true = HardwareModel([girf_effect(gd), build_effect("delay", {"seconds": 3e-6}, axis="x")])
    save_measurement(
        simulate_measurement(true, probe_waveforms(3, 1500, dt, seed=3), dt, sigma_G=0.01, seed=4), tmp_path / "m.npz"
    )
    ident = ["identify", tmp_path / "m.npz", "--girf", tmp_path / "declared.npz", "-o", tmp_path / "u.json", "-q"]
    code, out, err = run_cli(capsys, *ident, "--json", "-")
    assert code == 0, err
    assert {"before", "after", "effects", "explained"} <= set(json.loads(out))  # stdout is the §3 report only
    assert "explained" in err  # the tables went to stderr
    code, out, err = run_cli(capsys, *ident, "--json", tmp_path / "r.json", "--force")
    assert code == 0 and "explained" in out and json.loads((tmp_path / "r.json").read_text())["effects"]
    mat = shared_data / "girf" / "kcl_7T_terra_2024" / "7T_GIRF.mat"
    if mat.exists():
        code, out, err = run_cli(capsys, "girf", "import", mat, "-o", tmp_path / "k.npz", "--json", "-")
        assert code == 0 and len(json.loads(out)["terms"]) >= 9 and "DC gain" in err


def test_report_keys_carry_units(capsys, tmp_path):
    code, out, _ = run_cli(capsys, "simulate", EPI, "--girf", GIRF, "--json", "-")
    r = json.loads(out)
    figures = {k for k in r if k.startswith(("nrmse", "ghost", "kspace"))}
    assert figures and all(UNIT.search(k) for k in figures), figures
    cmds = _commands(tmp_path)
    code, out, _ = run_cli(capsys, *cmds["optimize"], "--json", "-")
    m = json.loads(out)
    for side in ("before", "after"):
        bad = [k for k in m[side] if not (UNIT.search(k) or k.startswith("n_"))]
        assert not bad, bad
    # one key per quantity across commands: simulate and optimize name the k error the same way
    assert "kspace_max_error_dk" in r and "kspace_max_error_dk" in m["after"]
    # and the same number for the same file and model: optimize's "before" is what simulate reports
    assert m["before"]["kspace_max_error_dk"] == pytest.approx(r["kspace_max_error_dk"], rel=1e-6)


def _dtoc(*args, env=None):
    return subprocess.run(
        [sys.executable, "-m", "dtoc", *map(str, args)],
        cwd=REPO,
        capture_output=True,
        text=True,
        env={**os.environ, **(env or {})},
        timeout=600,
    )


@pytest.mark.parametrize(
    "stage, sig, code",
    [
        ("setup", "SIGINT", 130),
        ("setup", "SIGTERM", 143),
        ("warm_start", "SIGINT", 130),
        ("warm_start", "SIGTERM", 143),
        ("full_loss", "SIGTERM", 143),
        ("export", "SIGINT", 130),
    ],
)
def test_interrupt_at_each_stage(tmp_path, stage, sig, code):
    out, man = tmp_path / "o.seq", tmp_path / "o.json"
    r = _dtoc(
        "optimize",
        EPI,
        "--girf",
        GIRF,
        "-o",
        out,
        "--json",
        man,
        "-q",
        *FAST,
        env={"DTOC_FAULT_SIGNAL": f"{stage}:{sig}"},
    )
    assert r.returncode == code, r.stderr
    last = r.stderr.strip().splitlines()[-1]
    assert last.startswith(f"dtoc: interrupted by {sig}") and "Traceback" not in r.stderr, r.stderr
    files = sorted(p.name for p in tmp_path.iterdir())
    if stage == "setup":  # nothing to keep yet: nothing written
        assert files == [] and "no output written" in last
    elif stage == "export":  # the signal waits for the outputs, which are complete and not marked
        assert files == ["o.json", "o.seq", "o.traj.npz"] and "outputs were complete" in last
        assert json.loads(man.read_text())["interrupted"] is False
        assert b"DtocInterrupted" not in out.read_bytes()
    else:  # best-so-far, marked in the .seq and the manifest, with a checkpoint to resume from
        assert files == ["o.json", "o.seq", "o.seq.ckpt.npz", "o.traj.npz"]
        m = json.loads(man.read_text())
        assert m["interrupted"] is True and m["checkpoint"].endswith("o.seq.ckpt.npz")
        assert b"DtocInterrupted 1" in out.read_bytes()
        assert "--resume" in last
        r2 = _dtoc("check", out)
        assert r2.returncode == 0 and "interrupted" in r2.stderr  # valid, but flagged
        out2, man2 = tmp_path / "r.seq", tmp_path / "r.json"
        r3 = _dtoc(
            "optimize", EPI, "--girf", GIRF, "-o", out2, "--json", man2, "-q", *FAST, "--resume", m["checkpoint"]
        )
        assert r3.returncode == 0, r3.stderr
        m2 = json.loads(man2.read_text())
        assert m2["interrupted"] is False and m2["resumed_from"]["path"] == m["checkpoint"]
        assert b"DtocInterrupted" not in out2.read_bytes()
