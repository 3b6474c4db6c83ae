"""The sequence model (IR) that every part of dtoc works on.

A :class:`SequenceIR` holds the *demanded* gradient exactly as a Pulseq interpreter plays it, on a
uniform "fine" grid with spacing ``dt_fine_s = raster_s / 2``: sample ``m`` is the played value at
``t_m = m * raster_s / 2`` measured from the start of the first block, and the played waveform is the
straight line between consecutive samples.  Even samples lie on raster edges (trapezoid and extended
trapezoid vertices, block boundaries, arbitrary-gradient ``first``/``last``), odd samples on raster
centres (arbitrary-gradient samples).  Hence the IR is exact for every gradient type Pulseq plays,
and its k-space integrals (:mod:`dtoc.seq.kspace`) carry no quadrature error.

Optimizers change only the raster-edge samples (even indices) flagged in ``free_mask``; the
raster-centre samples of a modified waveform are then the mean of their two neighbours, and the
export writes the block as an extended trapezoid with a vertex on every raster edge.

RF pulses are instantaneous rotations at their centre time; ADC samples sit at
``t_start + (i + 0.5) * dwell`` (Pulseq convention).  Units: s, mT/m, rad, Hz, rad/m.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from dtoc.errors import InputError
from dtoc.seq.geometry import EncodingGeometry, encoding_geometry


@dataclass(frozen=True)
class RFEvent:
    """An RF pulse, simulated as an instantaneous rotation at ``t_center_s``.

    Attributes:
        block: index of the block that holds it.
        t_start_s: absolute start of the pulse waveform, s.
        t_center_s: absolute time of the effective rotation (Pulseq ``rf.center``), s.
        duration_s: pulse duration, s.
        flip_angle_rad: nominal flip angle (integral of the B1 waveform), rad.
        phase_rad: phase offset, rad (includes RF spoiling increments).
        freq_offset_hz: frequency offset, Hz.
        use: Pulseq use: 'excitation', 'refocusing', 'inversion', 'saturation', 'preparation', 'undefined'.
        grad_at_center_mT_per_m: demanded gradient on (x, y, z) at ``t_center_s`` (slice selection), mT/m.
        bandwidth_hz: full width at half maximum of the pulse's spectrum (the small-tip slice / band profile), Hz;
            None when unknown (synthetic IRs).  With ``freq_offset_hz`` and ``grad_at_center_mT_per_m`` it says which
            spins the pulse acts on (:mod:`dtoc.sim.slices`: slice groups of a multi-slice sequence).
        ppm_offset_hz: the part of the pulse's frequency offset given in ppm (Pulseq 1.5 ``freq_ppm``, e.g. a
            fat-saturation pulse), in Hz at the file's B0 (pypulseq's system B0 when the file gives none); the
            pulse's band is centred at ``freq_offset_hz + ppm_offset_hz``.
    """

    block: int
    t_start_s: float
    t_center_s: float
    duration_s: float
    flip_angle_rad: float
    phase_rad: float
    freq_offset_hz: float
    use: str
    grad_at_center_mT_per_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    bandwidth_hz: float | None = None
    ppm_offset_hz: float = 0.0

    @property
    def excites(self) -> bool:
        """True for an excitation: ``use`` 'excitation', or 'undefined' -- pypulseq's and Pulseq MATLAB's
        k-space calculation (``calculate_kspace`` / ``calcKspace``) treat an undefined use as an excitation
        (docs/conventions.md); dtoc follows them and says so when it happens (``meta['rf_use_undefined']``)."""
        return self.use in ("excitation", "undefined")

    @property
    def refocuses(self) -> bool:
        """True for a refocusing pulse (``use`` 'refocusing'): k -> -k at its centre."""
        return self.use == "refocusing"


@dataclass(frozen=True)
class ADCEvent:
    """An ADC readout: ``num_samples`` samples at ``t_start_s + (i + 0.5) * dwell_s``.

    Attributes:
        block: index of the block that holds it.
        t_start_s: absolute ADC start (block start + ADC delay), s.
        num_samples: number of samples.
        dwell_s: dwell time, s.
        phase_rad: receiver phase offset, rad.
        freq_offset_hz: receiver frequency offset, Hz.
    """

    block: int
    t_start_s: float
    num_samples: int
    dwell_s: float
    phase_rad: float = 0.0
    freq_offset_hz: float = 0.0

    @property
    def sample_times_s(self) -> np.ndarray:
        """(num_samples,) absolute sample times, s."""
        return self.t_start_s + (np.arange(self.num_samples) + 0.5) * self.dwell_s


#: ADC samples per piece of :meth:`SequenceIR.nominal_kspace_rad_per_m` (its temporaries: ~230 bytes per sample)
NOMINAL_K_PIECE = 1 << 20


@dataclass
class SequenceIR:
    """One sequence, as played.

    Attributes:
        raster_s: gradient raster time, s (the fine grid is ``raster_s / 2``).
        grad_mT_per_m: (3, 2N+1) demanded gradient on x, y, z at ``t_m = m * raster_s / 2``, mT/m.
        block_edges_s: (B+1,) absolute block boundaries, s (block b spans [edges[b], edges[b+1])).
        rf: RF events in time order.
        adc: ADC events in time order.
        free_mask: (3, 2N+1) bool, True where an optimizer may change the demanded gradient
            (only even samples are used as variables).
        definitions: the file's [DEFINITIONS] (values as strings or numbers).
        fov_m: field of view per axis (x, y, z), m, when known.
        matrix: image matrix (readout, phase[, partition]) when known.
        kind: 'gre', 'epi', 'tse' or None: selects defaults of later stages.
        readout_axis / phase_axis: physical axis index (0, 1, 2) of readout / phase encoding, when known.
        source: the pypulseq Sequence this was read from or built as (the writer copies RF, ADC,
            labels and definitions from it); None for synthetic IRs.
        source_grad_mT_per_m: (3, 2N+1) the demanded gradient of ``source`` as read (the writer rewrites
            only the blocks whose gradient differs from it); None for synthetic IRs.  The reader gives the IR's
            own ``grad_mT_per_m`` array here, not a copy (a whole-sequence waveform, 48 bytes per raster step):
            an IR's waveform is replaced (:meth:`with_grad`), never written into.
        meta: free-form extra facts (spec name, echo spacing, ...), JSON-serialisable.
    """

    raster_s: float
    grad_mT_per_m: np.ndarray
    block_edges_s: np.ndarray
    rf: list[RFEvent] = field(default_factory=list)
    adc: list[ADCEvent] = field(default_factory=list)
    free_mask: np.ndarray | None = None
    definitions: dict[str, Any] = field(default_factory=dict)
    fov_m: tuple[float, float, float] | None = None
    matrix: tuple[int, ...] | None = None
    kind: str | None = None
    readout_axis: int | None = None
    phase_axis: int | None = None
    source: Any = None
    source_grad_mT_per_m: np.ndarray | None = None
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self):
        self.grad_mT_per_m = np.asarray(self.grad_mT_per_m, dtype=np.float64)
        self.block_edges_s = np.asarray(self.block_edges_s, dtype=np.float64)
        if self.grad_mT_per_m.ndim != 2 or self.grad_mT_per_m.shape[0] != 3 or self.grad_mT_per_m.shape[1] % 2 != 1:
            raise ValueError(f"grad_mT_per_m must be (3, 2N+1), got {self.grad_mT_per_m.shape}")
        if self.free_mask is None:
            self.free_mask = np.zeros(self.grad_mT_per_m.shape, dtype=bool)
        self.free_mask = np.asarray(self.free_mask, dtype=bool)

    # ---- grids -------------------------------------------------------------------------------
    @property
    def dt_fine_s(self) -> float:
        """Spacing of the fine grid (half the gradient raster), s."""
        return self.raster_s / 2.0

    @property
    def n_fine(self) -> int:
        """Number of fine-grid samples (2N+1)."""
        return self.grad_mT_per_m.shape[1]

    @property
    def duration_s(self) -> float:
        """Total duration, s."""
        return (self.n_fine - 1) * self.dt_fine_s

    @property
    def t_fine_s(self) -> np.ndarray:
        """(2N+1,) fine-grid times, s."""
        return np.arange(self.n_fine) * self.dt_fine_s

    @property
    def edge_grad_mT_per_m(self) -> np.ndarray:
        """(3, N+1) gradient at raster edges (the optimizer's variables), mT/m."""
        return self.grad_mT_per_m[:, ::2]

    # ---- ADC ---------------------------------------------------------------------------------
    @property
    def adc_times_s(self) -> np.ndarray:
        """(N_adc,) all ADC sample times in order, s."""
        if not self.adc:
            return np.zeros(0)
        return np.concatenate([a.sample_times_s for a in self.adc])

    @property
    def n_adc_samples(self) -> int:
        return int(sum(a.num_samples for a in self.adc))

    def kspace_rad_per_m(self, grad_mT_per_m=None, times_s=None):
        """k-space (rad/m) of ``grad_mT_per_m`` (default: this IR's demanded = nominal gradient).

        Args:
            grad_mT_per_m: (..., 3, 2N+1) numpy array or torch tensor on this IR's fine grid.
            times_s: query times (default: every ADC sample).
        Returns:
            (..., 3, Q) torch tensor (float64 for numpy input), differentiable.
        """
        g = self.grad_mT_per_m if grad_mT_per_m is None else grad_mT_per_m
        t = self.adc_times_s if times_s is None else times_s
        from dtoc.seq.kspace import kspace_at  # torch: imported only where k-space is computed

        return kspace_at(g, self.dt_fine_s, t, [r.t_center_s for r in self.rf], [r.use for r in self.rf])

    def nominal_kspace_rad_per_m(self) -> np.ndarray:
        """(3, N_adc) target k-space at every ADC sample, rad/m (from the demanded = ideal gradient).

        More than :data:`NOMINAL_K_PIECE` ADC samples are computed piece by piece (a 5-minute 3D file: 5.8 M
        samples, ~1.3 GB of per-sample temporaries at once otherwise): the same numbers bit for bit, as each
        sample's k is its own running integral and reset (:func:`dtoc.seq.kspace.kspace_at`), whatever the other
        query times; each piece integrates the waveform again (a pass per 2^20 samples)."""
        t = self.adc_times_s
        if len(t) <= NOMINAL_K_PIECE:
            return self.kspace_rad_per_m().numpy()
        out = np.empty((3, len(t)))
        for i in range(0, len(t), NOMINAL_K_PIECE):
            out[:, i : i + NOMINAL_K_PIECE] = self.kspace_rad_per_m(times_s=t[i : i + NOMINAL_K_PIECE]).numpy()
        return out

    @property
    def dk_rad_per_m(self) -> np.ndarray | None:
        """(3,) k-space grid step 2*pi/FOV per axis, rad/m (a 3D-encoded file without definitions: of the grid
        inferred from its ADC k, ``meta['grid3d']``; None when the FOV is unknown)."""
        if self.fov_m is None:
            g = self.meta.get("grid3d")
            return None if g is None else np.array([2 * np.pi / f for f in g["fov_m"]])
        return np.array([2 * np.pi / f if f else np.inf for f in self.fov_m])

    @property
    def geometry(self) -> EncodingGeometry | None:
        """The Cartesian encoding geometry (matrix by readout/phase axis, FOV, voxel, dk; docs/conventions.md),
        or None when the sequence declares no FOV / matrix."""
        return encoding_geometry(self.fov_m, self.matrix, self.readout_axis, self.phase_axis)

    @property
    def phase_image_dim(self) -> int:
        """Dimension of a (ny, nx) image along which this sequence phase-encodes (-2 rows when unknown)."""
        geo = self.geometry
        return geo.phase_image_dim if geo is not None else -2

    def require_geometry(self, what: str) -> EncodingGeometry:
        """:attr:`geometry`, or an InputError naming ``what`` needs it."""
        geo = self.geometry
        if geo is None:
            raise InputError(
                f"{what}: no image grid for this sequence (its ADC samples are on none dtoc can reconstruct: the "
                "notes say why); "
                "'dtoc predict' gives its k-space figures"
            )
        return geo

    # ---- edits -------------------------------------------------------------------------------
    def with_grad(self, grad_mT_per_m: np.ndarray) -> SequenceIR:
        """A copy with another demanded gradient (same grid); ``source`` is shared, not copied, and so is the free
        mask, as a read-only view (3 bytes per fine sample: a 4.9 min MPRAGE's 177 MB, held through the export)."""
        g = np.asarray(grad_mT_per_m, dtype=np.float64)
        if g.shape != self.grad_mT_per_m.shape:
            raise ValueError(f"gradient shape {g.shape} != {self.grad_mT_per_m.shape}")
        new = copy.copy(self)
        new.grad_mT_per_m = g
        new.free_mask = self.free_mask.view()
        new.free_mask.flags.writeable = False
        new.meta = dict(self.meta)
        return new

    def grad_at(self, t_s, grad_mT_per_m: np.ndarray | None = None) -> np.ndarray:
        """(3, len(t)) the demanded gradient at times ``t_s`` (linear between fine samples, as ``np.interp`` on
        :attr:`t_fine_s`, held at the ends), without building the fine time axis (long files: 37M samples)."""
        g = self.grad_mT_per_m if grad_mT_per_m is None else grad_mT_per_m
        return interp_fine(g, np.atleast_1d(np.asarray(t_s, dtype=np.float64)), self.dt_fine_s)

    def block_of_fine_index(self, m: np.ndarray) -> np.ndarray:
        """Block index of fine-grid samples (a boundary sample belongs to the block it starts)."""
        t = np.asarray(m) * self.dt_fine_s
        return np.clip(np.searchsorted(self.block_edges_s, t + 1e-12, side="right") - 1, 0, len(self.block_edges_s) - 2)


def interp_fine(g: np.ndarray, t_s: np.ndarray, dt_fine_s: float) -> np.ndarray:
    """(..., len(t)) samples ``g`` (..., M) of the fine grid ``m * dt_fine_s`` at times ``t_s``: the numbers
    ``np.interp(t, np.arange(M) * dt_fine_s, g)`` gives (its interval search, slope and exact-node rule, held at
    the ends), without building the fine time axis."""
    n = g.shape[-1]
    t = np.asarray(t_s, dtype=np.float64)
    if n == 1:
        return np.repeat(g[..., :1], len(t), axis=-1)
    j = np.clip(np.floor(t / dt_fine_s).astype(np.int64), 0, n - 2)
    j = np.where((j > 0) & (j * dt_fine_s > t), j - 1, j)  # xp[j] <= t < xp[j + 1], as a binary search finds
    j = np.where((j < n - 2) & ((j + 1) * dt_fine_s <= t), j + 1, j)
    x0, x1 = j * dt_fine_s, (j + 1) * dt_fine_s
    y0, y1 = g[..., j], g[..., j + 1]
    out = (y1 - y0) / (x1 - x0) * (t - x0) + y0
    out = np.where(t == x0, y0, out)
    out = np.where(t <= 0.0, g[..., :1], out)
    return np.where(t >= (n - 1) * dt_fine_s, g[..., -1:], out)


def edges_to_fine(edge_grad):
    """Expand raster-edge samples (..., N+1) to the fine grid (..., 2N+1) by linear interpolation.

    Works for numpy arrays and torch tensors (differentiable).
    """
    import torch

    if isinstance(edge_grad, torch.Tensor):
        mid = 0.5 * (edge_grad[..., 1:] + edge_grad[..., :-1])
        out = torch.stack([edge_grad[..., :-1], mid], dim=-1).reshape(edge_grad.shape[:-1] + (-1,))
        return torch.cat([out, edge_grad[..., -1:]], dim=-1)
    e = np.asarray(edge_grad)
    out = np.empty(e.shape[:-1] + (2 * e.shape[-1] - 1,), dtype=e.dtype)
    out[..., ::2] = e
    out[..., 1::2] = 0.5 * (e[..., 1:] + e[..., :-1])
    return out
