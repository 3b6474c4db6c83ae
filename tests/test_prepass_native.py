"""The compiled core of the PDG pre-pass (``dtoc/sim/_pdg_split.c``, built at install where a C compiler is there)
builds the same graph as the numpy formulation, bit for bit: every array of every interval (states, k, tau,
amplitude bounds, edges, representatives, emitters) with the same dtype, shape and bytes, on sequences and phantoms
that take each of its branches -- box, sinc and 'none' voxels, 2D and 3D spectra, with and without B0/T2' (merged
regardless of tau), conjugating edges (TSE), the max_states cap, 'pd' probe weighting, the calibrated emitters and
the steady-state dummy train (final longitudinal states observed).

Without the extension (a machine with no compiler) the comparisons are skipped and the numpy formulation is what
every other pre-pass test checks (tests/test_prepass_golden.py, tests/test_prepass_equivalence.py).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from dtoc.seq.load import load_sequence
from dtoc.sim import pdg
from dtoc.sim.pdg_dummies import detect_rf_spoiling, dummy_train
from dtoc.sim.pdg_graph import build_graph
from dtoc.sim.pdg_graph_step import native_available, native_in_use, prepass_backend
from dtoc.sim.phantom import brain_phantom, brain_phantom_3d

REPO = Path(__file__).resolve().parents[1]
needs_native = pytest.mark.skipif(
    not native_available(), reason="the compiled pre-pass core was not built at install: the numpy formulation runs"
)


def _assert_identical(got, want, key: str) -> None:
    """Every attribute of the two graphs (and of each interval) equal: arrays by dtype, shape and bytes."""

    def same(a, b, name):
        if isinstance(b, np.ndarray):
            assert isinstance(a, np.ndarray) and a.dtype == b.dtype and a.shape == b.shape, f"{key}: {name}"
            assert np.ascontiguousarray(a).tobytes() == np.ascontiguousarray(b).tobytes(), f"{key}: {name} differs"
        elif name != "config":
            assert a == b, f"{key}: {name}"

    assert len(got.intervals) == len(want.intervals), key
    for n, (a, b) in enumerate(zip(got.intervals, want.intervals, strict=True)):
        for name, v in vars(b).items():
            same(getattr(a, name), v, f"interval {n} {name}")
    for name, v in vars(want).items():
        if name != "intervals":
            same(getattr(got, name), v, name)


def _both(key: str, build) -> int:
    with prepass_backend("numpy"):
        assert not native_in_use()
        want = build()
    with prepass_backend("native"):
        assert native_in_use()
        got = build()
    _assert_identical(got, want, key)
    return want.n_states_total


def _no_tau(ph):
    """The phantom without B0 and T2': the pre-pass merges states regardless of tau."""
    ph.b0_hz = np.zeros_like(ph.b0_hz)
    ph.t2dash_s = np.full_like(ph.t2dash_s, np.inf)
    return ph


@needs_native
def test_native_and_numpy_build_the_same_graphs_2d():
    states = {}
    for name in ("gre_small", "epi_small"):
        ir = load_sequence(REPO / "sequences" / f"{name}.seq")
        fov = tuple(ir.fov_m[:2])
        for label, ph in (
            ("maps", brain_phantom(32, fov_m=fov, b0=True, b1=True)),
            ("plain", brain_phantom(32, fov_m=fov)),
            ("no_tau", _no_tau(brain_phantom(32, fov_m=fov))),
        ):
            for cname, cfg in (("default", pdg.PDGConfig()), ("strict", pdg.PDGConfig.strict())):
                key = f"{name}/{label}/{cname}"
                states[key] = _both(key, lambda ir=ir, cfg=cfg, ph=ph: build_graph(ir, cfg, ph))
        for shape in ("sinc", "none"):
            ph = brain_phantom(32, fov_m=fov, b0=True, b1=True)
            ph.voxel_shape = shape
            key = f"{name}/{shape}"
            states[key] = _both(key, lambda ir=ir, ph=ph: build_graph(ir, pdg.PDGConfig(), ph))
        ph = brain_phantom(32, fov_m=fov, b0=True, b1=True)
        for key, cfg in (
            (f"{name}/pd_probes", pdg.PDGConfig(probe_weighting="pd")),
            (f"{name}/no_spectrum", pdg.PDGConfig(object_spectrum=False)),
            (f"{name}/cap64", pdg.PDGConfig(max_states=64)),
        ):
            states[key] = _both(key, lambda ir=ir, cfg=cfg, ph=ph: build_graph(ir, cfg, ph))
        states[f"{name}/steady"] = _both(
            f"{name}/steady", lambda ir=ir, ph=ph: build_graph(ir, pdg.PDGConfig(), ph, final_z_readout=True)
        )
        states[f"{name}/no_phantom"] = _both(f"{name}/no_phantom", lambda ir=ir: build_graph(ir, pdg.PDGConfig()))
    assert states["gre_small/maps/strict"] > 2000  # real graphs, not trivial ones
    assert states["gre_small/cap64"] < states["gre_small/maps/default"]  # the cap bit


@needs_native
def test_native_and_numpy_build_the_same_graphs_calibrated_and_dummies():
    ir = load_sequence(REPO / "sequences" / "gre_small.seq")
    ph = brain_phantom(32, fov_m=tuple(ir.fov_m[:2]), b0=True, b1=True)
    cal = pdg.PDGConfig(
        min_emitted_signal=3e-4, min_latent_signal=1e-4, min_magnitude=1e-5, calibrate_emission=True, taylor_tol=3e-5
    )
    assert _both("calibrated", lambda: pdg.build_graph(ir, cal, ph)) > 300
    gre = load_sequence(REPO / "sequences" / "gre_paper.seq")
    train = dummy_train(gre, 40, None, detect_rf_spoiling(gre))
    steady = pdg.PDGConfig(min_latent_signal=1e-6, min_emitted_signal=1e-6, min_magnitude=1e-7, max_states=1500)
    ph32 = brain_phantom(32, fov_m=tuple(gre.fov_m[:2]))
    assert _both("dummies40", lambda: build_graph(train, steady, ph32, final_z_readout=True)) > 20_000


@needs_native
def test_native_and_numpy_build_the_same_graphs_tse_and_3d(tmp_path):
    pytest.importorskip("pypulseq")
    from foreign.writers import gre3d, tse

    p = tmp_path / "tse.seq"
    p.write_bytes(tse(n=32, etl=8))
    ir = load_sequence(p)
    ph = brain_phantom(32, fov_m=tuple(ir.fov_m[:2]), b0=True, b1=True)
    assert _both("tse", lambda: build_graph(ir, pdg.PDGConfig(), ph)) > 1000
    p = tmp_path / "gre3d.seq"
    p.write_bytes(gre3d(n=8, nz=4, fov=0.2, fovz=0.06))
    ir3 = load_sequence(p)
    for shape in ("box", "sinc"):
        ph3 = brain_phantom_3d((8, 8, 4), (0.2, 0.2, 0.06))
        ph3.voxel_shape = shape
        assert _both(f"gre3d/{shape}", lambda ph3=ph3: build_graph(ir3, pdg.PDGConfig(), ph3)) > 100


@needs_native
def test_native_and_numpy_build_the_same_graphs_in_chunks(monkeypatch):
    """The emission bound evaluated a few states at a time (as for long readouts x many states): the same graph as
    in one piece, from both formulations."""
    from dtoc.sim import pdg_graph

    ir = load_sequence(REPO / "sequences" / "gre_small.seq")
    ph = brain_phantom(32, fov_m=tuple(ir.fov_m[:2]), b0=True, b1=True)
    with prepass_backend("numpy"):
        whole = build_graph(ir, pdg.PDGConfig(), ph)
    monkeypatch.setattr(pdg_graph, "EXACT_CHUNK_ELEMS", 5 * 64)  # a few states per piece
    _both("chunks", lambda: build_graph(ir, pdg.PDGConfig(), ph))
    with prepass_backend("native"):
        _assert_identical(build_graph(ir, pdg.PDGConfig(), ph), whole, "chunks vs whole")


def test_prepass_backend_switch():
    """The numpy formulation can always be chosen; the compiled one only where it was built; the default is the
    compiled one where it was built (unless DTOC_PREPASS_NATIVE=0)."""
    with pytest.raises(ValueError, match="expected 'numpy' or 'native'"):
        with prepass_backend("fortran"):
            pass
    with prepass_backend("numpy"):
        assert not native_in_use()
    if os.environ.get("DTOC_PREPASS_NATIVE", "1") != "0":
        assert native_in_use() == native_available()
    if not native_available():
        with pytest.raises(ValueError, match="not built"):
            with prepass_backend("native"):
                pass
