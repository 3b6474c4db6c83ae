"""The fast main-pass paths equal the generic-autograd, per-interval reference (no timing here).

* :mod:`dtoc.sim.pdg_evolve`: amplitude propagation as one autograd node with a hand-written adjoint
  (diffusion makes the amplitudes depend on the gradient waveform, so its adjoint is exercised);
* :mod:`dtoc.sim.pdg_signal_batch`: the 'gemm' signal batched over intervals (separable spatial
  phases, per-tau factors, cached time factors, Taylor orders as row prefixes, T2' sign classes);

against ``pdg_reference.main_loop_autograd`` (generic autograd, one interval at a time, the path these replace).
Tolerances: float64 signal 1e-10 and gradient 1e-9 relative to their maxima (rounding only: the
same terms summed in another order); float32 1e-5 of the maximum.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from test_sim_physics import rich_phantom, se_epi_like, small_gre

import dtoc.sim.pdg_main as M
from dtoc.sim.pdg import PDGConfig, build_graph, simulate
from dtoc.sim.pdg_reference import main_loop_autograd


def _signal_and_grad(ir, ph, graph, cfg, dtype=torch.float64):
    g = torch.as_tensor(ir.grad_mT_per_m, dtype=dtype).clone().requires_grad_(True)
    s = simulate(ir, ph, g, graph=graph, config=cfg, dtype=dtype)
    (s.real**2 + s.imag**2).sum().backward()
    return s.detach().numpy(), g.grad.numpy()


@pytest.mark.parametrize("seq,d_scale,coils", [("gre", 1.0, False), ("gre", 1e4, True), ("se", 1e2, True)])
def test_fast_paths_equal_generic_autograd(seq, d_scale, coils, monkeypatch):
    """Signal and gradient w.r.t. every gradient sample: fast paths == reference (B0, T2', B1, D, coils,
    tau crossing zero in the ADC, strong diffusion with per-state exact fallback), also with the
    recomputing adjoint (checkpoint_bytes 0)."""
    ir = small_gre(n_rep=4) if seq == "gre" else se_epi_like()
    ph = rich_phantom()
    ph.d_m2_per_s = ph.d_m2_per_s * d_scale
    if coils:
        ph.coil_sens = np.stack([np.ones((4, 4)), np.exp(1j * np.arange(16).reshape(4, 4) / 3.0)])
    cfg = PDGConfig(signal_method="gemm")
    graph = build_graph(ir, cfg, ph)
    s_new, g_new = _signal_and_grad(ir, ph, graph, cfg)
    s_rc, g_rc = _signal_and_grad(ir, ph, graph, PDGConfig(signal_method="gemm", checkpoint_bytes=0))
    monkeypatch.setattr(M, "main_loop", main_loop_autograd)
    s_ref, g_ref = _signal_and_grad(ir, ph, graph, cfg)
    assert np.abs(g_ref).max() > 0
    assert np.abs(s_new - s_ref).max() < 1e-10 * np.abs(s_ref).max()
    assert np.abs(g_new - g_ref).max() < 1e-9 * np.abs(g_ref).max()
    assert np.abs(g_rc - g_ref).max() < 1e-9 * np.abs(g_ref).max()


def test_fast_paths_float32_and_paper_gre(monkeypatch):
    """float32 fast paths against the float64 reference (1e-5 of the maximum) on the paper's GRE
    (32 TRs, RF spoiling, brain phantom 8x8 with B0/B1 maps: ~50 states per interval, equal ADC
    timing in every TR, so the cached time factors are reused)."""
    from pathlib import Path

    from dtoc.seq.load import load_sequence
    from dtoc.sim.phantom import brain_phantom

    seq = Path(__file__).resolve().parents[1] / "sequences" / "gre_paper_r100us.seq"
    if not seq.exists():
        pytest.skip("sequences/gre_paper_r100us.seq not present")
    ir = load_sequence(seq)
    ph = brain_phantom(8, fov_m=ir.fov_m[0], b0=True, b1=True)
    cfg = PDGConfig(min_latent_signal=3e-4, min_emitted_signal=3e-4, min_magnitude=3e-5)
    graph = build_graph(ir, cfg, ph)
    s32, g32 = _signal_and_grad(ir, ph, graph, cfg, torch.float32)
    s64, g64 = _signal_and_grad(ir, ph, graph, cfg)
    monkeypatch.setattr(M, "main_loop", main_loop_autograd)
    s_ref, g_ref = _signal_and_grad(ir, ph, graph, cfg)
    assert np.abs(s64 - s_ref).max() < 1e-10 * np.abs(s_ref).max()
    assert np.abs(g64 - g_ref).max() < 1e-9 * np.abs(g_ref).max()
    assert np.abs(s32 - s_ref).max() < 1e-5 * np.abs(s_ref).max()
    assert np.abs(g32 - g_ref).max() < 1e-3 * np.abs(g_ref).max()


def test_separable_spatial_phase_and_vectorised_taylor_orders():
    """VoxelData.spatial_phase (per-axis factors on the voxel grid) equals exp(-i (kx x + ky y)) per
    voxel (1e-12, float64, k up to 1e5 rad/m); the vectorised Taylor orders equal the scalar rule."""
    from dtoc.sim.pdg_signal import VoxelData, taylor_order
    from dtoc.sim.pdg_signal_batch import taylor_orders

    ph = rich_phantom(n=6)
    vox = VoxelData.from_phantom(ph, None, torch.float64, "cpu", PDGConfig())
    rng = np.random.default_rng(3)
    kx = torch.as_tensor(rng.uniform(-1e5, 1e5, (3, 5)))
    ky = torch.as_tensor(rng.uniform(-1e5, 1e5, (3, 5)))
    direct = torch.exp(-1j * (kx[..., None] * vox.x + ky[..., None] * vox.y))
    assert (vox.spatial_phase(kx, ky) - direct).abs().max() < 1e-12
    # its hand-written adjoint equals autograd of the direct formula (loss mixing real and imaginary parts)
    W = torch.as_tensor(rng.normal(size=direct.shape) + 1j * rng.normal(size=direct.shape))
    grads = []
    for f in (
        lambda a, b: vox.spatial_phase(a, b),
        lambda a, b: torch.exp(-1j * (a[..., None] * vox.x + b[..., None] * vox.y)),
    ):
        a, b = kx.clone().requires_grad_(True), ky.clone().requires_grad_(True)
        ((f(a, b) * W).real.sum() + (f(a, b) * W).imag.sum() ** 2 * 1e-3).backward()
        grads.append((a.grad, b.grad))
    for u, w in zip(grads[0], grads[1]):
        assert torch.allclose(u, w, rtol=1e-9, atol=1e-9 * float(w.abs().max()))
    x = np.concatenate([[0.0, 1e-12, 1e-9], np.logspace(-10, 0.5, 300)])
    for tol in (1e-9, 1e-6):
        assert np.array_equal(taylor_orders(x, tol), [taylor_order(float(v), tol) for v in x])


def test_tissue_compression_is_exact():
    """Propagating amplitudes per distinct (T1, T2, D, B1, Mz0/PD) tuple equals per-voxel propagation:
    signal (1e-10) and gradient (1e-9) in float64 with a steady-state initial Mz (ratio varies per
    tissue) and a partial-volume brain phantom (fewer tuples than voxels); steady_state_mz too."""
    from dtoc.sim.pdg import steady_state_mz
    from dtoc.sim.pdg_main import TissueClasses
    from dtoc.sim.pdg_signal import VoxelData
    from dtoc.sim.phantom import brain_phantom

    ir = small_gre(n_rep=4, n=4, fov=0.032)
    ph = brain_phantom(12, fov_m=0.032, b0=True)
    vox = VoxelData.from_phantom(ph, None, torch.float64, "cpu", PDGConfig())
    assert 1 < TissueClasses(vox, True).n < vox.n  # the compression does something here
    res = []
    for comp in (True, False):
        cfg = PDGConfig(compress_tissues=comp)
        mz0 = steady_state_mz(
            ir,
            ph,
            5,
            config=PDGConfig(
                compress_tissues=comp, min_latent_signal=1e-6, min_emitted_signal=1e-6, min_magnitude=1e-7
            ),
        )
        g = torch.as_tensor(ir.grad_mT_per_m).clone().requires_grad_(True)
        s = simulate(ir, ph, g, config=cfg, initial_mz=mz0)
        (s.real**2 + s.imag**2).sum().backward()
        res.append((mz0.numpy(), s.detach().numpy(), g.grad.numpy()))
    (m1, s1, g1), (m0, s0, g0) = res
    assert np.abs(m1 - m0).max() < 1e-12 * np.abs(m0).max()
    assert np.abs(s1 - s0).max() < 1e-10 * np.abs(s0).max()
    assert np.abs(g1 - g0).max() < 1e-9 * np.abs(g0).max()


@pytest.mark.parametrize("fused", [True, False])
def test_tissue_compression_with_strong_diffusion_fallback(fused, monkeypatch):
    """Regression: the exact per-state path of strongly dephased states (D |db| > 0.5 in the window) must
    receive voxel amplitudes, not tissue-tuple rows, when the tissue compression is on (it crashed on a
    128x128 brain phantom).  Compressed == per-voxel, float64, signal 1e-10 and gradient 1e-9."""
    import dtoc.sim.pdg_signal_batch as SB
    from dtoc.sim.pdg_main import TissueClasses
    from dtoc.sim.pdg_signal import VoxelData
    from dtoc.sim.phantom import brain_phantom

    ir = small_gre(n_rep=4, n=4, fov=0.032)
    ph = brain_phantom(12, fov_m=0.032, b0=True)
    ph.d_m2_per_s = ph.d_m2_per_s * 1e4  # strongly dephased pathways take the exact per-state path
    vox = VoxelData.from_phantom(ph, None, torch.float64, "cpu", PDGConfig())
    assert 1 < TissueClasses(vox, True).n < vox.n
    calls = []
    orig = SB._sig.emit_signal_direct
    monkeypatch.setattr(SB._sig, "emit_signal_direct", lambda *a, **k: calls.append(1) or orig(*a, **k))
    res = []
    for comp in (True, False):
        cfg = PDGConfig(compress_tissues=comp, fused_signal_adjoint=fused)
        g = torch.as_tensor(ir.grad_mT_per_m).clone().requires_grad_(True)
        s = simulate(ir, ph, g, config=cfg)
        (s.real**2 + s.imag**2).sum().backward()
        res.append((s.detach().numpy(), g.grad.numpy()))
    assert calls  # the fallback ran
    (s1, g1), (s0, g0) = res
    assert np.abs(s1 - s0).max() < 1e-10 * np.abs(s0).max()
    assert np.abs(g1 - g0).max() < 1e-9 * np.abs(g0).max()


def test_unrolled_k_paths_equal_recursion(monkeypatch):
    """The k of every state from the unrolled path matrix (one product for all intervals) equals the
    interval-by-interval recursion (used above _K_PATH_MAX_ELEMS): signal 1e-12, gradient 1e-10."""
    ir = small_gre(n_rep=4)
    ph = rich_phantom()
    graph = build_graph(ir, PDGConfig(), ph)
    s_mat, g_mat = _signal_and_grad(ir, ph, graph, PDGConfig())
    assert graph._torch_cache.get("kpath") is not None
    graph._torch_cache.pop("kpath")
    monkeypatch.setattr(M, "_K_PATH_MAX_ELEMS", 0)
    s_rec, g_rec = _signal_and_grad(ir, ph, graph, PDGConfig())
    assert graph._torch_cache["kpath"] is None
    assert np.abs(s_mat - s_rec).max() < 1e-12 * np.abs(s_rec).max()
    assert np.abs(g_mat - g_rec).max() < 1e-10 * np.abs(g_rec).max()


@pytest.mark.parametrize(
    "seq,d_scale,coils", [("gre", 1.0, False), ("gre", 1e4, True), ("se", 1e2, True), ("se", 1.0, False)]
)
def test_fused_signal_adjoint_equals_generic_chain(seq, d_scale, coils, monkeypatch):
    """The batched signal's hand-written adjoint (PDGConfig.fused_signal_adjoint, one autograd node)
    equals the generic autograd chain of the same batched evaluation: float64 signal 1e-10 and
    gradient 1e-9 of their maxima, with B0, T2' (states whose tau changes sign inside the ADC window:
    both kernel signs), Taylor orders >= 1 of the in-window diffusion, strong diffusion (exact per-state
    fallback), two coils, and the memory-saving (recomputing) propagation; the plan must really
    contain those features (else the comparison would not test them)."""
    import dtoc.sim.pdg_signal_batch as B

    ir = small_gre(n_rep=4) if seq == "gre" else se_epi_like()
    ph = rich_phantom()
    ph.d_m2_per_s = ph.d_m2_per_s * d_scale
    if coils:
        ph.coil_sens = np.stack([np.ones((4, 4)), np.exp(1j * np.arange(16).reshape(4, 4) / 3.0)])
    cfg = PDGConfig(signal_method="gemm", fused_signal_adjoint=False)
    graph = build_graph(ir, cfg, ph)
    seen = {"signs": set(), "order": 0, "masked": False}
    apply = B._BatchedGemm.apply

    def spy(*args):
        plan = args[-1]
        for st in plan.steps:
            seen["signs"].add(st.sgn)
            seen["order"] = max(seen["order"], len(st.orders) - 1)
            seen["masked"] |= st.orders[0].mask is not None
        return apply(*args)

    monkeypatch.setattr(B._BatchedGemm, "apply", spy)
    s_ref, g_ref = _signal_and_grad(ir, ph, graph, cfg)
    for extra in (dict(), dict(checkpoint_bytes=0)):
        s_new, g_new = _signal_and_grad(
            ir, ph, graph, PDGConfig(signal_method="gemm", fused_signal_adjoint=True, **extra)
        )
        assert np.abs(g_ref).max() > 0
        assert np.abs(s_new - s_ref).max() < 1e-10 * np.abs(s_ref).max()
        assert np.abs(g_new - g_ref).max() < 1e-9 * np.abs(g_ref).max()
    assert seen["signs"] == {1.0, -1.0}  # T2' present: both kernel signs
    if d_scale > 1:
        assert seen["order"] >= 1  # Taylor terms of the in-window diffusion
    if seq == "se":
        assert seen["masked"]  # tau crosses zero inside the ADC window (class 2)


@pytest.mark.parametrize("diffusion,with_b0", [(False, False), (False, True), (True, False), (True, True)])
def test_fused_moments_adjoint_equals_generic_autograd(diffusion, with_b0):
    """pdg_moments: the hand-written adjoint of the exact PWL moments (I, and J1, J2 with diffusion)
    equals generic autograd of the reference formulas (fused=False), float64: values 1e-12 and
    gradient w.r.t. every gradient and B0 sample 1e-9 relative to the maximum.  Query times include
    t = 0, the last sample, a time past the end (clamped), duplicates and exact grid points; the
    loss is linear plus quadratic in every output so each cotangent is a distinct non-constant."""
    from dtoc.sim.pdg_moments import compute_moments

    rng = np.random.default_rng(3)
    M, dt = 1201, 5e-6
    T = (M - 1) * dt
    bound_t = np.sort(np.r_[0.0, rng.uniform(0, T, 15), 40 * dt, T, T + 3 * dt])
    adc_t = np.sort(np.r_[rng.uniform(0, T, 40), 7 * dt, 7 * dt, 0.5 * dt, T - 0.5 * dt])
    g = torch.tensor(rng.standard_normal((3, M)) * 20.0, dtype=torch.float64, requires_grad=True)
    b0 = torch.tensor(rng.standard_normal(M), dtype=torch.float64, requires_grad=True) if with_b0 else None
    inputs = [g] + ([b0] if with_b0 else [])
    weights = None
    res = []
    for fused in (False, True):
        mom = compute_moments(g, b0, dt, bound_t, adc_t, diffusion, fused=fused)
        outs = [mom.I_bound, mom.I_adc]
        if diffusion:
            outs += [mom.J1_bound, mom.J1_adc, mom.J2_bound, mom.J2_adc]
        if weights is None:
            weights = [torch.as_tensor(rng.standard_normal(tuple(o.shape))) for o in outs]
        scale = [1.0 / float(o.detach().abs().max()) for o in outs]
        loss = sum((o * w).sum() * s + ((o * s) ** 2).sum() for o, w, s in zip(outs, weights, scale))
        grads = torch.autograd.grad(loss, inputs)
        res.append(([o.detach() for o in outs], grads))
    for a, b in zip(res[0][0], res[1][0]):
        assert float((a - b).abs().max()) <= 1e-12 * float(a.abs().max())
    for a, b in zip(res[0][1], res[1][1]):
        assert float(a.abs().max()) > 0.0
        assert float((a - b).abs().max()) <= 1e-9 * float(a.abs().max())


def test_rf_coefficients_cached_per_flip_equal_direct():
    """rf_coefficients with a cache (trigonometry per flip, phase factors per pulse) equals the direct
    evaluation (float64, 1e-15) for several phases sharing one cached flip, and different flips do not
    share a cache entry."""
    b1 = torch.linspace(0.6, 1.3, 17, dtype=torch.float64)
    cache: dict = {}
    for flip in (0.3, 1.2):
        for phase in (0.0, 0.7, -2.9, 117.0 * np.pi / 180.0 * 6):
            a = M.rf_coefficients(flip, phase, b1, torch.complex128)
            b = M.rf_coefficients(flip, phase, b1, torch.complex128, cache)
            assert float((a - b).abs().max()) <= 1e-15
    assert sum(1 for k in cache if isinstance(k, tuple) and k[0] == "rf_base") == 2


@pytest.mark.parametrize("cdtype", [torch.complex64, torch.complex128])
def test_add_rows_equals_complex_index_add(cdtype):
    """pdg_rfsplit.add_rows_ / take_rows (complex row scatter-add / gather through the real view) give
    exactly torch's complex index_add_ / index_select (repeated indices, a conjugate-view source, a
    non-contiguous target, a 3-d source)."""
    from dtoc.sim.pdg_rfsplit import add_rows_, take_rows

    g = torch.Generator().manual_seed(0)
    src = torch.randn(40, 7, dtype=cdtype, generator=g)
    idx = torch.randint(0, 9, (40,), generator=g)
    for s in (src, src.conj()):
        base = torch.randn(9, 7, dtype=cdtype, generator=g)
        ref = base.clone().index_add_(0, idx, s)
        out = add_rows_(base.clone(), idx, s)
        assert torch.equal(out, ref)
        nc = base.clone().T.contiguous().T  # non-contiguous target: generic fallback
        assert torch.equal(add_rows_(nc, idx, s), ref)
    for X in (src, src.conj(), src.reshape(40, 7, 1).expand(40, 7, 3).contiguous()):
        got = take_rows(X, idx[:25] % 40)
        assert torch.equal(got, X.index_select(0, idx[:25] % 40)) and got.shape == (25,) + tuple(X.shape[1:])


def test_unique_rows_equals_numpy_unique():
    """The pre-pass merges states with ``unique_rows`` (one lexsort): same rows, same order, same inverse
    as ``np.unique(axis=0)`` (the graph, and so every simulation, is unchanged), negatives and huge keys included."""
    from dtoc.sim.pdg_rows import unique_rows

    rng = np.random.default_rng(3)
    for n in (0, 1, 7, 5000):
        for scale in (1, 10**12, 10**17):  # packed single key (first two) and the lexsort fallback (spans > 2^62)
            a = rng.integers(-4, 4, size=(n, 5)).astype(np.int64)
            a[:, 2] *= scale
            u0, i0 = np.unique(a, axis=0, return_inverse=True)
            u1, i1 = unique_rows(a)
            assert np.array_equal(u0, u1) and np.array_equal(i0.reshape(-1), i1)


def test_first_max_by_group_equals_lexsort_choice():
    """The representative edge of each merged state (largest amplitude bound, ties to the lowest edge index)
    is the same as the first entry per group of ``np.lexsort((-value, group))``, empty groups -1."""
    from dtoc.sim.pdg_rows import first_max_by_group

    rng = np.random.default_rng(4)
    group = rng.integers(0, 40, 600)
    value = rng.integers(0, 5, 600).astype(float) * 0.25  # many ties
    order = np.lexsort((-value, group))
    first = np.ones(order.size, dtype=bool)
    first[1:] = group[order][1:] != group[order][:-1]
    want = np.full(45, -1)
    want[group[order][first]] = order[first]
    got = first_max_by_group(group, value, 45)
    assert np.array_equal(got, want) and (got[40:] == -1).all() and (got[:40] >= 0).sum() == np.unique(group).size


def test_envelopes_per_axis_broadcast_equal_full_bit_for_bit():
    """The emission bound passes readout-constant k axes with a length-1 dimension: the voxel envelope and the
    object-spectrum estimate are then the same numbers as on the full (S, T) arrays."""
    from dtoc.sim.pdg_graph import ObjectSpectrum, voxel_envelope, voxel_envelope_axes
    from dtoc.sim.phantom import brain_phantom

    rng = np.random.default_rng(6)
    kx = rng.normal(0, 3000, (50, 17))
    ky = rng.normal(0, 3000, (50, 1))
    ky[3] = 0.0
    kz = np.zeros((1, 1))
    full = np.stack(np.broadcast_arrays(kx, ky, kz), axis=-1)
    for shape in ("box", "sinc", "none"):
        want = voxel_envelope(full, (1e-3, 2e-3, 5e-3), shape)
        assert np.array_equal(voxel_envelope_axes((kx, ky, kz), (1e-3, 2e-3, 5e-3), shape), want)
    spec = ObjectSpectrum(brain_phantom(32, fov_m=(0.2, 0.2)))
    assert np.array_equal(spec.at_axes(kx, ky, kz), spec(full))
    assert 0 < spec(full).min() and spec(full).max() <= 1


def test_row_sums_by_bincount_equal_add_at_bit_for_bit():
    """The pre-pass's child amplitude sums (dtoc.sim.pdg_graph.add_rows_by_index) equal np.add.at exactly,
    including repeated indices, empty groups and signed zeros."""
    from dtoc.sim.pdg_rows import add_rows_by_index

    rng = np.random.default_rng(5)
    idx = rng.integers(0, 50, 400)
    rows = rng.normal(size=(400, 6)) + 1j * rng.normal(size=(400, 6))
    rows[::7] = -0.0
    want = np.zeros((60, 6), dtype=np.complex128)
    np.add.at(want, idx, rows)
    got = add_rows_by_index(idx, rows, 60)
    assert np.array_equal(got.view(np.int64), want.view(np.int64))


def test_top_k_mask_and_dense_rank_equal_the_sorts_they_replace():
    """``top_k_mask`` keeps the same set as ``np.argsort(-score, kind='stable')[:k]`` (ties to the lowest index,
    +inf kept, -1 fillers last); ``dense_rank`` is ``np.unique``'s inverse."""
    from dtoc.sim.pdg_rows import dense_rank, top_k_mask

    rng = np.random.default_rng(7)
    score = np.round(rng.random(3000), 2)  # many ties
    score[rng.integers(0, 3000, 400)] = -1.0
    score[17] = np.inf
    for k in (0, 1, 5, 100, 2599, 2999, 3000, 5000):
        want = np.zeros(score.size, dtype=bool)
        want[np.argsort(-score, kind="stable")[:k]] = True
        assert np.array_equal(top_k_mask(score, k), want), k
    c = rng.integers(-(10**15), 10**15, 500)
    c[::3] = c[0]
    assert np.array_equal(dense_rank(c), np.unique(c, return_inverse=True)[1].reshape(-1))
