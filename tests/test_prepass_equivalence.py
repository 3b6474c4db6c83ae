"""The PDG pre-pass builds, on sequences beyond those of ``test_prepass_golden``, the same graphs as the per-interval
builder did when ``fixtures/prepass_equivalence.json`` was recorded (commit 0d5baba, before the builder was
vectorised per interval class).

Same contract and fingerprint as tests/test_prepass_golden.py: integer structure (states, edges, representative
parents, emitters, ADC slices) bit for bit, float arrays (nominal k, tau, amplitude bounds) to 1e-12 relative.
Sequences with what the golden set lacks: a CPMG turbo spin echo and a single-shot half-Fourier one (refocusing
pulses: conjugating edges, stimulated echoes, many echoes per excitation), a spoiled GRE whose file starts with
dummy repetitions (RF without ADC), the README job's EPI, the spin-echo EPI, and the Fig-5 GRE with the phantom the
optimizer makes for it and a short dummy train of it.

Regenerate (only for an intended change of the graph): ``python -m tests.test_prepass_equivalence``.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from dtoc.seq.load import load_sequence
from dtoc.sim import pdg
from dtoc.sim.pdg_dummies import detect_rf_spoiling, dummy_train
from dtoc.sim.pdg_graph import build_graph
from dtoc.sim.phantom import brain_phantom

try:  # pytest puts tests/ on the path; ``python -m tests.test_prepass_equivalence`` runs from the repository
    from test_prepass_golden import fingerprint
except ImportError:  # pragma: no cover
    from tests.test_prepass_golden import fingerprint

REPO = Path(__file__).resolve().parents[1]
GOLDEN = Path(__file__).parent / "fixtures" / "prepass_equivalence.json"


def _gre_with_dummies(n: int = 16, dummies: int = 6) -> bytes:
    """A small RF-spoiled 2D GRE (117 deg) whose first ``dummies`` repetitions play RF and gradients without ADC."""
    import pypulseq as pp

    from dtoc.seq.pulseq import quiet

    sys_ = pp.Opts(
        max_grad=32, grad_unit="mT/m", max_slew=130, slew_unit="T/m/s", rf_ringdown_time=30e-6,
        rf_dead_time=100e-6, adc_dead_time=10e-6,
    )  # fmt: skip
    seq = pp.Sequence(sys_)
    fov = 0.22
    dk = 1 / fov
    rf = pp.make_block_pulse(flip_angle=math.radians(15), duration=0.5e-3, system=sys_, delay=sys_.rf_dead_time)
    gx = pp.make_trapezoid("x", flat_area=n * dk, flat_time=1.6e-3, system=sys_)
    adc = pp.make_adc(n, duration=gx.flat_time, delay=gx.rise_time, system=sys_)
    gxpre = pp.make_trapezoid("x", area=-gx.area / 2, duration=1e-3, system=sys_)
    spoil = pp.make_trapezoid("x", area=2 * n * dk, system=sys_)
    phase, inc = 0.0, 0.0
    for i in range(-dummies, n):
        rf.phase_offset = adc.phase_offset = math.radians(phase)
        inc = (inc + 117) % 360
        phase = (phase + inc) % 360
        gy = pp.make_trapezoid("y", area=(max(i, 0) - n / 2) * dk, duration=1e-3, system=sys_)
        seq.add_block(rf)
        seq.add_block(gxpre, gy)
        seq.add_block(gx, adc) if i >= 0 else seq.add_block(gx)
        seq.add_block(spoil, pp.scale_grad(gy, -1))
    import os
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        p = os.path.join(d, "x.seq")
        with quiet():
            seq.write(p)
        return Path(p).read_bytes()


def _load_bytes(data: bytes, tmp: Path, name: str):
    p = tmp / f"{name}.seq"
    p.write_bytes(data)
    return load_sequence(p)


def _cases(tmp: Path):
    from foreign.writers import se_epi, tse

    default, fast = pdg.PDGConfig(), pdg.PDGConfig.fast()
    steady = pdg.PDGConfig(min_latent_signal=1e-6, min_emitted_signal=1e-6, min_magnitude=1e-7)
    irs = {
        "tse": _load_bytes(tse(n=32, etl=8), tmp, "tse"),
        "tse_single_shot": _load_bytes(tse(n=32, single_shot=True), tmp, "haste"),
        "gre_dummies": _load_bytes(_gre_with_dummies(), tmp, "gre_dummies"),
        "se_epi": _load_bytes(se_epi(n=32), tmp, "se_epi"),
        "epi_esp081": load_sequence(REPO / "sequences" / "epi_esp081.seq"),
    }
    for name, ir in irs.items():
        fov = tuple(ir.fov_m[:2])
        for maps in (True, False):
            ph = brain_phantom(32, fov_m=fov, b0=maps, b1=maps)
            for cname, cfg in (("default", default), ("fast", fast)):
                yield f"{name}/{cname}/maps={maps}", build_graph(ir, cfg, ph)
        ph = brain_phantom(32, fov_m=fov, b0=True, b1=True)
        yield f"{name}/steady", build_graph(ir, steady, ph, final_z_readout=True)
    # the Fig-5 GRE as the optimizer builds it: the phantom at the sequence's matrix and field, the main and the
    # loop presets, and a 50-cycle dummy train at the steady-state thresholds
    from dtoc.optimize.config import OptimizeConfig
    from dtoc.optimize.run import make_phantoms

    ir = load_sequence(REPO / "sequences" / "gre_paper_fig5.yaml")
    ph = make_phantoms(ir, OptimizeConfig())[0]
    yield "gre_fig5/default", build_graph(ir, default, ph)
    yield "gre_fig5/fast", build_graph(ir, fast, ph)
    train = dummy_train(ir, 50, None, detect_rf_spoiling(ir))
    yield "gre_fig5/dummies50", build_graph(train, steady, ph, final_z_readout=True)


def test_prepass_builds_the_recorded_graphs_of_more_sequences(tmp_path):
    pytest.importorskip("pypulseq")
    if not GOLDEN.exists():
        pytest.fail(f"{GOLDEN} missing: run python -m tests.test_prepass_equivalence")
    want = json.loads(GOLDEN.read_text())
    got = {key: fingerprint(g) for key, g in _cases(tmp_path)}
    assert sorted(got) == sorted(want)
    # graphs that exercise what the golden set lacks: refocused (conjugating) edges, many states
    assert want["tse/default/maps=True"]["states"] > 1000
    assert want["gre_fig5/dummies50"]["states"] > 10_000
    for key, fp in got.items():
        w = want[key]
        assert fp["states"] == w["states"], key
        assert fp["structure"] == w["structure"], f"{key}: graph structure changed"
        for name, vals in w["floats"].items():
            np.testing.assert_allclose(fp["floats"][name], vals, rtol=1e-12, atol=1e-300, err_msg=f"{key}: {name}")


if __name__ == "__main__":
    import sys
    import tempfile

    sys.path.insert(0, str(Path(__file__).parent))
    with tempfile.TemporaryDirectory() as d:
        fps = {key: fingerprint(g) for key, g in _cases(Path(d))}
    GOLDEN.write_text(json.dumps(fps, indent=1, sort_keys=True) + "\n")
    print(f"wrote {GOLDEN}: " + ", ".join(f"{k} {v['states']}" for k, v in fps.items()))
