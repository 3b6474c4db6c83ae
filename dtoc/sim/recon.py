"""Plain inverse-FFT reconstruction onto the target Cartesian grid, assuming *nominal* k (as the paper).

Conventions (consistent with :class:`dtoc.sim.phantom.Phantom` and the simulator's signal model
``s(k) = sum_r m(r) exp(-i k . r)``, docs/conventions.md):

* Each ADC sample i is placed at grid index ``j = round(k0_i / dk) + N/2`` per in-plane axis, where
  ``k0 = ir.nominal_kspace_rad_per_m()`` (rad/m) and ``dk = 2 pi / FOV``; so grid index j holds
  k = (j - N/2) dk, j = 0..N-1 (k = -N/2 dk .. (N/2-1) dk).  Samples must lie on the grid within
  ``on_grid_tol`` (fraction of dk), inside it, and not on top of each other (several samples at one
  grid point are averaged).  Discarded samples (``keep_mask`` False) and unsampled grid points are
  zero-filled.
* ``image = fftshift(ifft2(ifftshift(K)))`` with numpy's default 1/N normalisation: pixel (iy, ix)
  is at x = (ix - nx/2) dx, y = (iy - ny/2) dy -- exactly the Phantom's voxel positions -- and a
  voxel of transverse magnetisation m at that position reconstructs to value m (no flip, no shift).
* Image array layout (ny, nx): rows = physical y, columns = physical x (z ignored: 2D).
* 3D-encoded sequences (``ir.meta['grid3d']``, inferred from the ADC k positions by
  :func:`dtoc.seq.geometry.infer_cartesian_grid_3d`): the same rules on every axis, image (nz, ny, nx)
  by ``fftshift(ifftn(ifftshift(K)))`` over the three axes (:func:`cartesian_grid_3d`).
* Multi-coil: root-sum-of-squares magnitude over coils; one coil: the complex image.

Everything is torch and differentiable with respect to the signal (the optimizer's image loss).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from dtoc.errors import InputError


@dataclass(frozen=True)
class CartesianGrid:
    """Mapping of ADC samples onto the (ny, nx) Cartesian target grid ((nz, ny, nx) for a 3D grid).

    Attributes:
        shape: (ny, nx) image matrix, or (nz, ny, nx).
        fov_m: (fov_x, fov_y), m, or (fov_x, fov_y, fov_z).
        flat_index: (N_adc,) int64 index into the flattened k-space grid (-1: sample not used).
        counts: (prod(shape),) number of samples on each grid point.
        max_off_grid: largest |k0/dk - round(k0/dk)| over used samples (fraction of dk).
    """

    shape: tuple[int, ...]
    fov_m: tuple[float, ...]
    flat_index: np.ndarray
    counts: np.ndarray
    max_off_grid: float

    @property
    def fill_fraction(self) -> float:
        """Fraction of grid points that receive at least one sample."""
        return float(np.mean(self.counts > 0))


def _infer_matrix_fov(ir, matrix, fov_m):
    """(ny, nx) and (fov_x, fov_y): the explicit arguments, else the IR's encoding geometry."""
    geo = ir.geometry
    if fov_m is None:
        if ir.fov_m is None:
            raise InputError("reconstruction: the sequence has no FOV; pass fov_m")
        fov_m = (ir.fov_m[0], ir.fov_m[1])
    fov = np.asarray(fov_m, dtype=np.float64).ravel()
    fov = np.repeat(fov, 2) if fov.size == 1 else fov[:2]
    if fov.size != 2 or not np.all(np.isfinite(fov)) or np.any(fov <= 0):
        raise InputError(f"reconstruction: fov_m {fov_m!r}: expected positive (fov_x, fov_y) in m")
    if matrix is None:
        if geo is None:
            raise InputError("reconstruction: the sequence has no matrix size; pass matrix=(nx, ny)")
        if not geo.in_plane:
            raise InputError(
                f"reconstruction: readout/phase axes {geo.readout_axis}/{geo.phase_axis} are not the x-y plane"
            )
        matrix = geo.matrix_xy
    nx, ny = (int(matrix[0]), int(matrix[1])) if np.size(matrix) == 2 else (int(matrix), int(matrix))
    return (ny, nx), (float(fov[0]), float(fov[1]))


def cartesian_grid(
    ir, keep_mask=None, *, matrix=None, fov_m=None, k0_rad_per_m=None, on_grid_tol: float = 0.05
) -> CartesianGrid:
    """Grid indices of every ADC sample of ``ir`` from its nominal k-space.

    Args:
        ir: :class:`dtoc.seq.ir.SequenceIR`.
        keep_mask: (N_adc,) bool; False samples are discarded (index -1).
        matrix: (nx, ny) image matrix (default from ``ir.matrix`` and its readout/phase axes).
        fov_m: (fov_x, fov_y), m (default ``ir.fov_m``).
        k0_rad_per_m: (3, N_adc) nominal k to use instead of ``ir.nominal_kspace_rad_per_m()``.
        on_grid_tol: allowed distance from a grid point, fraction of dk.
    Raises:
        InputError: samples off the grid, outside it, or shape mismatch.
    """
    (ny, nx), fov = _infer_matrix_fov(ir, matrix, fov_m)
    k0 = np.asarray(ir.nominal_kspace_rad_per_m() if k0_rad_per_m is None else k0_rad_per_m, dtype=np.float64)
    n_adc = k0.shape[1]
    keep = np.ones(n_adc, dtype=bool) if keep_mask is None else np.asarray(keep_mask, dtype=bool).ravel()
    if keep.shape != (n_adc,):
        raise InputError(f"keep_mask has {keep.size} entries, expected one per ADC sample ({n_adc})")
    dk = 2 * np.pi / np.asarray(fov)
    u = k0[:2] / dk[:, None]  # (2, N_adc) in grid units
    offset = (getattr(ir, "meta", None) or {}).get("grid_offset_dk")
    if offset is not None:  # an inferred grid whose samples sit between its points (e.g. half a step)
        u = u - np.asarray(offset[:2], dtype=np.float64)[:, None]
    r = np.rint(u)
    off = np.abs(u - r)
    max_off = float(off[:, keep].max()) if keep.any() else 0.0
    if max_off > on_grid_tol:
        i = int(np.argmax(np.where(keep, off.max(0), -1)))
        raise InputError(
            f"nominal k-space is not on the {nx}x{ny} Cartesian grid (sample {i} is {max_off:.3f} dk off; tolerance {on_grid_tol}): "
            "plain iFFT reconstruction needs on-grid nominal samples"
        )
    jx = r[0].astype(np.int64) + nx // 2
    jy = r[1].astype(np.int64) + ny // 2
    # an even grid is periodic: k = +N/2 dk is the -N/2 point (a mirrored layout -N/2+1 .. N/2, e.g. JEMRIS)
    if nx % 2 == 0:
        jx[jx == nx] = 0
    if ny % 2 == 0:
        jy[jy == ny] = 0
    outside = keep & ((jx < 0) | (jx >= nx) | (jy < 0) | (jy >= ny))
    if outside.any():
        i = int(np.argmax(outside))
        raise InputError(
            f"nominal k-space sample {i} lies outside the {nx}x{ny} grid (k/dk = {u[0, i]:.2f}, {u[1, i]:.2f})"
        )
    flat = np.where(keep, jy * nx + jx, -1).astype(np.int64)
    counts = np.bincount(flat[keep], minlength=ny * nx)
    return CartesianGrid((ny, nx), fov, flat, counts, max_off)


def cartesian_grid_3d(ir, keep_mask=None, *, on_grid_tol: float = 0.05) -> CartesianGrid:
    """Grid indices of every ADC sample of a 3D-encoded ``ir`` on its inferred (nz, ny, nx) grid
    (``ir.meta['grid3d']``, :func:`dtoc.seq.geometry.infer_cartesian_grid_3d`)."""
    g = (getattr(ir, "meta", None) or {}).get("grid3d")
    if g is None:
        raise InputError("reconstruction: the sequence has no 3D Cartesian grid (see its notes)")
    n = np.asarray(g["matrix_xyz"], dtype=np.int64)
    fov = np.asarray(g["fov_m"], dtype=np.float64)
    k0 = np.asarray(ir.nominal_kspace_rad_per_m(), dtype=np.float64)
    n_adc = k0.shape[1]
    keep = np.ones(n_adc, dtype=bool) if keep_mask is None else np.asarray(keep_mask, dtype=bool).ravel()
    if keep.shape != (n_adc,):
        raise InputError(f"keep_mask has {keep.size} entries, expected one per ADC sample ({n_adc})")
    u = k0 / (2 * np.pi / fov)[:, None] - np.asarray(g["offset_dk"], dtype=np.float64)[:, None]
    r = np.rint(u)
    off = np.abs(u - r)
    max_off = float(off[:, keep].max()) if keep.any() else 0.0
    if max_off > on_grid_tol:
        i = int(np.argmax(np.where(keep, off.max(0), -1)))
        raise InputError(f"nominal k-space sample {i} is {max_off:.3f} dk off the 3D grid (tolerance {on_grid_tol})")
    j = r.astype(np.int64) + (n // 2)[:, None]  # (3, N_adc): (jx, jy, jz)
    for a in range(3):  # an even grid is periodic: +N/2 is the -N/2 point (as in cartesian_grid)
        if n[a] % 2 == 0:
            j[a][j[a] == n[a]] = 0
    outside = keep & np.any((j < 0) | (j >= n[:, None]), axis=0)
    if outside.any():
        i = int(np.argmax(outside))
        raise InputError(f"nominal k-space sample {i} lies outside the {n[0]}x{n[1]}x{n[2]} grid")
    flat = np.where(keep, (j[2] * n[1] + j[1]) * n[0] + j[0], -1).astype(np.int64)
    counts = np.bincount(flat[keep], minlength=int(n.prod()))
    shape = (int(n[2]), int(n[1]), int(n[0]))
    return CartesianGrid(shape, (float(fov[0]), float(fov[1]), float(fov[2])), flat, counts, max_off)


def grid_kspace(signal, grid: CartesianGrid) -> torch.Tensor:
    """Scatter samples onto the grid (averaging duplicates, zero elsewhere).

    Args:
        signal: (..., N_adc) complex tensor/array.
    Returns:
        (..., ny, nx) complex tensor, index (jy, jx) holding k = ((jx - nx/2) dkx, (jy - ny/2) dky).
    """
    s = torch.as_tensor(signal)
    if not s.is_complex():
        s = s.to(torch.complex128 if s.dtype == torch.float64 else torch.complex64)
    if s.shape[-1] != grid.flat_index.size:
        raise InputError(f"signal has {s.shape[-1]} samples, the sequence {grid.flat_index.size} ADC samples")
    used = np.where(grid.flat_index >= 0)[0]
    idx = torch.as_tensor(grid.flat_index[used], device=s.device)
    src = s[..., torch.as_tensor(used, device=s.device)]
    cnt = grid.counts[grid.flat_index[used]]
    if np.any(cnt > 1):
        src = src / torch.as_tensor(cnt, dtype=src.real.dtype, device=s.device)
    out = torch.zeros(s.shape[:-1] + (int(np.prod(grid.shape)),), dtype=s.dtype, device=s.device)
    out = out.index_add(-1, idx, src)
    return out.reshape(s.shape[:-1] + tuple(grid.shape))


def kspace_to_image(kgrid: torch.Tensor, ndim: int = 2) -> torch.Tensor:
    """(..., ny, nx) centred k-space grid -> (..., ny, nx) complex image (see module conventions);
    ``ndim=3``: (..., nz, ny, nx) -> (..., nz, ny, nx)."""
    if ndim == 2:
        dims = (-2, -1)
        return torch.fft.fftshift(torch.fft.ifft2(torch.fft.ifftshift(kgrid, dim=dims), dim=dims), dim=dims)
    d3 = tuple(range(-ndim, 0))
    return torch.fft.fftshift(torch.fft.ifftn(torch.fft.ifftshift(kgrid, dim=d3), dim=d3), dim=d3)


def reconstruct(
    signal,
    ir,
    keep_mask=None,
    *,
    grid: CartesianGrid | None = None,
    matrix=None,
    fov_m=None,
    coil_axis: bool | None = None,
) -> torch.Tensor:
    """Inverse-FFT image from simulated/measured samples assuming nominal k.

    Args:
        signal: (n_coils, N_adc) or (N_adc,) complex (leading batch dims allowed: (..., n_coils, N_adc)).
        ir: the sequence (nominal k, FOV, matrix).
        keep_mask: (N_adc,) bool, samples to keep (others zero-filled).
        grid: precomputed :func:`cartesian_grid` (then ``keep_mask``/``matrix``/``fov_m`` are ignored).
        coil_axis: whether the second-to-last axis is a coil axis (default: True for 2D+ input).
    Returns:
        (ny, nx) complex image for one coil, or (ny, nx) real root-sum-of-squares magnitude for several
        ((nz, ny, nx) for a 3D-encoded sequence).
    """
    s = torch.as_tensor(signal)
    meta = getattr(ir, "meta", None) or {}
    if grid is None and meta.get("recon") == "ndft":
        from dtoc.sim.ndft import ndft_image  # non-Cartesian 2D: non-uniform DFT on the nominal trajectory

        img = ndft_image(s, ir, keep_mask)
    else:
        if grid is None:
            if meta.get("grid3d") is not None and matrix is None:
                grid = cartesian_grid_3d(ir, keep_mask)
            else:
                grid = cartesian_grid(ir, keep_mask, matrix=matrix, fov_m=fov_m)
        img = kspace_to_image(grid_kspace(s, grid), len(grid.shape))
    if coil_axis is None:
        coil_axis = s.ndim >= 2
    if not coil_axis:
        return img
    cdim = -1 - (img.ndim - s.ndim + 1)  # the coil axis just before the image axes
    if img.shape[cdim] == 1:
        return img.squeeze(cdim)
    return rss(img, dim=cdim)


def rss(images: torch.Tensor, dim: int = -3) -> torch.Tensor:
    """Root-sum-of-squares magnitude over the coil axis (differentiable; no NaN gradient at 0)."""
    p = (images.real**2 + images.imag**2).sum(dim=dim)
    return torch.sqrt(p + torch.finfo(p.dtype).tiny)
