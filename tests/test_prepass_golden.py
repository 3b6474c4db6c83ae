"""The PDG pre-pass builds the same graph as the commit that recorded ``fixtures/prepass_golden.json``.

Speed work on :func:`dtoc.sim.pdg_graph.build_graph` must not change the graph: every integer array (states,
edges, representative parents, emitters, ADC slices) must be identical, bit for bit, and every float array
(nominal k, tau, amplitude bounds) equal to 1e-12 relative (its bits depend on the numpy build's exp/sin, which
may differ between machines; on the machine that recorded the file they were identical too, see
docs/benchmarks.md "PDG pre-pass").  Five sequences x four configurations (fast, default, strict, calibrated),
with and without B0/B1 maps, the steady-state variant (final longitudinal states observed) and the paper GRE's
300-cycle dummy train.

Regenerate (only for an intended change of the graph): ``python -m tests.test_prepass_golden``.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest

from dtoc.seq.load import load_sequence
from dtoc.sim import pdg
from dtoc.sim.pdg_dummies import detect_rf_spoiling, dummy_train
from dtoc.sim.pdg_graph import build_graph
from dtoc.sim.phantom import brain_phantom
from tests.numerics import golden_for, signature

REPO = Path(__file__).resolve().parents[1]
GOLDEN = Path(__file__).parent / "fixtures" / "prepass_golden.json"
SEQUENCES = ("gre_paper", "gre_paper_r100us", "gre_paper_fig5", "gre_small", "epi_small")
CONFIGS = {
    "fast": pdg.PDGConfig.fast(),
    "default": pdg.PDGConfig(),
    "strict": pdg.PDGConfig.strict(),
    "calibrated": pdg.PDGConfig(
        min_emitted_signal=3e-4, min_latent_signal=1e-4, min_magnitude=1e-5, calibrate_emission=True, taylor_tol=3e-5
    ),
}


def fingerprint(graph) -> dict:
    """sha256 of the graph's integer structure, and each float array as two sums over the
    intervals: of |x| and of x * (index + 1) * (interval + 1)."""
    h = hashlib.sha256()
    floats: dict[str, list[float]] = {}
    for n, iv in enumerate(graph.intervals):
        for name in sorted(vars(iv)):
            v = getattr(iv, name)
            if isinstance(v, np.ndarray) and v.dtype.kind == "f":
                w = np.arange(1, v.size + 1, dtype=np.float64).reshape(v.shape) * (n + 1)
                acc = floats.setdefault(name, [0.0, 0.0])
                acc[0] += float(np.abs(v).sum())
                acc[1] += float((v * w).sum())
            elif isinstance(v, np.ndarray):
                h.update(name.encode())
                h.update(np.ascontiguousarray(v.astype(np.int64)).tobytes())
            else:
                h.update(f"{name}={v!r}".encode())
    return {"structure": h.hexdigest(), "floats": floats, "states": graph.n_states_total}


def assert_same_graphs(got: dict, want: dict) -> None:
    """Each fingerprint of ``got`` equals the recorded one of ``want`` (same keys): states and integer structure
    bit for bit, every float sum to 1e-12 relative."""
    for key, fp in got.items():
        w = want[key]
        assert fp["states"] == w["states"], key
        assert fp["structure"] == w["structure"], f"{key}: graph structure changed"
        for name, vals in w["floats"].items():
            np.testing.assert_allclose(fp["floats"][name], vals, rtol=1e-12, atol=1e-300, err_msg=f"{key}: {name}")


def _cases():
    for name in SEQUENCES:
        ir = load_sequence(REPO / "sequences" / f"{name}.seq")
        fov = tuple(ir.fov_m[:2])
        for maps in (True, False):
            ph = brain_phantom(32, fov_m=fov, b0=maps, b1=maps)
            for cname, cfg in CONFIGS.items():
                yield f"{name}/{cname}/maps={maps}", pdg.build_graph(ir, cfg, ph)
        ph = brain_phantom(32, fov_m=fov, b0=True, b1=True)
        yield f"{name}/default/steady", build_graph(ir, CONFIGS["default"], ph, final_z_readout=True)
    # the paper GRE's 300-cycle dummy train at the steady-state thresholds (~2e5 states, max_states truncation)
    ir = load_sequence(REPO / "sequences" / "gre_paper.seq")
    train = dummy_train(ir, 300, None, detect_rf_spoiling(ir))
    cfg = pdg.PDGConfig(min_latent_signal=1e-6, min_emitted_signal=1e-6, min_magnitude=1e-7)
    yield (
        "gre_paper/dummies300",
        build_graph(train, cfg, brain_phantom(32, fov_m=tuple(ir.fov_m[:2])), final_z_readout=True),
    )


def test_prepass_builds_the_recorded_graphs():
    if not GOLDEN.exists():
        pytest.fail(f"{GOLDEN} missing: run python -m tests.test_prepass_golden")
    want = json.loads(golden_for(GOLDEN).read_text())  # (per kind of machine: tests/numerics.py)
    got = {key: fingerprint(g) for key, g in _cases()}
    assert sorted(got) == sorted(want)
    assert sum(w["states"] for w in want.values()) > 50_000  # graphs of real size, not trivial ones
    assert_same_graphs(got, want)


if __name__ == "__main__":  # --this-machine: the golden of this kind of machine (tests/numerics.py)
    import sys

    out = GOLDEN.with_name(f"{GOLDEN.stem}.{signature()}.json") if "--this-machine" in sys.argv else GOLDEN
    out.write_text(json.dumps({key: fingerprint(g) for key, g in _cases()}, indent=1, sort_keys=True) + "\n")
    print(f"wrote {out}")
