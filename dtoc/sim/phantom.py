"""Phantoms: voxel maps of the tissue parameters the simulator needs.

The :class:`Phantom` container is the simulator's input contract; generators (the built-in brain
phantom), loaders (``.npz``) and transforms (rotation, resampling) live beside it.

Geometry: a 2D phantom of shape (ny, nx) covers ``fov_m = (fov_x, fov_y)`` centred on the isocentre;
voxel (iy, ix) sits at x = (ix - nx/2) * fov_x / nx, y = (iy - ny/2) * fov_y / ny (m), the positions
a plain inverse FFT of a centred k-space grid assigns to its pixels.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Phantom:
    """Tissue maps, each (ny, nx) float64 unless noted.

    Attributes:
        pd: proton density (relative, >= 0).
        t1_s, t2_s, t2dash_s: relaxation times, s (> 0; use np.inf for "none").
        d_m2_per_s: isotropic diffusion coefficient, m^2/s (>= 0).
        b0_hz: off-resonance, Hz.
        b1: relative transmit field (1 = nominal flip angle).
        fov_m: (fov_x, fov_y), m.
        coil_sens: optional (n_coils, ny, nx) complex receive sensitivities (None = one uniform coil).
        voxel_shape: 'box' or 'sinc' or 'none': the intra-voxel signal model the simulator applies
            (a box voxel attenuates a state of dephasing k by sinc(k dx / 2pi) per axis).
    """

    pd: np.ndarray
    t1_s: np.ndarray
    t2_s: np.ndarray
    t2dash_s: np.ndarray
    d_m2_per_s: np.ndarray
    b0_hz: np.ndarray
    b1: np.ndarray
    fov_m: tuple[float, float]
    coil_sens: np.ndarray | None = None
    voxel_shape: str = "box"

    @property
    def shape(self) -> tuple[int, int]:
        return tuple(self.pd.shape)

    def positions_m(self) -> tuple[np.ndarray, np.ndarray]:
        """(x, y) voxel-centre coordinates, each (ny, nx), m."""
        ny, nx = self.shape
        x = (np.arange(nx) - nx / 2) * self.fov_m[0] / nx
        y = (np.arange(ny) - ny / 2) * self.fov_m[1] / ny
        yy, xx = np.meshgrid(y, x, indexing="ij")
        return xx, yy
