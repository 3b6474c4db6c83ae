"""Image / encoding geometry of a Cartesian sequence, derived once from its definitions (docs/conventions.md).

A sequence declares a field of view per physical axis (x, y, z) and a matrix in *encoding* order
(readout, phase[, partition]); which physical axis reads out and which phase-encodes is the IR's
``readout_axis`` / ``phase_axis`` (default x / y; a readout on y phase-encodes x).  Images are
(ny, nx) arrays: rows = physical y, columns = physical x (:mod:`dtoc.sim.recon`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from dtoc.errors import InputError


@dataclass(frozen=True)
class EncodingGeometry:
    """In-plane Cartesian encoding of a sequence.

    Attributes:
        readout_axis: physical axis index (0, 1, 2) of the readout.
        phase_axis: physical axis index of the phase encoding.
        matrix_readout_phase: (n_readout, n_phase) as the sequence declares it.
        fov_m: (fov_x, fov_y, fov_z) field of view per physical axis, m.
    """

    readout_axis: int
    phase_axis: int
    matrix_readout_phase: tuple[int, int]
    fov_m: tuple[float, float, float]

    @property
    def in_plane(self) -> bool:
        """True when readout and phase encoding span the physical x-y plane (what the 2D recon images)."""
        return {self.readout_axis, self.phase_axis} == {0, 1}

    @property
    def matrix_xy(self) -> tuple[int, int]:
        """(nx, ny) image matrix along physical x and y."""
        n = [0, 0, 0]
        n[self.readout_axis], n[self.phase_axis] = self.matrix_readout_phase
        return n[0], n[1]

    @property
    def image_shape(self) -> tuple[int, int]:
        """(ny, nx): shape of the reconstructed image array."""
        nx, ny = self.matrix_xy
        return ny, nx

    @property
    def fov_xy_m(self) -> tuple[float, float]:
        """(fov_x, fov_y), m."""
        return self.fov_m[0], self.fov_m[1]

    @property
    def voxel_m(self) -> tuple[float | None, float | None, float | None]:
        """Voxel size per physical axis, m (None on the axis that is not encoded in plane)."""
        vox: list[float | None] = [None, None, None]
        vox[self.readout_axis] = self.fov_m[self.readout_axis] / self.matrix_readout_phase[0]
        vox[self.phase_axis] = self.fov_m[self.phase_axis] / self.matrix_readout_phase[1]
        return vox[0], vox[1], vox[2]

    @property
    def dk_rad_per_m(self) -> tuple[float, float, float]:
        """k-space grid step 2 pi / FOV per physical axis, rad/m (inf where the FOV is 0)."""
        return tuple(2 * math.pi / f if f else math.inf for f in self.fov_m)  # type: ignore[return-value]

    @property
    def phase_image_dim(self) -> int:
        """Array dimension of the phase-encoding direction in a (ny, nx) image: -1 (columns) for a phase
        encoding along x, else -2 (rows)."""
        return -1 if self.phase_axis == 0 else -2


def encoding_geometry(
    fov_m: Any, matrix: Any, readout_axis: int | None = None, phase_axis: int | None = None
) -> EncodingGeometry | None:
    """The geometry of a sequence's definitions (None when FOV or an in-plane matrix is not declared).

    Args:
        fov_m: (fov_x, fov_y, fov_z), m, or None.
        matrix: (n_readout, n_phase[, n_partition]) or None.
        readout_axis / phase_axis: physical axes (None: x readout; phase on the other in-plane axis).
    """
    if fov_m is None or matrix is None or len(matrix) < 2:
        return None
    ro = readout_axis if readout_axis is not None else 0
    pe = phase_axis if phase_axis is not None else (1 - ro if ro in (0, 1) else 1)
    if ro == pe:
        raise InputError(f"readout and phase encoding both on axis {'xyz'[ro]}")
    f = tuple(float(v) for v in fov_m)
    f3 = (f + (0.0, 0.0, 0.0))[:3]
    return EncodingGeometry(ro, pe, (int(matrix[0]), int(matrix[1])), f3)  # type: ignore[arg-type]
