"""`dtoc simulate`: ideal vs realized, JSON contract, determinism, one-line errors."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from dtoc.cli.main import run

REPO = Path(__file__).resolve().parents[1]
EPI = REPO / "sequences" / "epi_small.yaml"
# a small spoiled GRE (8 x 8, 8 repetitions) keeps these tests fast
GRE_SPEC = """kind: gre
name: gre_tiny
fov_mm: 32
matrix: 8
dwell_us: 100
flip_angle_deg: 15
tr_ms: 5
te_ms: 1.75
repetitions: 8
spoiler_mT_per_m: 17.6
spoiler_duration_ms: 1.0
"""


@pytest.fixture(scope="module")
def GRE(tmp_path_factory):
    p = tmp_path_factory.mktemp("spec") / "gre_tiny.yaml"
    p.write_text(GRE_SPEC)
    return p


def _run(argv, capsys):
    try:
        run([str(a) for a in argv])
        code = 0
    except SystemExit as e:
        code = e.code if isinstance(e.code, int) else 1
    out = capsys.readouterr()
    return code, out.out, out.err


@pytest.fixture(scope="module")
def delay_model(tmp_path_factory):
    p = tmp_path_factory.mktemp("hw") / "delay.json"
    p.write_text(json.dumps({"effects": [{"kind": "delay", "axis": "x", "params": {"seconds": 3e-6}}]}))
    return p


def test_simulate_ideal_gre_is_exact_and_deterministic(tmp_path, capsys, GRE):
    j1, j2, p1, p2 = (tmp_path / n for n in ("a.json", "b.json", "a.png", "b.png"))
    code, out, err = _run(["simulate", GRE, "--json", j1, "--png", p1], capsys)
    assert code == 0, err
    r = json.loads(j1.read_text())
    assert r["nrmse_percent"] == 0.0 and r["kspace_rms_error_rad_per_m"] == 0.0 and r["kspace_max_error_dk"] == 0.0
    assert r["ghost_ratio_percent"] is None and r["hardware"]["identity"] is True
    assert r["sequence"]["matrix"] == [8, 8] and r["sequence"]["n_adc_samples"] == 64
    assert "NRMSE" in out and "NRMSE" not in err  # table on stdout, progress on stderr
    code, _, _ = _run(["simulate", GRE, "--json", j2, "--png", p2], capsys)
    assert code == 0
    assert j1.read_bytes() == j2.read_bytes() and p1.read_bytes() == p2.read_bytes()
    assert p1.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # outputs are not clobbered without --force
    code, _, err = _run(["simulate", GRE, "--json", j1], capsys)
    assert code != 0 and "--force" in err and err.count("\n") == 1


def test_simulate_epi_readout_delay_makes_nyquist_ghosts(tmp_path, capsys, delay_model):
    # A readout-axis delay shifts odd and even EPI lines in opposite k_x directions: N/2 ghosts.
    code, out, err = _run(["simulate", EPI, "--model", delay_model, "--json", "-"], capsys)
    assert code == 0, err
    r = json.loads(out)
    assert r["hardware"]["identity"] is False
    assert r["ghost_ratio_percent"] > 20 * r["ghost_ratio_ideal_percent"] and r["ghost_ratio_percent"] > 0.1
    assert 1 < r["nrmse_percent"] < 100
    # every sample lies on a flat top (dwell 10 us, gamma G_ro dwell = dk): a 3 us delay moves each by
    # gamma G_ro 3 us = 0.3 dk along x, alternating in sign with the readout polarity
    dk = 2 * np.pi / 0.25
    assert r["kspace_max_error_dk"] == pytest.approx(0.3, rel=1e-6)
    assert r["kspace_rms_error_rad_per_m"] == pytest.approx(0.3 * dk, rel=1e-6)


@pytest.mark.parametrize(
    "extra,needle",
    [
        (["--phantom", "missing.npz"], "phantom file not found"),
        (["--phantom", "BAD"], "missing key(s) t1_s"),
        (["--dtype", "float16"], "--dtype 'float16'"),
        (["--girf", "g.npz", "--model", "m.json"], "either --girf or --model"),
    ],
)
def test_simulate_bad_inputs_are_one_line_errors(tmp_path, capsys, GRE, extra, needle):
    bad = tmp_path / "bad.npz"
    np.savez(bad, pd=np.ones((8, 8)), t2_s=np.ones((8, 8)), fov_m=np.array(0.032))
    extra = [str(bad) if e == "BAD" else e for e in extra]
    code, out, err = _run(["simulate", GRE, *extra], capsys)
    assert code == 2
    assert err.startswith("dtoc: error: ") and err.count("\n") == 1 and "Traceback" not in err
    assert needle in err
