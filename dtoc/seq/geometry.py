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


@dataclass(frozen=True)
class InferredGrid:
    """A Cartesian grid read off the nominal k of the ADC samples (for files without FOV/matrix definitions).

    Attributes:
        readout_axis / phase_axis: physical axes (k varies within an ADC / between ADCs).
        matrix_readout_phase: grid points along readout and phase.
        fov_m: 2 pi / dk per physical axis (0 on the axis that is not encoded), m.
        offset_dk: (3,) where the samples sit between grid points, fraction of dk in [-0.5, 0.5) (pypulseq's
            usual readout has its centre at sample N/2: no offset; a readout centred between samples: 0.5).
    """

    readout_axis: int
    phase_axis: int
    matrix_readout_phase: tuple[int, int]
    fov_m: tuple[float, float, float]
    offset_dk: tuple[float, float, float]

    def describe(self, declared: str | None = None) -> str:
        """One note line; ``declared``: the file's own FOV/matrix definitions, when it has some (then compared)."""
        ro, pe = "xyz"[self.readout_axis], "xyz"[self.phase_axis]
        n_ro, n_pe = self.matrix_readout_phase
        f = self.fov_m
        head = "no FOV/matrix definitions" if declared is None else f"the file defines {declared}"
        if n_pe == 1:  # no phase encoding: a projection; no FOV along the unencoded axis
            s = (
                f"{head}: Cartesian grid inferred from the ADC k positions: {n_ro} ({ro}, readout) x 1 ({pe} not "
                f"encoded: every readout on one line, the image a 1D projection, no figure along {pe}), FOV "
                f"{1e3 * f[self.readout_axis]:.4g} mm along {ro}"
            )
        else:
            s = (
                f"{head}: Cartesian grid inferred from the ADC k positions: {n_ro} ({ro}, readout) x "
                f"{n_pe} ({pe}, phase), FOV {1e3 * f[self.readout_axis]:.4g} x {1e3 * f[self.phase_axis]:.4g} mm"
            )
        off = [o for o in self.offset_dk if abs(o) > 1e-3]
        if off:
            s += f", samples offset by {', '.join(f'{o:+.3g}' for o in self.offset_dk)} dk"
        return s


def _grid_step(values, tol: float = 1e-3) -> tuple[float, float] | None:
    """(dk, offset) when sorted distinct ``values`` sit on a common grid ``(i + offset) dk``; None otherwise."""
    import numpy as np

    x = np.sort(np.asarray(values, dtype=np.float64))
    span = float(x[-1] - x[0]) if x.size else 0.0
    if span <= 0:
        return None
    # merge values closer than 1e-5 of the span (amplitudes rounded to 6 digits by the writers)
    v = x[np.concatenate([[True], np.diff(x) > 1e-5 * span])]
    if v.size < 2:
        return None
    d = np.diff(v)
    d = d[d > 1e-9 * max(span, 1e-300)]
    if d.size == 0:
        return None
    dk = float(np.min(d))
    if dk <= 0 or span / dk > 1e5:
        return None
    steps = d / dk
    if np.max(np.abs(steps - np.rint(steps))) > tol * 10:
        return None
    # refine dk on the whole span, then the common offset
    n = np.rint((v - v[0]) / dk)
    dk = float(np.polyfit(n, v, 1)[0]) if n[-1] > 0 else dk
    o0 = float(v[0] / dk - math.floor(v[0] / dk + 0.5))  # offset of the first value, in [-0.5, 0.5)
    r = v / dk - o0
    dev = r - np.rint(r)  # every value's distance from the grid through the first one
    if np.max(np.abs(dev)) > tol * 10:
        return None
    off = o0 + float(np.median(dev))
    return dk, off - math.floor(off + 0.5)


def _layout_points(u) -> int:
    """Grid points of integer sample indices ``u``: ``2h + 1`` when symmetric (-h .. h), N for the mirrored
    standard layout -N/2+1 .. N/2 (phase encoded from the top, as JEMRIS and others write it: on the periodic
    N-point grid the +N/2 line is the -N/2 line, so a 64-line EPI is 64, not 66), else the even standard layout
    -N/2 .. N/2-1 (the larger side sets N, as for partial Fourier)."""
    lo, hi = int(u.min()), int(u.max())
    if -lo == hi:
        return 2 * hi + 1
    if hi - lo + 1 == 2 * hi and hi > 1:  # -N/2+1 .. N/2, complete
        return 2 * hi
    return 2 * max(-lo, hi + 1)


def infer_cartesian_grid(k0_rad_per_m, adc_sizes) -> InferredGrid | None:
    """The Cartesian grid of a 2D sequence from the nominal k of its ADC samples; None when the samples are
    not on one (radial, spiral, 3D, or nothing varies).

    Args:
        k0_rad_per_m: (3, N_adc) nominal k at every ADC sample.
        adc_sizes: samples per ADC event, in order (they sum to N_adc).
    Rules: the readout axis is the one along which k varies within ADC events, the phase axis the one that
    varies between them and is constant within each; each must sit on a common grid ``(i + offset) dk``.
    The matrix is the even number of points the standard layout ``-N/2 .. N/2 - 1`` needs (the larger side
    sets it for a partial-Fourier layout), or ``2h + 1`` for a layout symmetric about 0 (``-h .. h``).
    Ramp-sampled readouts (non-uniform k along the readout) are not a grid: None.
    """
    import numpy as np

    k = np.asarray(k0_rad_per_m, dtype=np.float64)
    edges = np.cumsum([0, *adc_sizes])
    if k.ndim != 2 or k.shape[0] != 3 or edges[-1] != k.shape[1] or k.shape[1] == 0:
        return None
    scale = max(float(np.abs(k).max()), 1e-12)
    within, between = spread_within_between(k, edges)
    varies = within > 1e-4 * scale
    if varies.sum() != 1:
        return None  # no readout, or k moves on two axes within one ADC (radial, spiral): not Cartesian
    ro = int(np.argmax(varies))
    pe_candidates = [a for a in range(3) if a != ro and between[a] > 1e-4 * scale]
    if len(pe_candidates) > 1:
        return None  # 3D or oblique encoding: not handled by the 2D grid
    pe = pe_candidates[0] if pe_candidates else (1 if ro == 0 else 0)
    out_n = [1, 1, 1]
    fov = [0.0, 0.0, 0.0]
    off = [0.0, 0.0, 0.0]
    for a in (ro, pe):
        if a == pe and not pe_candidates:  # a single line (e.g. a 1D readout): one phase point
            continue
        g = _axis_grid(k[a])
        if g is None:
            return None
        out_n[a], fov[a], off[a] = g
    if fov[ro] == 0.0 or not _readout_step_is_grid_step(k[ro], edges, fov[ro]):
        return None
    if fov[pe] == 0.0:
        fov[pe] = fov[ro] * out_n[pe] / out_n[ro]  # one line: a nominal FOV, the recon needs one
    return InferredGrid(ro, pe, (out_n[ro], out_n[pe]), (fov[0], fov[1], fov[2]), (off[0], off[1], off[2]))


def spread_within_between(k, edges) -> tuple:
    """Per axis (3,): the largest k spread within one ADC event, and the spread of the events' mean k."""
    import numpy as np

    within = np.zeros(3)
    between = np.zeros(3)
    for a in range(3):
        spreads = [np.ptp(k[a, s:e]) for s, e in zip(edges[:-1], edges[1:]) if e > s]
        within[a] = max(spreads) if spreads else 0.0
        means = [np.mean(k[a, s:e]) for s, e in zip(edges[:-1], edges[1:]) if e > s]
        between[a] = np.ptp(means) if means else 0.0
    return within, between


def _axis_grid(values) -> tuple[int, float, float] | None:
    """(points, FOV m, offset in dk) of one axis' k values on a common grid (:func:`_grid_step`,
    :func:`_layout_points`); None when they are not on one."""
    import numpy as np

    g = _grid_step(values)
    if g is None:
        return None
    dk, o = g
    # a half-step offset is +0.5 or -0.5 alike: take the one that gives the smaller standard grid
    cands = [o] + ([o - math.copysign(1.0, o)] if abs(o) > 0.49 else [])
    n, o = min((_layout_points(np.rint(values / dk - c).astype(np.int64)), c) for c in cands)
    return n, 2 * math.pi / dk, float(o)


def _readout_step_is_grid_step(k_ro, edges, fov_ro: float) -> bool:
    """The readout's own sampling step must be the grid step: lines whose samples sit at different offsets
    (an ADC not centred on alternating readouts) only form a finer grid that half the points never fill."""
    import numpy as np

    step = float(np.median([np.median(np.abs(np.diff(k_ro[s:e]))) for s, e in zip(edges[:-1], edges[1:]) if e - s > 1]))
    return step <= 1.1 * 2 * math.pi / fov_ro


@dataclass(frozen=True)
class InferredGrid3D:
    """A 3D Cartesian grid read off the nominal k of the ADC samples (k varies along one axis within each
    ADC and along the two others between ADCs).

    Attributes:
        readout_axis: physical axis of the readout.
        matrix_xyz: grid points per physical axis (nx, ny, nz).
        fov_m: 2 pi / dk per physical axis, m.
        offset_dk: where the samples sit between grid points, fraction of dk per axis.
    """

    readout_axis: int
    matrix_xyz: tuple[int, int, int]
    fov_m: tuple[float, float, float]
    offset_dk: tuple[float, float, float]

    def describe(self) -> str:
        n, f = self.matrix_xyz, self.fov_m
        s = (
            f"3D Cartesian grid inferred from the ADC k positions: {n[0]} x {n[1]} x {n[2]} (x, y, z; readout "
            f"{'xyz'[self.readout_axis]}), FOV {1e3 * f[0]:.4g} x {1e3 * f[1]:.4g} x {1e3 * f[2]:.4g} mm"
        )
        if any(abs(o) > 1e-3 for o in self.offset_dk):
            s += f", samples offset by {', '.join(f'{o:+.3g}' for o in self.offset_dk)} dk"
        return s + "; image term on a 3D phantom when one is given (--phantom brain3d)"

    def as_meta(self) -> dict:
        """The JSON-able form kept in ``SequenceIR.meta['grid3d']``."""
        return {
            "readout_axis": self.readout_axis,
            "matrix_xyz": list(self.matrix_xyz),
            "fov_m": list(self.fov_m),
            "offset_dk": list(self.offset_dk),
        }


def infer_cartesian_grid_3d(k0_rad_per_m, adc_sizes) -> InferredGrid3D | None:
    """The 3D Cartesian grid of a sequence from the nominal k of its ADC samples; None when the samples are not
    on one.  Same rules per axis as :func:`infer_cartesian_grid` (standard layouts, half-step offsets,
    partial Fourier), with k varying along one axis within ADCs and along both others between them."""
    import numpy as np

    k = np.asarray(k0_rad_per_m, dtype=np.float64)
    edges = np.cumsum([0, *adc_sizes])
    if k.ndim != 2 or k.shape[0] != 3 or edges[-1] != k.shape[1] or k.shape[1] == 0:
        return None
    scale = max(float(np.abs(k).max()), 1e-12)
    within, between = spread_within_between(k, edges)
    varies = within > 1e-4 * scale
    if varies.sum() != 1:
        return None
    ro = int(np.argmax(varies))
    if not all(between[a] > 1e-4 * scale for a in range(3) if a != ro):
        return None
    n, fov, off = [0, 0, 0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]
    for a in range(3):
        g = _axis_grid(k[a])
        if g is None:
            return None
        n[a], fov[a], off[a] = g
    if not _readout_step_is_grid_step(k[ro], edges, fov[ro]):
        return None
    return InferredGrid3D(ro, (n[0], n[1], n[2]), (fov[0], fov[1], fov[2]), (off[0], off[1], off[2]))


def sampling_step_dk(k0_rad_per_m, adc_sizes) -> float | None:
    """The k-space unit of a sequence without a grid (radial, spiral, ...): the readouts' sampling step, rad/m --
    the median over ADC events of the largest distance between consecutive samples (2 pi / FOV for radial
    and Cartesian readouts; for a spiral the step along the path at peak gradient).  None without readouts."""
    import numpy as np

    k = np.asarray(k0_rad_per_m, dtype=np.float64)
    edges = np.cumsum([0, *adc_sizes])
    steps = []
    for s, e in zip(edges[:-1], edges[1:]):
        if e - s >= 2:
            steps.append(float(np.max(np.linalg.norm(np.diff(k[:, s:e], axis=1), axis=0))))
    steps = [x for x in steps if x > 0]
    return float(np.median(steps)) if steps else None


def radial_like_step(k0_rad_per_m, adc_sizes, constant: bool = True) -> float | None:
    """The sampling step when every readout runs along a straight line through k-space with a constant step
    (radial, UTE: then 2 pi / step is the FOV); None otherwise (spiral, ...).  ``constant=False``: the step
    may vary along the line (ramp sampling); the largest step of each line (its flat top), the same for every
    line, is returned."""
    import numpy as np

    k = np.asarray(k0_rad_per_m, dtype=np.float64)[:2]
    edges = np.cumsum([0, *adc_sizes])
    steps = []
    for s, e in zip(edges[:-1], edges[1:]):
        if e - s < 3:
            continue
        d = np.diff(k[:, s:e], axis=1)
        nrm = np.linalg.norm(d, axis=0)
        if nrm.max() <= 0:
            continue
        u = d / np.maximum(nrm, 1e-30)
        if np.max(np.abs(u[0] * u[0, 0] + u[1] * u[1, 0] - 1)) > 1e-3:  # not straight
            return None
        if constant and np.ptp(nrm) > 1e-3 * nrm.mean():  # not a constant step
            return None
        steps.append(float(nrm.mean() if constant else nrm.max()))
    if not steps or np.ptp(steps) > 1e-3 * np.mean(steps):
        return None
    return float(np.mean(steps))


def line_cartesian(k0_rad_per_m, adc_sizes) -> tuple[int, int, float, float, int, int] | None:
    """Readouts that are straight lines along one in-plane axis at phase positions on a uniform grid, with a
    non-uniform step along the line (ramp sampling): ``(readout_axis, phase_axis, step_readout, step_phase)``,
    rad/m, the readout step being the mean over each line (its span / (samples - 1), the median line), and
    ``(n_readout, n_phase)``: the median samples per line and the number of phase grid points spanned; None
    otherwise.  The non-uniform DFT then regrids the ramp samples (:mod:`dtoc.sim.ndft`)."""
    import numpy as np

    k = np.asarray(k0_rad_per_m, dtype=np.float64)[:2]
    edges = np.cumsum([0, *adc_sizes])
    scale = max(float(np.abs(k).max()), 1e-12)
    for ro in (0, 1):
        pe = 1 - ro
        pos, steps, counts, ok = [], [], [], True
        for s, e in zip(edges[:-1], edges[1:]):
            if e - s < 3:
                continue
            if np.ptp(k[pe, s:e]) > 1e-6 * scale:  # the phase coordinate moves within the readout
                ok = False
                break
            d = np.diff(k[ro, s:e])
            if not (np.all(d > 0) or np.all(d < 0)):
                ok = False
                break
            pos.append(float(k[pe, s]))
            steps.append(float(np.abs(d).sum()) / (e - s - 1))
            counts.append(e - s)
        if not ok or len(pos) < 2:
            continue
        p = np.sort(np.asarray(pos))
        p = p[np.concatenate([[True], np.diff(p) > 1e-6 * scale])]  # distinct line positions
        dp = np.diff(p)
        step0 = float(dp.min()) if dp.size else 0.0
        if step0 <= 0 or np.max(np.abs(dp / step0 - np.rint(dp / step0))) > 1e-3:
            continue
        n_pe = int(round(float(p[-1] - p[0]) / step0)) + 1
        step_pe = float(p[-1] - p[0]) / (n_pe - 1)
        return ro, pe, float(np.median(steps)), step_pe, int(np.median(counts)), n_pe
    return None
