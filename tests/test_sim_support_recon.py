"""Reconstruction (dtoc.sim.recon) and metrics (dtoc.sim.metrics): conventions, masks, coils, gradients."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from test_sim_support_irs import cartesian_gre_ir

from dtoc.errors import InputError
from dtoc.sim import metrics, recon
from dtoc.sim.phantom import Phantom, uniform_phantom


def analytic_signal(ir, phantom: Phantom, coil_sens=None) -> torch.Tensor:
    """s_i = sum_v m_v exp(-i k0_i . r_v) for point voxels (the simulator's sign convention)."""
    k0 = ir.nominal_kspace_rad_per_m()
    x, y = phantom.positions_m()
    ph = np.exp(-1j * (np.outer(k0[0], x.ravel()) + np.outer(k0[1], y.ravel())))  # (N_adc, V)
    m = phantom.pd.ravel()
    if coil_sens is None:
        return torch.as_tensor(ph @ m)[None]
    return torch.as_tensor(np.stack([ph @ (m * c.ravel()) for c in coil_sens]))


def dot_phantom(ny, nx, fov, iy, ix, value=1.0):
    p = uniform_phantom((ny, nx), fov, pd=0.0)
    p.pd[iy, ix] = value
    return p


@pytest.mark.parametrize("iy,ix", [(2, 5), (6, 1), (0, 0)])
def test_offcentre_dot_appears_at_its_pixel(iy, ix):
    # non-square matrix and FOV: catches transposed axes, flips and half-pixel shifts
    ir = cartesian_gre_ir(8, 10, (0.032, 0.05))
    ph = dot_phantom(10, 8, (0.032, 0.05), iy, ix, 0.7)
    img = recon.reconstruct(analytic_signal(ir, ph), ir)
    assert img.shape == (10, 8) and img.is_complex()
    expected = np.zeros((10, 8))
    expected[iy, ix] = 0.7  # a voxel of magnetisation m reconstructs to m, real and positive
    assert np.allclose(img.numpy(), expected, atol=1e-12)
    # positions agree: pixel (iy, ix) is where Phantom.positions_m puts the voxel
    x, y = ph.positions_m()
    assert x[iy, ix] == pytest.approx((ix - 4) * 0.004) and y[iy, ix] == pytest.approx((iy - 5) * 0.005)


def test_keep_mask_zero_fills_and_duplicates_average():
    ir = cartesian_gre_ir(8, 8, (0.03, 0.03))
    ph = dot_phantom(8, 8, (0.03, 0.03), 3, 4)
    s = analytic_signal(ir, ph)
    keep = np.ones(ir.n_adc_samples, bool)
    keep[:8] = False  # drop the line at ky = -N/2 dk
    grid = recon.cartesian_grid(ir, keep)
    assert grid.fill_fraction == pytest.approx(56 / 64)
    kg = recon.grid_kspace(s, grid)
    assert torch.all(kg[0, 0, :] == 0) and torch.all(kg[0, 1:, :] != 0)
    img = recon.reconstruct(s, ir, keep)
    # removing one line of a dot's k-space leaves 7/8 of the peak and a ripple along y
    assert abs(img[3, 4]) == pytest.approx(7 / 8, abs=1e-12)
    # same k sampled twice with different values -> their mean
    k0 = ir.nominal_kspace_rad_per_m()
    k2 = np.concatenate([k0, k0], axis=1)
    g2 = recon.cartesian_grid(ir, matrix=(8, 8), k0_rad_per_m=k2)
    assert g2.counts.max() == 2
    s2 = torch.cat([s, 3 * s], dim=-1)
    assert torch.allclose(recon.grid_kspace(s2, g2), 2 * recon.grid_kspace(s, recon.cartesian_grid(ir)))


def test_multicoil_rss_and_single_coil_complex():
    ir = cartesian_gre_ir(8, 8, (0.03, 0.03))
    ph = dot_phantom(8, 8, (0.03, 0.03), 5, 2, 2.0)
    sens = np.stack([np.full((8, 8), 0.6 + 0.0j), np.full((8, 8), 0.8j)])
    img = recon.reconstruct(analytic_signal(ir, ph, sens), ir)
    assert not img.is_complex()
    assert float(img[5, 2]) == pytest.approx(2.0, rel=1e-12)  # sqrt(0.6^2 + 0.8^2) * 2
    assert float(img.sum() - img[5, 2]) < 1e-6


def test_recon_is_differentiable():
    ir = cartesian_gre_ir(4, 4, (0.02, 0.02))
    s = analytic_signal(ir, dot_phantom(4, 4, (0.02, 0.02), 1, 1)).clone().requires_grad_(True)
    img = recon.reconstruct(s, ir)
    loss = (img.abs() ** 2).sum()
    loss.backward()
    # Parseval with numpy's 1/N ifft: sum |img|^2 = sum |s|^2 / N -> d/ds* = s / N
    assert torch.allclose(s.grad, 2 * s.detach() / 16, atol=1e-12)


def test_off_grid_and_outside_samples_are_one_line_errors():
    ir = cartesian_gre_ir(8, 8, (0.03, 0.03))
    with pytest.raises(InputError, match="not on the 8x8 Cartesian grid"):
        recon.cartesian_grid(ir, fov_m=(0.031, 0.03))
    with pytest.raises(InputError, match="outside the 4x8 grid"):
        recon.cartesian_grid(ir, matrix=(4, 8))
    with pytest.raises(InputError, match="one per ADC sample"):
        recon.cartesian_grid(ir, np.ones(3, bool))


# ---------------------------------------------------------------------------------------------
# metrics
# ---------------------------------------------------------------------------------------------
def test_nrmse_definition():
    rng = np.random.default_rng(1)
    i0 = rng.normal(size=(8, 8)) + 1j * rng.normal(size=(8, 8))
    assert float(metrics.nrmse(i0, i0)) == 0.0
    assert float(metrics.nrmse(np.zeros((8, 8)), i0)) == pytest.approx(1.0)
    # magnitude only: a global phase does not count
    assert float(metrics.nrmse(i0 * np.exp(1j), i0)) == pytest.approx(0.0, abs=1e-15)
    assert float(metrics.nrmse(1.1 * np.abs(i0), i0)) == pytest.approx(0.1, rel=1e-12)
    t = torch.tensor(np.abs(i0), requires_grad=True)
    metrics.nrmse(t * 1.05, i0).backward()
    assert torch.isfinite(t.grad).all() and float(t.grad.abs().sum()) > 0


def test_ghost_ratio_of_a_synthetic_nyquist_ghost():
    n = 32
    ideal = np.zeros((n, n))
    ideal[12:20, 10:22] = 1.0  # object: 8 rows x 12 cols, centred
    obj = metrics.object_mask(ideal)
    gh = metrics.ghost_mask(obj)
    assert gh.sum() == obj.sum()  # the shifted object lies fully outside the object here
    assert not (gh & obj).any()
    ghosted = ideal + 0.1 * np.roll(ideal, n // 2, axis=0)  # 10 % N/2 ghost along y (rows)
    assert float(metrics.ghost_ratio(ghosted, ideal)) == pytest.approx(0.01, rel=1e-12)
    assert float(metrics.ghost_ratio(ideal, ideal)) == 0.0
    # a ghost along x is not an N/2 ghost along phase = y
    assert float(metrics.ghost_ratio(ideal + 0.1 * np.roll(ideal, n // 2, axis=1), ideal)) == 0.0


def test_object_mask_includes_dark_tissue_inside_the_object():
    """A bright rim around a dark (5 % of max) interior, as a long-TE 7 T EPI of the head: the interior is
    object, not ghost region; the ideal image scores no ghost and a real N/2 ghost is still measured."""
    n = 32
    ideal = np.zeros((n, n))
    ideal[4:28, 8:24] = 1.0
    ideal[6:26, 10:22] = 0.05  # below the 10 % threshold, enclosed by the rim
    obj = metrics.object_mask(ideal)
    assert obj.sum() == 24 * 16
    assert float(metrics.ghost_ratio(ideal, ideal)) == 0.0
    ghosted = ideal + 0.1 * np.roll(ideal, n // 2, axis=0)
    gh = metrics.ghost_mask(obj)
    want = (np.abs(ghosted) ** 2)[gh].sum() / (np.abs(ghosted) ** 2)[obj].sum()
    assert want > 1e-3
    assert float(metrics.ghost_ratio(ghosted, ideal)) == pytest.approx(want, rel=1e-12)
    # a 2-pixel gap in the rim (as the longest 7 T echo train shows) still encloses the interior
    ideal[4:6, 15:17] = 0.05
    assert metrics.object_mask(ideal).sum() == 24 * 16
    assert float(metrics.ghost_ratio(ideal, ideal)) == 0.0
    # the closing does not erode an object that touches the image border
    edge = np.zeros((n, n))
    edge[0:5, 10:20] = 1.0
    assert (metrics.object_mask(edge) == (edge > 0)).all()


def test_kspace_errors():
    k0 = np.zeros((3, 4))
    k = k0.copy()
    k[0, 1] = 30.0
    k[1, 2] = 40.0
    e = metrics.kspace_errors(k, k0, dk_rad_per_m=(100.0, 200.0, np.inf))
    assert e["kspace_rmse_rad_per_m"] == pytest.approx(np.sqrt((900 + 1600) / 4))
    assert e["kspace_max_err_rad_per_m"] == pytest.approx(40.0)
    assert e["kspace_max_err_dk"] == pytest.approx(0.3)
    assert metrics.kspace_within(k, k0, (100.0, 200.0, np.inf), tol_dk=0.25).tolist() == [True, False, True, True]
