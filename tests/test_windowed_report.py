"""A k-space-only optimization of a long sequence is windowed with the image kept for the report; the windowed
solve states its k error against the tolerance and names what it cannot reach (docs/optimize.md, "Long
sequences")."""

from __future__ import annotations

import json

import numpy as np
import pytest

from dtoc.hardware.effects import Delay, ExpEddy, Gain
from dtoc.hardware.model import HardwareModel
from dtoc.optimize.config import load_config
from dtoc.optimize.run import free_edges, optimize_sequence, window_plan
from dtoc.seq.load import load_sequence
from tests.cli_helpers import run_cli
from tests.test_windowed import _idle_gre_ir

#: the paper's GRE on its 0.1 ms grid (sequences/gre_paper_r100us.yaml), 16 x 16 and 16 TRs of 10 ms: fast windows
GRE_SPEC = """kind: gre
name: gre16_r100us
fov_mm: 32
matrix: 16
dwell_us: 100
flip_angle_deg: 15
tr_ms: 10
te_ms: 2.35
rf_period_ms: 2.0
rf_spoiling_inc_deg: 117
repetitions: 16
spoiler_mT_per_m: 17.6
spoiler_duration_ms: 2.0
system:
  name: paper-gre-unconstrained
  max_grad_mT_per_m: 50
  max_slew_T_per_m_per_s: 500
  grad_raster_s: 1.0e-4
  block_raster_s: 1.0e-4
"""


@pytest.fixture
def gre(tmp_path):
    p = tmp_path / "gre16.yaml"
    p.write_text(GRE_SPEC)
    return str(p)


def _hw(*extra):
    return HardwareModel([ExpEddy(0.01, 2e-3), Delay(4e-6), *extra]).frozen()


def test_long_gre_with_image_weight_and_no_full_loss_is_windowed_with_image_figures(gre, tmp_path):
    # 'long' = above window_auto_s (lowered so that the test's 16 TRs are long); the GRE kind: image weight 1, iters 0
    cfg = load_config("gre", None, {"window_auto_s": 0.05})
    assert cfg.weights.image > 0 and cfg.iters == 0 and cfg.windowed == "auto"
    res = optimize_sequence(gre, out=tmp_path / "o.seq", hardware=_hw(), config=cfg)
    m = res.manifest
    assert m["windowed"]["windows"] == 16  # one per excitation (the first in block 0)
    assert m["sequence"]["image_term"] is True and "the image for the report" in m["windowed"]["note"]
    nb, na = m["before"]["nrmse_percent"], m["after"]["nrmse_percent"]
    assert nb is not None and na is not None and na < 0.5 * nb  # the image of the windowed output, before -> after
    sv = m["solver"]
    assert sv["method"] == "windowed" and sv["stop_reason"] == "tolerance"
    # the report's k error is the exported waveform's, within the tolerance: the norm over the encoded axes (the
    # solver's convention) of the same errors whose largest single axis the manifest's figure is
    per_axis = m["after"]["kspace_max_error_dk"]
    assert per_axis * (1 - 1e-9) <= sv["achieved_max_adc_dk"] <= np.sqrt(2) * per_axis * (1 + 1e-9)
    assert sv["achieved_max_dk"] <= cfg.k_tol_dk and sv["unreachable"]["n_samples"] == 0
    assert m["before"]["kspace_max_error_dk"] > 3 * cfg.k_tol_dk  # the model moves k: there was work to do


def test_windowed_run_names_the_samples_the_limits_leave_off_target(gre, tmp_path):
    # the chain plays 0.8 of the demand: the readout plateau needs 1.25x its amplitude, beyond gmax
    ir = load_sequence(gre)
    t_fine = np.arange(ir.n_fine) * ir.dt_fine_s
    g_ro = float(np.median(np.abs(np.interp(ir.adc_times_s, t_fine, ir.grad_mT_per_m[ir.readout_axis]))))
    cfg = load_config("gre", None, {"windowed": "on", "gmax_mT_per_m": 1.1 * g_ro / (1 - 0.005)})
    res = optimize_sequence(gre, out=tmp_path / "o.seq", hardware=_hw(Gain(0.8)), config=cfg, with_image=False)
    sv = res.manifest["solver"]
    assert sv["stop_reason"] == "converged" and sv["achieved_max_dk"] > cfg.k_tol_dk
    un = sv["unreachable"]
    assert un["n_samples"] > 0 and un["n_limits"] == un["n_samples"]  # reachable without the limits
    worst = un["worst"][0]
    assert worst["reason"] == "limits" and worst["limit"] in ("amplitude x", "slew x")  # on the readout axis
    assert worst["unconstrained_error_dk"] <= cfg.k_tol_dk < worst["error_dk"]
    assert f"sample {worst['sample']} at" in sv["summary"] and f"{worst['limit']} limit active" in sv["summary"]
    # the named figure is the exported file's
    assert worst["error_dk"] <= np.sqrt(2) * res.manifest["after"]["kspace_max_error_dk"] * (
        1 + 1e-9
    )  # norm vs one axis


def test_goldens_and_short_sequences_stay_whole_many_short_periods_are_windowed():
    hw = _hw()
    for path in ("sequences/gre_small.yaml", "sequences/gre_paper_fig5.yaml", "sequences/epi_small.yaml"):
        ir = load_sequence(path)
        cfg = load_config(ir.kind, None)
        assert window_plan(ir, hw, cfg, free_edges(ir), None) is None, path
    # 256 lines of 256 samples in 0.87 s (below window_auto_s): the whole solve is estimated far above the windowed
    ir = _idle_gre_ir(256, idle_edges=0, r_s=1e-5, n=256, fov_m=0.32)
    assert ir.duration_s < load_config("gre", None).window_auto_s
    plan = window_plan(ir, hw, load_config("gre", None), free_edges(ir), None)
    assert plan is not None and "whole solve estimated" in plan["note"]
    # ... but not when the full loss would use the image asked for, nor with windowed: off
    dto = load_config("gre", None, {"iters": 5})
    assert window_plan(ir, hw, dto, free_edges(ir), True) is None
    assert window_plan(ir, hw, load_config("gre", None, {"windowed": "off"}), free_edges(ir), None) is None


def test_windowed_solver_line_on_stderr(gre, tmp_path, capsys):
    cfgp = tmp_path / "c.yaml"
    cfgp.write_text('windowed: "on"\n')
    mp = tmp_path / "m.json"
    code, _, err = run_cli(
        capsys, "optimize", gre, "--girf", "girf/example_7T.npz", "-o", tmp_path / "o.seq", "--config", cfgp, "-q",
        "--json", mp,
    )  # fmt: skip
    assert code == 0
    m = json.loads(mp.read_text())
    assert "solver: windowed, " in m["solver"]["summary"] and m["solver"]["summary"] in err


def test_a_windowed_run_without_image_weight_simulates_no_image(gre):
    from dtoc.optimize.run import RunIO, plan_run

    cfg = load_config("gre", None, {"window_auto_s": 0.05, "weights": {"image": 0.0}})
    plan = plan_run(gre, RunIO(base_path=gre), config=cfg, hardware=_hw())
    assert plan.window is not None and plan.with_image is False and plan.imager is None
    assert "no image term" in plan.window["note"]
