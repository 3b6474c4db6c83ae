"""`dtoc optimize` end to end on the small EPI spec with the repo's example 7 T GIRF: the written
.seq passes `dtoc check`, is byte-identical on a re-run, reduces the k-space error; bad input gives
one line, a non-zero exit and no output; Ctrl-C keeps the best-so-far and --resume continues."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
GIRF = REPO / "girf" / "example_7T.npz"
EPI = REPO / "sequences" / "epi_small.yaml"
FAST = ["--warm-iters", "40", "--iters", "2", "--threads", "1", "--b0", "7"]


def _dtoc(*args, cwd=None):
    return subprocess.run(
        [sys.executable, "-m", "dtoc", *map(str, args)], capture_output=True, text=True, cwd=cwd, timeout=300
    )


@pytest.fixture(scope="module")
def run1(tmp_path_factory):
    if not GIRF.exists():
        pytest.skip("girf/example_7T.npz absent")
    d = tmp_path_factory.mktemp("opt")
    r = _dtoc("optimize", EPI, "--girf", GIRF, "-o", d / "a.seq", "--json", d / "a.json", "--png", d / "a.png", *FAST)
    assert r.returncode == 0, r.stderr
    return d


def test_outputs_exist_and_manifest_has_contract_keys(run1):
    m = json.loads((run1 / "a.json").read_text())
    for side in ("before", "after"):
        for key in ("nrmse_percent", "ghost_ratio_percent", "kspace_rms_error_rad_per_m", "kspace_max_error_dk"):
            assert key in m[side]
    for key in ("n_samples_discarded", "loss_history", "run_time_s", "inputs", "options", "versions"):
        assert key in m
    # EPI: the ideal image's own ghost-region energy and the excess the hardware adds
    a = m["after"]
    assert (
        a["ghost_ratio_ideal_percent"] == m["before"]["ghost_ratio_ideal_percent"]
        and a["ghost_ratio_ideal_percent"] >= 0
    )
    assert a["ghost_ratio_excess_percent"] == pytest.approx(
        a["ghost_ratio_percent"] - a["ghost_ratio_ideal_percent"], abs=1e-12
    )
    assert m["before"]["ghost_ratio_excess_percent"] > a["ghost_ratio_excess_percent"]
    assert m["inputs"]["base"]["sha256"] and m["inputs"]["girf"]["sha256"]
    assert m["limit_violations"] == 0 and m["output"]["check_ok"] is True
    # the optimization must actually help: k-space error and image error drop
    assert m["after"]["kspace_max_error_dk"] < 0.2 * m["before"]["kspace_max_error_dk"]
    assert m["after"]["nrmse_percent"] < m["before"]["nrmse_percent"]
    ex = m["exported_extremes"]
    assert max(ex["gmax_mT_per_m"]) <= m["limits"]["gmax_mT_per_m"]
    assert max(ex["smax_T_per_m_per_s"][:2]) <= m["limits"]["smax_T_per_m_per_s"]
    assert (run1 / "a.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_written_file_passes_check_and_reads_back(run1):
    r = _dtoc("check", run1 / "a.seq")
    assert r.returncode == 0, r.stdout + r.stderr
    from dtoc.seq.read import read_seq

    ir = read_seq(run1 / "a.seq")
    assert ir.n_adc_samples == 256


def test_rerun_is_byte_identical(run1):
    r = _dtoc("optimize", EPI, "--girf", GIRF, "-o", run1 / "b.seq", *FAST)
    assert r.returncode == 0, r.stderr
    assert (run1 / "a.seq").read_bytes() == (run1 / "b.seq").read_bytes()


def test_existing_output_needs_force(run1):
    r = _dtoc("optimize", EPI, "--girf", GIRF, "-o", run1 / "a.seq", *FAST)
    assert r.returncode != 0 and "--force" in r.stderr and len(r.stderr.strip().splitlines()) == 1


@pytest.mark.parametrize(
    "extra, match",
    [
        (["--gmax", "1"], "gmax"),  # below the readout amplitude: no waveform can sample k-space
        (["--smax", "5"], "smax"),  # fixed slice-select ramps already exceed it
    ],
)
def test_impossible_limits_one_line_nothing_written(tmp_path, extra, match):
    if not GIRF.exists():
        pytest.skip("girf/example_7T.npz absent")
    out = tmp_path / "x.seq"
    r = _dtoc("optimize", EPI, "--girf", GIRF, "-o", out, "--json", tmp_path / "m.json", *extra, *FAST)
    assert r.returncode == 2
    assert r.stderr.startswith("dtoc: error:") and match in r.stderr and len(r.stderr.strip().splitlines()) == 1
    assert list(tmp_path.iterdir()) == []


def test_girf_of_wrong_shape_one_line_nothing_written(tmp_path):
    bad = tmp_path / "bad.npz"
    np.savez(bad, dt=10e-6, h=np.ones((2, 2, 5)))
    out = tmp_path / "x.seq"
    r = _dtoc("optimize", EPI, "--girf", bad, "-o", out)
    assert r.returncode != 0 and r.stderr.startswith("dtoc: error:") and len(r.stderr.strip().splitlines()) == 1
    assert not out.exists()


def test_sequence_without_adc_is_rejected(tmp_path):
    import copy

    from dtoc.errors import InputError
    from dtoc.optimize.run import optimize_sequence
    from dtoc.seq.load import load_sequence

    ir = copy.copy(load_sequence(EPI))
    ir.adc = []
    with pytest.raises(InputError, match="no ADC"):
        optimize_sequence(ir, out=tmp_path / "x.seq")
    assert not (tmp_path / "x.seq").exists()


def test_interrupt_keeps_best_and_resume_continues(tmp_path):
    if not GIRF.exists():
        pytest.skip("girf/example_7T.npz absent")
    from dtoc.optimize.config import load_config
    from dtoc.optimize.run import optimize_sequence

    cfg = load_config("epi", None, {"warm_iters": 20, "iters": 6, "threads": 1, "optimizer": "adam", "lr": 1e-5})
    calls = {"n": 0}

    def progress(stage, it, total, loss):
        if stage == "full" and it == 3:
            raise KeyboardInterrupt

    res = optimize_sequence(EPI, girf=GIRF, out=tmp_path / "a.seq", config=cfg, progress=progress)
    m = res.manifest
    assert m["interrupted"] is True and (tmp_path / "a.seq").exists()
    ck = Path(m["checkpoint"])
    assert ck.exists()
    assert m["after"]["kspace_rms_error_rad_per_m"] < m["before"]["kspace_rms_error_rad_per_m"]
    res2 = optimize_sequence(EPI, girf=GIRF, out=tmp_path / "b.seq", config=cfg, resume=ck)
    m2 = res2.manifest
    assert m2["interrupted"] is False
    full_its = [h["it"] for h in m2["loss_history"] if h["stage"] == "full"]
    assert full_its[-1] == 6 and min(full_its) <= 3  # history carried over, continued to the end
    assert calls["n"] == 0


def test_golden_precompensated_seq_regression(run1):
    """CI regression: the small golden file (regenerate with the command in docs/optimize.md) must match
    a fresh run within 5 uT/m (an algorithm change moves samples by far more)."""
    golden = REPO / "sequences" / "golden_opt_epi_small.seq"
    if not golden.exists():
        pytest.skip("golden file absent")
    r = _dtoc("diff", golden, run1 / "a.seq", "--rtol", "1e-4", "--atol", "5e-3")
    assert r.returncode == 0, r.stdout + r.stderr


def test_golden_gre_amplitude_limited_regression(tmp_path):
    """CI regression of the GRE path (IRLS warm start, hard limits at gmax 20 mT/m, the paper's eddy
    currents as a model file): regenerate sequences/golden_opt_gre_small.seq with the command in
    docs/optimize.md and compare with `dtoc diff`; the file obeys the 20 mT/m limit."""
    golden = REPO / "sequences" / "golden_opt_gre_small.seq"
    model = REPO / "girf" / "paper_eddy_both.json"
    out = tmp_path / "g.seq"
    r = _dtoc(
        "optimize",
        REPO / "sequences" / "gre_small.yaml",
        "--model",
        model,
        "-o",
        out,
        "--gmax",
        "20",
        "--warm-iters",
        "60",
        "--threads",
        "1",
    )
    assert r.returncode == 0, r.stderr
    r = _dtoc("diff", golden, out, "--rtol", "1e-4", "--atol", "5e-3")
    assert r.returncode == 0, r.stdout + r.stderr
    r = _dtoc("check", out, "--gmax", "20")
    assert r.returncode == 0, r.stdout + r.stderr
    r = _dtoc("check", out, "--gmax", "19")  # the limit is active: a tighter one is violated
    assert r.returncode != 0


@pytest.mark.slow  # (23 s)
def test_phantom_option_changes_the_figures_not_the_gre_waveform(tmp_path):
    """`--phantom brain-noscalp` (the paper's kind of phantom) is recorded in the manifest and changes the
    image figures; the GRE default (k-space warm start, no image term) does not look at the phantom, so
    the exported waveform is byte-identical: the pre-compensation is not fitted to one object."""
    model = REPO / "girf" / "paper_eddy_both.json"
    m = {}
    for ph in ("brain", "brain-noscalp"):
        r = _dtoc(
            "optimize",
            REPO / "sequences" / "gre_small.yaml",
            "--model",
            model,
            "-o",
            tmp_path / f"{ph}.seq",
            "--json",
            tmp_path / f"{ph}.json",
            "--gmax",
            "20",
            "--warm-iters",
            "60",
            "--threads",
            "1",
            "--phantom",
            ph,
        )
        assert r.returncode == 0, r.stderr
        m[ph] = json.loads((tmp_path / f"{ph}.json").read_text())
        assert m[ph]["phantom"] == {"builtin": ph}
    assert m["brain"]["output"]["sha256"] == m["brain-noscalp"]["output"]["sha256"]
    assert abs(m["brain"]["before"]["nrmse_percent"] - m["brain-noscalp"]["before"]["nrmse_percent"]) > 1
    r = _dtoc(
        "optimize",
        REPO / "sequences" / "gre_small.yaml",
        "--model",
        model,
        "-o",
        tmp_path / "x.seq",
        "--phantom",
        "brain-noscalp:zz",
    )
    assert r.returncode != 0 and len(r.stderr.strip().splitlines()) == 1 and not (tmp_path / "x.seq").exists()
