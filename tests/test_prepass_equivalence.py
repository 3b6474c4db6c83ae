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
    from test_prepass_golden import assert_same_graphs, fingerprint
except ImportError:  # pragma: no cover
    from tests.test_prepass_golden import assert_same_graphs, fingerprint
from tests.numerics import golden_for, signature

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
    want = json.loads(golden_for(GOLDEN).read_text())  # (per kind of machine: tests/numerics.py)
    got = {key: fingerprint(g) for key, g in _cases(tmp_path)}
    assert sorted(got) == sorted(want)
    # graphs that exercise what the golden set lacks: refocused (conjugating) edges, many states
    assert want["tse/default/maps=True"]["states"] > 1000
    assert want["gre_fig5/dummies50"]["states"] > 10_000
    assert_same_graphs(got, want)


def test_nominal_integrals_are_pwl_integral_at_bit_for_bit():
    """The pre-pass integrates the demanded gradient in numpy: the same operations in the same order as
    dtoc.seq.kspace.pwl_integral_at (torch), so the same bits (the merge keys round these k values)."""
    import torch

    from dtoc.constants import GAMMA_RAD_PER_S_PER_MT
    from dtoc.seq.kspace import pwl_integral_at
    from dtoc.sim.pdg_graph import nominal_integrals

    for name in ("gre_paper", "epi_small"):
        ir = load_sequence(REPO / "sequences" / f"{name}.seq")
        t_rf = np.array([0.0] + [r.t_center_s for r in ir.rf] + [ir.duration_s, ir.duration_s + 1e-3, -1e-3])
        t_adc = np.sort(ir.adc_times_s)
        got = nominal_integrals(ir, t_rf, t_adc, np.zeros(0))
        for t, g in zip((t_rf, t_adc), got, strict=False):
            want = (GAMMA_RAD_PER_S_PER_MT * pwl_integral_at(torch.as_tensor(ir.grad_mT_per_m), ir.dt_fine_s, t)).T
            np.testing.assert_array_equal(g, want.numpy())
        assert got[2].shape == (0, 3)


def test_packed_keys_order_the_children_as_unique_rows():
    """The RF split merges children by packed parent keys: sorting them gives the same merged states, in the same
    order, with the same inverse as pdg_graph.unique_rows of the explicit (type, +-k, +-tau) rows -- with narrow
    columns (offset), wide ones (ranked) and an all-zero one; and it declines (None) when even ranks cannot fit."""
    from dtoc.sim.pdg_graph_step import packed_parent_keys
    from dtoc.sim.pdg_rows import unique_rows

    rng = np.random.default_rng(3)
    S = 500
    for widths in ((50, 50, 1, 50), (10**12, 7, 1, 10**15), (10**17, 10**17, 10**17, 10**17)):
        cols = [rng.integers(-w, w, S) if w > 1 else np.zeros(S, dtype=np.int64) for w in widths]
        cols[0][:20] = cols[0][20:40]  # coinciding parents, and their negatives
        cols[0][40:60] = -cols[0][20:40]
        same, conj, zkey, span = packed_parent_keys(cols)
        K = np.stack(cols, axis=1)
        rows = np.concatenate(
            [np.c_[np.zeros(S, np.int64), K], np.c_[np.zeros(S, np.int64), -K], np.c_[np.ones(S, np.int64), K]]
        )
        rows = np.concatenate([rows, [[1, 0, 0, 0, 0]]])
        keys = np.concatenate([same, conj, same + span, [zkey + span]])
        want_rows, want_inv = unique_rows(rows)
        u, inv = np.unique(keys, return_inverse=True)
        np.testing.assert_array_equal(inv.reshape(-1), want_inv.reshape(-1))
        assert u.size == want_rows.shape[0] and keys.max() < 2**62
    wide = [rng.integers(-(10**17), 10**17, 40_000) for _ in range(4)]
    assert packed_parent_keys(wide) is None


def test_split_without_packed_keys_builds_the_same_graph(monkeypatch):
    """The fallback of the RF split (explicit key rows through unique_rows, used when the packed keys cannot fit)
    builds the same graph as the packed keys."""
    import dtoc.sim.pdg_graph_step as step

    ir = load_sequence(REPO / "sequences" / "gre_small.seq")
    ph = brain_phantom(32, fov_m=tuple(ir.fov_m[:2]), b0=True, b1=True)
    with step.prepass_backend("numpy"):  # the numpy formulation's fallback (the compiled core has its own)
        want = build_graph(ir, pdg.PDGConfig(), ph)
        monkeypatch.setattr(step, "packed_parent_keys", lambda cols: None)
        got = build_graph(ir, pdg.PDGConfig(), ph)
    assert got.n_states_total == want.n_states_total > 500
    for a, b in zip(got.intervals, want.intervals, strict=True):
        for name, v in vars(b).items():
            np.testing.assert_array_equal(getattr(a, name), v, err_msg=name)


def test_emission_bound_is_never_below_the_exact_emission(monkeypatch):
    """The pre-pass skips the exact emission of a state when an upper bound of it can change neither the state's
    latent bound nor its emitter decision; that bound is never below the exact value (every transverse state of
    every interval, box and sinc voxels, with and without B0/T2' and spectrum), and it does skip states."""
    from dtoc.sim import pdg_graph

    seen = {"states": 0, "tight": 0, "skipped": 0}
    of = pdg_graph._Emission.of

    def checked(self, n, best):
        R = self.raw[n]
        tr = np.flatnonzero(~R["is_z"])
        if self.adc_hi[n] > self.adc_lo[n] and tr.size:
            ub, ex = self.bound(n, tr), self.exact(n, tr)
            assert np.all(ub >= ex), (n, float((ex - ub).max()))
            seen["states"] += tr.size
            seen["tight"] += int((ub < 0.5).sum())
            if best is not None:
                seen["skipped"] += int(((ub <= best[tr]) & (R["mag"][tr] * ub < self.min_emitted)).sum())
        return of(self, n, best)

    monkeypatch.setattr(pdg_graph._Emission, "of", checked)
    for name in ("gre_small", "epi_small"):
        ir = load_sequence(REPO / "sequences" / f"{name}.seq")
        for maps, shape in ((True, "box"), (False, "box"), (True, "sinc")):
            ph = brain_phantom(32, fov_m=tuple(ir.fov_m[:2]), b0=maps, b1=maps)
            ph.voxel_shape = shape
            build_graph(ir, pdg.PDGConfig(), ph)
    assert seen["states"] > 5000 and seen["tight"] > 1000 and seen["skipped"] > 1000, seen


def test_add_rows_by_index_is_add_at_bit_for_bit():
    """The children's amplitude sums: one bincount over interleaved real/imaginary parts adds in edge order from
    zero, as np.add.at does (values of very different magnitudes, so a different order would round differently)."""
    from dtoc.sim.pdg_rows import add_rows_by_index

    rng = np.random.default_rng(5)
    E, P, n = 4000, 3, 700
    idx = rng.integers(0, n, E)
    rows = (rng.standard_normal((E, P)) + 1j * rng.standard_normal((E, P))) * 10.0 ** rng.integers(-12, 6, (E, 1))
    want = np.zeros((n, P), dtype=np.complex128)
    np.add.at(want, idx, rows)
    got = add_rows_by_index(idx, rows, n)
    assert np.array_equal(got.view(np.float64), want.view(np.float64))


if __name__ == "__main__":
    import sys
    import tempfile

    sys.path.insert(0, str(Path(__file__).parent))
    with tempfile.TemporaryDirectory() as d:
        fps = {key: fingerprint(g) for key, g in _cases(Path(d))}
    out = GOLDEN.with_name(f"{GOLDEN.stem}.{signature()}.json") if "--this-machine" in sys.argv else GOLDEN
    out.write_text(json.dumps(fps, indent=1, sort_keys=True) + "\n")  # --this-machine: tests/numerics.py
    print(f"wrote {out}: " + ", ".join(f"{k} {v['states']}" for k, v in fps.items()))
