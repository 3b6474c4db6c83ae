"""The report image of a windowed run is estimated from its phase distribution graph (issue 36, the trufi files).

A balanced SSFP keeps its transverse pathways: ~160 of them emit at every ADC sample of pypulseq's 256-line trufi
(KomaMRI's spoiled 256-line GREs: ~2), and its report image's simulation passed the bench's 6 GB after minutes while the estimate from
voxels x samples said ~2 GiB.  :func:`dtoc.util.cost.emission_cost` counts the emitting states x samples of the
graph; a windowed run whose report image is estimated beyond :data:`dtoc.util.cost.REPORT_IMAGE_MAX_SECONDS` (or the
memory) replaces the image figures by their reason and keeps its k-space figures.  The file is written here (a
16-line trueFISP: ~16 pathways per sample on its 16 x 16 phantom)."""

from __future__ import annotations

import math

import numpy as np
import pytest

import dtoc.util.cost as cost
from dtoc.hardware.effects import Delay, ExpEddy
from dtoc.hardware.model import HardwareModel
from dtoc.optimize.config import load_config
from dtoc.optimize.run import make_phantoms, optimize_sequence, report_image_reason
from dtoc.seq.load import load_sequence
from dtoc.sim.pdg import PDGConfig, build_graph


def _write(seq, p):
    from dtoc.seq.pulseq import quiet

    with quiet():
        seq.write(str(p))
    return p


def ssfp(p, n: int = 16):
    """A 2D balanced SSFP (trueFISP), n x n, TR ~4 ms, 40 deg with alternating RF phase, every gradient rewound."""
    import pypulseq as pp

    sys = pp.Opts(max_grad=32, grad_unit="mT/m", max_slew=130, slew_unit="T/m/s", rf_ringdown_time=30e-6,
                  rf_dead_time=100e-6, adc_dead_time=10e-6)  # fmt: skip
    seq = pp.Sequence(sys)
    rf = pp.make_block_pulse(flip_angle=math.radians(40), duration=0.5e-3, system=sys, delay=sys.rf_dead_time)
    dk = 1 / 0.22
    gx = pp.make_trapezoid("x", flat_area=n * dk, flat_time=1.6e-3, system=sys)
    adc = pp.make_adc(n, duration=gx.flat_time, delay=gx.rise_time, system=sys)
    gxpre = pp.make_trapezoid("x", area=-gx.area / 2, duration=8e-4, system=sys)
    gxr = pp.make_trapezoid("x", area=-gx.area / 2, duration=8e-4, system=sys)
    for i in range(n):
        rf.phase_offset = adc.phase_offset = math.pi * (i % 2)
        area = (i - n / 2) * dk
        seq.add_block(rf)
        seq.add_block(gxpre, pp.make_trapezoid("y", area=area, duration=8e-4, system=sys))
        seq.add_block(gx, adc)
        rewind = pp.make_trapezoid("y", area=-area, duration=8e-4, system=sys)
        seq.add_block(gxr, rewind)
    seq.set_definition("FOV", [0.22, 0.22, 0.005])
    return _write(seq, p)


@pytest.fixture(scope="module")
def ir(tmp_path_factory):
    return load_sequence(ssfp(tmp_path_factory.mktemp("ssfp") / "bssfp.seq"))


def test_the_estimate_sees_the_pathways_of_a_steady_state(ir):
    """The estimate's work is the graph's emitting states x samples x voxels: for the balanced file, many pathways per
    ADC sample where the estimate from voxels x samples (:func:`dtoc.util.cost.simulation_cost`) assumes one."""
    cfg = load_config("gre", None, None)
    ph = make_phantoms(ir, cfg)
    g = build_graph(ir, PDGConfig(), ph[0])
    vox = int(np.asarray(ph[0].pd).size)
    mem, sec, per = cost.emission_cost(g, vox)
    work = sum(iv.emit.size * (iv.adc_stop - iv.adc_start) for iv in g.intervals)
    assert sec == pytest.approx(work * vox * cost.SIM_SECONDS_PER_VOXEL_SAMPLE)
    assert per == pytest.approx(work / ir.n_adc_samples) and per > 8, per
    assert sec == pytest.approx(cost.simulation_cost(vox, ir.n_adc_samples)[1] * per)  # the old one, x per
    most = max(iv.emit.size for iv in g.intervals)
    assert mem == pytest.approx(vox * (cost.SIM_BYTES_PER_VOXEL + cost.SIM_EMIT_ARRAYS * 16 * most))


@pytest.mark.parametrize("over", [False, True])
def test_report_image_beyond_its_budget_is_replaced_by_its_reason(ir, tmp_path, monkeypatch, over):
    """A windowed run (the image for the report only) with the report's budget just below its estimate: the image
    figures are its reason (never a number), the k figures stay; just above: image figures."""
    cfg = load_config("gre", None, {"windowed": "on", "gmax_mT_per_m": 32, "smax_T_per_m_per_s": 130})
    ph = make_phantoms(ir, cfg)
    est = cost.emission_cost(build_graph(ir, PDGConfig(), ph[0]), int(np.asarray(ph[0].pd).size))[1] * 4  # 3 + 1 runs
    monkeypatch.setattr(cost, "REPORT_IMAGE_MAX_SECONDS", est * (0.99 if over else 1.01))
    why = report_image_reason(ir, cfg, ph)[1]
    assert (why is not None) == over
    m = optimize_sequence(ir, out=tmp_path / "o.seq", hardware=HW, config=cfg).manifest
    assert "windowed" in m and m["after"]["kspace_max_error_dk"] < m["before"]["kspace_max_error_dk"]
    if over:
        assert why is not None and "signal pathways emit at each ADC sample" in why
        assert "image figures not computed" in why and m["sequence"]["image_term"] is False
        for s in ("before", "after"):
            assert m[s]["nrmse_percent"] is None and m[s]["image_reason"] == why
    else:
        assert m["sequence"]["image_term"] is True and m["after"]["nrmse_percent"] is not None
        assert "image_reason" not in m["after"]


HW = HardwareModel([ExpEddy(0.01, 2e-3), Delay(4e-6)]).frozen()
