"""'auto' cuts the long periods of a short multi-slice EPI in parts when the cost rule holds (docs/optimize.md,
"Long sequences"): the full-loss stage is then not run and the image is kept for the report; a sequence longer than
``window_auto_s`` keeps the old rule (whole: not yet measured)."""

from __future__ import annotations

import pytest

import dtoc.optimize.run as R
from dtoc.hardware.effects import Delay, ExpEddy
from dtoc.hardware.model import HardwareModel
from dtoc.optimize.config import load_config
from dtoc.optimize.run import free_edges, image_in_loss, window_plan
from dtoc.optimize.windowed import DENSE_MAX, period_free_counts
from dtoc.seq.load import load_sequence

pytest.importorskip("pypulseq")


@pytest.fixture(scope="module")
def ms_epi(tmp_path_factory):
    from bench.protocols import epi_multislice

    p = tmp_path_factory.mktemp("msepi") / "ms.seq"
    p.write_bytes(epi_multislice(n=64, slices=3, labels=False))
    return load_sequence(str(p))


def test_a_short_multislice_epi_is_cut_in_parts_only_by_the_cost_rule(ms_epi, monkeypatch):
    ir, hw = ms_epi, HardwareModel([ExpEddy(0.01, 2e-3), Delay(4e-6)]).frozen()
    free = free_edges(ir)
    cfg = load_config(ir.kind, None)
    assert ir.kind == "epi" and image_in_loss(cfg)
    assert period_free_counts(ir, free).max() > DENSE_MAX  # a slice's echo train is longer than a dense window
    assert ir.duration_s <= cfg.window_auto_s
    # the estimates of this small file are below the rule's 120 s: whole, as before
    assert window_plan(ir, hw, cfg, free, None) is None
    monkeypatch.setattr(R, "WINDOW_AUTO_WHOLE_S", 0.0)
    monkeypatch.setattr(R, "WINDOW_AUTO_GAIN", 1.0)
    plan = window_plan(ir, hw, cfg, free, None)
    assert plan is not None and plan["by_cost"] and "parts of periods" in plan["note"]
    assert "the image for the report" in plan["note"] and "full-loss stage is not run" in plan["note"]
    # an image asked for explicitly keeps the whole solve with its full loss
    assert window_plan(ir, hw, cfg, free, True) is None
    # longer than window_auto_s: parts of non-spin-echo periods are not taken by 'auto' (not yet measured)
    assert window_plan(ir, hw, load_config(ir.kind, None, {"window_auto_s": 0.1}), free, None) is None
