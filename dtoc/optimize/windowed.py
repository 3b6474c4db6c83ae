"""Windowed pre-compensation of long sequences: memory bounded by one window, time a sum over windows.

The warm start's objective (:func:`dtoc.optimize.optimizer.linear_objective`: k at every ADC sample, the
moment before every RF pulse, G during RF, a small change penalty) is a sum over excitation periods, and a
period's terms depend on the demanded waveform only within the hardware's memory
(:func:`dtoc.hardware.memory.memory_s`).  So the sequence is solved one excitation period (the *core*) at a
time, in time order (receding horizon):

* the window is ``[core start - horizon, core end + lookahead]`` (block boundaries; the lookahead reaches at
  least the next period's excitation; a part of a period starts ``horizon`` before its reference,
  :func:`part_reference_s`): the committed waveform before the core (history) and the base
  waveform after it are fixed, only the core's free edges move;
* the core's terms: its ADC samples (exact k: the core begins with an excitation, which resets k), the
  moment and the G-during-RF of every pulse after its own excitation up to the next period's excitation,
  the change penalty on its own samples -- each term counted in exactly one window, with the whole
  sequence's normalisation, so that the windows' objectives add up to the whole-sequence objective;
* with an affine hardware chain the residual vector is ``r0 + J d`` exactly; ``J`` depends only on the
  period's timing (not on the gradient amplitudes), so periods of one structure (every TR of a train)
  share one Jacobian, built from the chain's impulse responses (:mod:`dtoc.optimize.window_jacobian`:
  three forwards and a lookup per row and column), and one Cholesky factor of the normal matrix;
* each window's exact quadratic is then minimised: by back-substitution when the unconstrained optimum
  is within the limits, else by ADMM on the box and slew constraints (the normal matrix plus the
  constraints' Gram matrix factored once per structure), followed by the exact projection; a window is
  left unchanged if that is not better.

Edges in long idle stretches (more than :data:`PAD_S` from any non-zero base gradient or ADC sample) are
held at the base value (zero): a delay of a second adds no variables.  What is left out against the
whole-sequence solve: the part of the hardware's memory beyond the horizon, and the future periods that
cannot answer back.  Cost and error against the whole-sequence solve: docs/benchmarks.md ("Long
sequences"), docs/optimize.md.  Units: mT/m, s, rad/m.
"""

from __future__ import annotations

import hashlib
import math
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
import torch

from dtoc.optimize import window_jacobian as WJ
from dtoc.optimize.limits import EdgeProjector, Limits, edges_to_played, fine_free_mask
from dtoc.optimize.loss import LossContext
from dtoc.seq.ir import SequenceIR, edges_to_fine
from dtoc.seq.kspace import kspace_at
from dtoc.util.blas import on_torch_threads

#: a period with more free variables than this is not solved densely (the whole-sequence path is used)
DENSE_MAX = 6000
#: a period with more than DENSE_MAX free variables is cut into parts of at most this many (the Jacobian's cost grows
#: with the square of a core's size and its factorisation with the cube: small parts are faster in all; bench rows in
#: docs/optimize.md, "Long sequences")
PART_MAX = 1500
#: solutions of the most recent distinct window problems kept for identical later windows
SOLVES_KEPT = 32
#: the per-structure matrices kept, bytes (least recently used dropped beyond it; a structure needs up to ~4 dense
#: n_free^2 float64 matrices: 1.15 GB at DENSE_MAX)
STRUCTURES_KEPT_BYTES = 3_000_000_000
#: ADMM iterations of one window at most
ADMM_MAX_ITER = 2000
#: ADMM's stopping tolerance (relative primal and dual residuals), and the tighter one of a window whose k error is
#: still above :data:`REFINE_SHARE` of the run's k tolerance after it (:func:`windowed_warm_start`, ``k_tol_dk``)
ADMM_TOL = 1e-4
ADMM_TOL_REFINE = 1e-6
REFINE_SHARE = 0.5
#: a refined window stops when its largest k error fell by less than REFINE_MIN_GAIN over REFINE_PATIENCE checks
REFINE_PATIENCE = 5
REFINE_MIN_GAIN = 0.05
#: a structure whose last windows needed the limits tries the unconstrained optimum again every this many windows
DIRECT_RETRY = 16
#: edges farther than this from any non-zero base gradient or ADC sample are held at the base value, s
PAD_S = 2e-3


@dataclass
class Window:
    """One excitation period (core) and its context, as block indices ``[b0, b1)``."""

    core: tuple[int, int]
    sub: tuple[int, int]
    adc: list[int]  # indices into ir.adc
    rf: list[int]  # indices into ir.rf kept in the window (k resets, moments)
    moment_rf: list[int]  # RF pulses whose moment counts here
    rfterm_rf: list[int]  # RF pulses whose G-during-RF counts here
    #: the core begins an excitation period (False: a part of a long period, k carried in from the part before)
    starts_period: bool = True


@dataclass
class WindowStats:
    windows: int = 0
    structures: int = 0
    max_free: int = 0
    direct: int = 0
    admm_iters: int = 0
    reused: int = 0
    groups: dict = field(default_factory=dict)  # solve key -> [window indices solved as one]
    horizon_s: float = 0.0
    lookahead_s: float = 0.0
    times_s: dict = field(default_factory=dict)
    admm_capped: int = 0  # windows whose ADMM stopped at its iteration cap (not converged)
    refined: int = 0  # windows whose ADMM ran on to ADMM_TOL_REFINE (k error above REFINE_SHARE of the tolerance)
    #: per ADC sample / per RF pulse (its moment; nan: none), the k error of its window's unconstrained optimum, dk
    #: (the window's quadratic without the limits: what the free edges could reach there; nan where not solved)
    unconstrained_adc_dk: np.ndarray | None = None
    unconstrained_moment_dk: np.ndarray | None = None
    #: per ADC sample, its k error in its window's model at the committed solution, dk (what the window saw; the whole
    #: sequence's realization differs by the hardware's memory beyond the horizon and the later windows' changes)
    window_adc_dk: np.ndarray | None = None
    #: per RF pulse, the k error of its moment in its window's model at the committed solution, dk (nan: none)
    window_moment_dk: np.ndarray | None = None

    def as_dict(self) -> dict:
        return {
            "windows": self.windows,
            "distinct_structures": self.structures,
            "max_free_variables_per_window": self.max_free,
            "windows_solved_directly": self.direct,
            "admm_iterations": self.admm_iters,
            "windows_refined": self.refined,
            "windows_reusing_a_solve": self.reused,
            "solved_as_one": solved_as_one(self.groups),
            "horizon_s": self.horizon_s,
            "lookahead_s": self.lookahead_s,
            "times_s": {k: round(v, 3) for k, v in self.times_s.items()},
        }


def solved_as_one(groups: dict, max_groups: int = 20) -> list[dict]:
    """The manifest's record of the windows that shared one solve: per group (largest first, at most
    ``max_groups``) the number of windows and their indices as ``[first, last]`` runs."""
    out = []
    for idx in sorted(groups.values(), key=lambda v: (-len(v), v[0]))[:max_groups]:
        if len(idx) < 2:
            break
        runs: list[list[int]] = []
        for i in idx:
            if runs and i == runs[-1][1] + 1:
                runs[-1][1] = i
            else:
                runs.append([i, i])
        out.append({"windows": len(idx), "runs": runs})
    return out


def period_starts(ir: SequenceIR) -> list[int]:
    """First block of every excitation period (block 0, then every block holding an exciting pulse)."""
    return [0] + sorted({r.block for r in ir.rf if r.excites} - {0})


def plan_windows(
    ir: SequenceIR,
    horizon_s: float,
    lookahead_s: float,
    free: np.ndarray | None = None,
    pad_s: float = PAD_S,
    dense_max: int = DENSE_MAX,
    part_max: int = PART_MAX,
) -> list[Window]:
    """Cores = excitation periods (from the block of one exciting pulse to the next's), a period with more than
    ``dense_max`` free variables (``free`` given) cut into parts of at most ``part_max`` (:func:`core_blocks`);
    their windows.
    Linear in the number of events: RF and ADC events are in time order, found per core by bisection."""
    edges = ir.block_edges_s
    nb = len(edges) - 1
    cores = core_blocks(ir, free, pad_s, dense_max, part_max) if free is not None else _period_cores(ir)
    rf_block = np.array([r.block for r in ir.rf], dtype=np.int64)
    adc_block = np.array([a.block for a in ir.adc], dtype=np.int64)

    def in_blocks(blocks: np.ndarray, b0: int, b1: int) -> list[int]:
        return list(range(int(np.searchsorted(blocks, b0)), int(np.searchsorted(blocks, b1))))

    out = []
    for b0, b1, starts_period in cores:
        t0, t1 = edges[b0], edges[b1]
        # the history: the hardware's causal memory before the earliest time whose realized gradient the window
        # integrates -- the core's start, or a part's reference (:func:`part_reference_s`: its acausal memory
        # earlier); a history cut at the core's start - horizon would leave the part's k without the memory of
        # the waveform before it (the KCL GIRF's 25 ms: k errors of 0.06 dk that the window saw as 1e-4)
        t_hist = t0 if starts_period else t0 - ir.raster_s - lookahead_s
        sb0 = int(max(0, np.searchsorted(edges, t_hist - horizon_s, side="right") - 1))
        # the next period's excitation (its moment and G-during-RF depend on this core)
        nxt = [i for i in in_blocks(rf_block, b1, b1 + 1) if ir.rf[i].excites] if b1 < nb else []
        t_end = t1 + lookahead_s
        if nxt:
            t_end = max(t_end, edges[b1 + 1])
        sb1 = int(min(nb, np.searchsorted(edges, t_end - 1e-12, side="left")))
        sb1 = max(sb1, b1)
        in_core = in_blocks(rf_block, b0, b1)
        first = in_core[0] if (in_core and b0 > 0 and ir.rf[in_core[0]].excites) else None
        rf_idx = in_core + nxt[:1]
        own = [i for i in rf_idx if i != first]
        moment = [i for i in own if i > 0]  # the sequence's first pulse has no moment term
        out.append(Window((b0, b1), (sb0, sb1), in_blocks(adc_block, b0, b1), rf_idx, moment, own, starts_period))
    return out


def _period_cores(ir: SequenceIR) -> list[tuple[int, int, bool]]:
    starts = period_starts(ir)
    return [(b0, b1, True) for b0, b1 in zip(starts, starts[1:] + [len(ir.block_edges_s) - 1])]


def _block_counts(free: np.ndarray, act: np.ndarray, e: np.ndarray) -> np.ndarray:
    """Free variables (free edges within activity) of the blocks whose edges are ``[e[i], e[i + 1])``."""
    return np.array([np.count_nonzero(free[:, a:b] & act[None, a:b]) for a, b in zip(e[:-1], e[1:])], dtype=np.int64)


def core_blocks(
    ir: SequenceIR, free: np.ndarray, pad_s: float = PAD_S, dense_max: int = DENSE_MAX, part_max: int = PART_MAX
) -> list[tuple[int, int, bool]]:
    """The cores ``(b0, b1, starts_period)``: every excitation period, one with more than ``dense_max`` free
    variables cut at block boundaries into parts of at most ``part_max`` (a single larger block is a part of its
    own; above ``dense_max`` ``why_not_windowed`` refuses it), each cut preferably right after a block holding an RF pulse (the train's
    refocusing pulses: the moment before a pulse then counts in the core that plays its crusher).  Blocks are
    counted only in the periods that are cut."""
    act = active_edges(ir, pad_s)
    e = np.round(ir.block_edges_s / ir.raster_s).astype(int)
    periods = _period_cores(ir)
    n_per = _block_counts(free, act, e[[p[0] for p in periods] + [len(e) - 1]])
    rf_after = np.zeros(len(e) + 1, dtype=bool)
    rf_after[np.array([r.block for r in ir.rf], dtype=np.int64) + 1] = True
    out = []
    for (b0, b1, _), n in zip(periods, n_per):
        if n <= dense_max:
            out.append((b0, b1, True))
            continue
        per = _block_counts(free, act, e[b0 : b1 + 1])
        s = b0
        while s < b1:
            cs = np.cumsum(per[s - b0 :])
            end = s + max(1, int(np.searchsorted(cs, part_max, side="right")))
            if end < b1:
                cut = np.flatnonzero(rf_after[s + 1 : end + 1])
                if cut.size:
                    end = s + 1 + int(cut[-1])
            out.append((s, end, s == b0))
            s = end
    return out


def core_free_counts(
    ir: SequenceIR, free: np.ndarray, pad_s: float = PAD_S, dense_max: int = DENSE_MAX, part_max: int = PART_MAX
) -> np.ndarray:
    """Free variables of every core of :func:`core_blocks` (a value above ``part_max``: a single block)."""
    act = active_edges(ir, pad_s)
    e = np.round(ir.block_edges_s / ir.raster_s).astype(int)
    cores = core_blocks(ir, free, pad_s, dense_max, part_max)
    return _block_counts(free, act, e[[c[0] for c in cores] + [len(e) - 1]])


def active_edges(ir: SequenceIR, pad_s: float) -> np.ndarray:
    """(N+1,) bool: raster edges within ``pad_s`` of a non-zero base gradient (any axis) or an ADC sample.
    Memory: the result and one (3, N+1) bool temporary (the busy runs are dilated run by run, no index arrays)."""
    busy = np.any(ir.edge_grad_mT_per_m != 0, axis=0)
    n = busy.size
    for a in ir.adc:
        i0 = int(np.floor(a.t_start_s / ir.raster_s))
        i1 = int(np.ceil((a.t_start_s + a.num_samples * a.dwell_s) / ir.raster_s))
        busy[max(i0, 0) : min(i1, n - 1) + 1] = True
    pad = int(math.ceil(pad_s / ir.raster_s))
    out = np.zeros(n, dtype=bool)
    for s, e in _runs(busy):  # [s, e) of busy edges, merged once dilated
        out[max(s - pad, 0) : min(e + pad, n)] = True
    return out


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """Runs ``[start, end)`` of True in a 1-D bool array (one int8 difference, indices per run only)."""
    if mask.size == 0:
        return []
    d = np.diff(mask.view(np.int8))
    starts = np.flatnonzero(d == 1) + 1
    ends = np.flatnonzero(d == -1) + 1
    if mask[0]:
        starts = np.r_[0, starts]
    if mask[-1]:
        ends = np.r_[ends, mask.size]
    return list(zip(starts.tolist(), ends.tolist()))


def period_free_counts(ir: SequenceIR, free: np.ndarray, pad_s: float = PAD_S) -> np.ndarray:
    """Free variables of every excitation period (core) in windowed mode (cheap: no window is built, no
    whole-sequence temporary beyond one bool mask)."""
    act = active_edges(ir, pad_s)
    edges = ir.block_edges_s
    e = np.round(edges[period_starts(ir) + [len(edges) - 1]] / ir.raster_s).astype(int)
    return _block_counts(free, act, e)


class _Scales:
    """Per-term residual weights with the whole sequence's normalisation (see loss.py)."""

    def __init__(self, ir: SequenceIR, weights, ctx: LossContext):
        n_adc = max(ir.n_adc_samples, 1)
        n_mom = max(len(ir.rf) - 1, 1)
        n_rf = max(int(ctx.rf_mask.sum()), 1)
        gref = ctx.g_ref_mT_per_m
        dk = ctx.dk_rad_per_m.cpu().numpy().astype(np.float64)
        inv = np.where(np.isfinite(dk), 1.0 / dk, 0.0)
        self.k = math.sqrt(weights.kspace / n_adc) * inv
        self.m = math.sqrt(weights.moment / n_mom) * inv
        self.rf = math.sqrt(weights.rf / n_rf) / gref
        self.reg = math.sqrt(weights.reg / (3 * ir.n_fine)) / gref
        self.k_axes = np.flatnonzero(inv > 0)
        # a residual row divided by these is a k error in dk (0: the term is not weighted, no figure)
        self.k_unit = math.sqrt(weights.kspace / n_adc)
        self.m_unit = math.sqrt(weights.moment / n_mom)

    def k_errors_dk(self, rd: np.ndarray, n_adc: int, n_mom: int) -> tuple[np.ndarray, np.ndarray]:
        """Per ADC sample and per moment, the k error (norm over the encoded axes, as the whole solve's), dk, of the
        window's k-space residual rows ``rd`` (:func:`window_residual`'s order: the ADC samples' rows then the moments', axis by axis)."""
        na = self.k_axes.size
        out = []
        for rows, n, unit in (
            (rd[: na * n_adc], n_adc, self.k_unit),
            (rd[na * n_adc : na * (n_adc + n_mom)], n_mom, self.m_unit),
        ):
            if n == 0 or na == 0 or unit <= 0:
                out.append(np.full(n, np.nan))
            else:
                out.append(np.sqrt((rows.reshape(na, n) ** 2).sum(axis=0)) / unit)
        return out[0], out[1]


def _own_errors_dk(sc, rd: np.ndarray, n_adc: int, n_mom: int, core_adc: slice, n_guard_mom: int):
    """(ADC samples, moments) of ``sc.k_errors_dk`` (:meth:`_Scales.k_errors_dk`) that are the window's own: its
    core's ADC rows ``core_adc`` and its moments after the ``n_guard_mom`` guarded ones (a part's rows of the parts
    before)."""
    ka, km = sc.k_errors_dk(rd, n_adc, n_mom)
    return ka[core_adc], km[n_guard_mom:]


#: windows of one structure whose unconstrained optima's k errors are computed together (:class:`_UnconstrainedErrors`)
UNCONSTRAINED_BATCH = 64


class _UnconstrainedErrors:
    """Per ADC sample and moment, the k error of its window's unconstrained optimum (the manifest's 'fixed' or
    'limits' naming, :func:`dtoc.optimize.run.windowed_solver_record`): a diagnostic, not on the chain from one
    window to the next, so it is computed for up to :data:`UNCONSTRAINED_BATCH` consecutive windows of one
    structure at a time, one matrix product ``J_k [d_1 ... d_B]`` over the Jacobian's k rows (bound by arithmetic)
    instead of a matrix-vector product per window (bound by reading ``J``: the window loop's cost in a long train,
    docs/benchmarks.md "Long sequences").  Memory: the batch's optima and k rows, and one structure's ``J`` held."""

    def __init__(self, sc: _Scales, st: WindowStats, batch: int = UNCONSTRAINED_BATCH):
        self.sc, self.st, self.batch = sc, st, batch
        self.key: str | None = None
        self.J: np.ndarray | None = None
        self.Hinv: np.ndarray | None = None
        self.items: list[tuple] = []

    def add(self, key, c, r0d, grad0, n_adc, n_mom, sel_adc, core_adc, moment_rf, n_guard_mom) -> None:
        """A window: its structure ``key`` and matrices ``c`` (``J``, ``Hinv``), residual rows ``r0d``, gradient
        ``grad0`` (its unconstrained optimum is ``-Hinv grad0``, computed here for the batch in one product), sample
        and moment counts (its rows' layout), where its core's samples and moments go (``sel_adc``, ``core_adc``,
        ``moment_rf``; its first ``n_guard_mom`` moments are a part's guarded ones)."""
        if key != self.key or len(self.items) >= self.batch:
            self.flush()
        self.key, self.J, self.Hinv = key, c["J"], c["Hinv"]
        nk = len(self.sc.k_axes) * (n_adc + n_mom)
        self.items.append((r0d[:nk].copy(), grad0, n_adc, n_mom, sel_adc, core_adc, moment_rf, n_guard_mom))

    def flush(self) -> None:
        if not self.items:
            return
        J, n_adc, n_mom = self.J, self.items[0][2], self.items[0][3]
        ua_all, um_all = self.st.unconstrained_adc_dk, self.st.unconstrained_moment_dk
        assert J is not None and ua_all is not None and um_all is not None
        rk = np.stack([it[0] for it in self.items], axis=1)
        assert self.Hinv is not None
        rk -= J[: rk.shape[0]] @ (self.Hinv @ np.stack([it[1] for it in self.items], axis=1))
        for j, (_, _, _, _, sel_adc, core_adc, moment_rf, g) in enumerate(self.items):
            ua_all[sel_adc], um_all[moment_rf] = _own_errors_dk(self.sc, rk[:, j], n_adc, n_mom, core_adc, g)
        self.items, self.J, self.Hinv, self.key = [], None, None, None


@on_torch_threads
def windowed_warm_start(
    ir: SequenceIR,
    hardware,
    limits: Limits,
    free: np.ndarray,
    weights,
    ctx: LossContext,
    *,
    horizon_s: float,
    lookahead_s: float,
    pad_s: float = PAD_S,
    dtype: torch.dtype = torch.float64,
    device: str = "cpu",
    progress: Callable | None = None,
    reuse: bool = True,
    dense_max: int = DENSE_MAX,
    part_max: int = PART_MAX,
    k_tol_dk: float | None = None,
    realize_range: bool = True,
) -> tuple[np.ndarray, WindowStats]:
    """Solve the warm start's objective period by period (module doc).

    Args:
        ir: the base sequence; hardware: an affine chain (:func:`dtoc.hardware.memory.is_affine`).
        free: (3, N+1) optimizable edges (as :func:`dtoc.optimize.run.free_edges`).
        weights: :class:`~dtoc.optimize.config.LossWeights` (image, amplitude, slew ignored).
        ctx: the run's :class:`~dtoc.optimize.loss.LossContext` (nominal k at the ADC samples and before
            the RF pulses, k unit per axis, RF samples, gradient normalisation).
        horizon_s / lookahead_s: history kept before / base waveform kept after each core.
        reuse: a window whose problem equals an earlier one's (:func:`_solve_key`) takes its solution
            (``WindowStats.solved_as_one`` lists them).
        dense_max / part_max: a period with more free variables than ``dense_max`` is cut into parts of at most
            ``part_max`` (:func:`core_blocks`).
        k_tol_dk: the run's k tolerance, dk: a window whose ADMM solution leaves a core sample or moment above
            :data:`REFINE_SHARE` of it runs ADMM on to :data:`ADMM_TOL_REFINE` (None: every window stops at
            :data:`ADMM_TOL`).
        realize_range: a window's residual realizes the gradient only on the fine samples its rows read, by one
            FFT convolution with the chain's impulse response (:class:`~dtoc.optimize.window_jacobian.RangeRealizer`,
            where the chain allows it); False: the chain on the whole window (the same figures up to round-off).
    Returns:
        (3, N+1) edges within the limits, and :class:`WindowStats`.
    Raises:
        ValueError: a single block has more than ``dense_max`` free variables.

    numpy's and scipy's dense products run on torch's thread count (the run's ``threads``:
    :mod:`dtoc.util.blas`).
    """
    import time

    t_all = time.time()
    st = WindowStats(horizon_s=horizon_s, lookahead_s=lookahead_s)
    windows = plan_windows(ir, horizon_s, lookahead_s, free, pad_s, dense_max, part_max)
    st.windows = len(windows)
    dtf = ir.dt_fine_s
    sc = _Scales(ir, weights, ctx)
    base_fine = np.asarray(ir.grad_mT_per_m, dtype=np.float64)
    k0_full = ctx.k0_rad_per_m.cpu().numpy()
    adc_start = np.concatenate([[0], np.cumsum([a.num_samples for a in ir.adc])]).astype(int)
    t_mom_all = np.array([r.t_center_s - 1e-9 for r in ir.rf])
    # the nominal moment before pulse i is the context's column i - 1 (the first pulse has no moment term)
    m0_ctx = ctx.k0_moment_rad_per_m
    m0_full = np.zeros((3, len(ir.rf)))
    if m0_ctx is not None:
        m0_full[:, 1:] = m0_ctx.cpu().numpy()
    act = active_edges(ir, pad_s)  # (N+1,) bool; free edges outside it are held
    # the only whole-sequence array of the solve: the edges, committed as we go (the played waveform of a window is
    # rebuilt from them and the base: :func:`_played_window`)
    edges = np.array(ir.edge_grad_mT_per_m, dtype=np.float64)
    cache = _StructureCache(STRUCTURES_KEPT_BYTES)
    # solve key -> the change of the window's edges; the last SOLVES_KEPT only (memory)
    solved: OrderedDict[str, np.ndarray] = OrderedDict()
    tt = {"setup": 0.0, "jacobian": 0.0, "residual": 0.0, "solve": 0.0}
    st.unconstrained_adc_dk = np.full(ir.n_adc_samples, np.nan)
    st.unconstrained_moment_dk = np.full(len(ir.rf), np.nan)
    st.window_adc_dk = np.full(ir.n_adc_samples, np.nan)
    st.window_moment_dk = np.full(len(ir.rf), np.nan)
    # a part of a period (not its first): the realized k at its start, carried from the parts before (rad/m), and
    # the nominal k at every part's end (the next part's k must stay reachable)
    k_in = np.zeros(3)
    part_end = [i for i in range(len(windows) - 1) if not windows[i + 1].starts_period]
    k_end_nom = _nominal_k(ir, [ir.block_edges_s[windows[i].core[1]] for i in part_end])
    k_end = dict(zip(part_end, k_end_nom.T))
    t_rf = np.array([r.t_center_s for r in ir.rf])
    adc_block = np.array([a.block for a in ir.adc], dtype=np.int64)
    t_ref = 0.0
    unconstrained = _UnconstrainedErrors(sc, st)
    be = ir.block_edges_s
    w_max = max((int(round(be[w.sub[1]] / dtf)) - int(round(be[w.sub[0]] / dtf)) + 1 for w in windows), default=0)
    realizer = WJ.RangeRealizer.for_chain(hardware, dtf, w_max, dtype, device) if realize_range and w_max else None
    for wi, w in enumerate(windows):
        t0 = time.time()
        be = ir.block_edges_s
        n_guard = (0, 0)  # a part's guarded ADC rows and moments (first in their blocks)
        if w.starts_period:  # k of the period's parts counts from its excitation (the sequence's start: none)
            exc = [i for i in w.rf if ir.rf[i].excites and ir.rf[i].block == w.core[0]]
            t_ref, k_in = (ir.rf[exc[0]].t_center_s if exc else be[w.core[0]]), np.zeros(3)
        else:
            t_from, t_ref = t_ref, part_reference_s(ir, w, lookahead_s, t_ref)
            k_in = carried_k(
                ir, hardware, edges, base_fine, free, act, t_from, t_ref, k_in,
                int(round(be[w.core[0]] / ir.raster_s)), horizon_s, lookahead_s,
            )  # fmt: skip
        m0 = int(round(be[w.sub[0]] / dtf))
        m1 = int(round(be[w.sub[1]] / dtf))
        e0, e1 = m0 // 2, m1 // 2
        ec0, ec1 = int(round(be[w.core[0]] / ir.raster_s)), int(round(be[w.core[1]] / ir.raster_s))
        fr = np.zeros((3, e1 - e0 + 1), dtype=bool)
        fr[:, ec0 - e0 : ec1 - e0] = free[:, ec0:ec1] & act[None, ec0:ec1]
        n_free = int(fr.sum())
        st.max_free = max(st.max_free, n_free)
        if n_free == 0:
            continue
        if n_free > dense_max:
            raise ValueError(f"window {wi} (one block) has {n_free} free variables (> {dense_max})")
        tsub = be[w.sub[0]]
        x_sub = edges[:, e0 : e1 + 1].copy()
        fine_sub = _played_window(edges, base_fine, free, act, e0, e1, ec0)
        fmask = fine_free_mask(fr)
        # the limits bind the core's edges and their fixed neighbours only: project there
        rs = slice(max(ec0 - e0 - 1, 0), min(ec1 - e0 + 2, fr.shape[1]))
        fr_r = fr[:, rs]
        P = EdgeProjector(x_sub[:, rs], fr_r, ir.raster_s, limits)
        rf_c = [ir.rf[i].t_center_s - tsub for i in w.rf]
        rf_u = [ir.rf[i].use for i in w.rf]
        t_adc = np.concatenate([ir.adc[i].sample_times_s for i in w.adc]) - tsub if w.adc else np.zeros(0)
        sel_adc: np.ndarray | list[int] = (
            np.concatenate([np.arange(adc_start[i], adc_start[i + 1]) for i in w.adc]) if w.adc else []
        )
        k0 = k0_full[:, sel_adc] if w.adc else np.zeros((3, 0))
        t_mom = t_mom_all[w.moment_rf] - tsub
        mom0 = m0_full[:, w.moment_rf]
        if not w.starts_period:  # k from the part's reference (a reset there) plus the carried k, signed by the pulses
            # the samples and moments of the parts before, from the reference on: this core moves their k too
            # (the hardware's acausal memory); guarded here (their residual held at what is committed: a change
            # there is penalised, not their remaining error chased), scored in their own windows
            g_adc = range(int(np.searchsorted(adc_block, w.sub[0])), int(np.searchsorted(adc_block, w.core[0])))
            # each readout by its first, middle and last sample, weighted as its samples together (the change a
            # later core makes there is smooth: the chain's acausal tail)
            sg = [
                adc_start[i] + j
                for i in g_adc
                for j in sorted({0, ir.adc[i].num_samples // 2, ir.adc[i].num_samples - 1})
                if ir.adc[i].sample_times_s[j] >= t_ref
            ]
            row_w = np.ones(t_adc.size)
            if sg:
                tg = np.concatenate([ir.adc[i].sample_times_s for i in g_adc])
                s_all = np.concatenate([np.arange(adc_start[i], adc_start[i + 1]) for i in g_adc])
                tg = tg[np.searchsorted(s_all, sg)]
                n_per = np.array([ir.adc[int(np.searchsorted(adc_start, j, side="right")) - 1].num_samples for j in sg])
                t_adc = np.r_[tg - tsub, t_adc]
                k0 = np.concatenate([k0_full[:, sg], k0], axis=1)
                row_w = np.r_[np.sqrt(n_per / 3.0), row_w]
            g_mom = [i for i in _pulses_between(t_rf, t_ref + 1e-9, be[w.core[0]]) if i > 0]
            t_mom = np.r_[t_mom_all[g_mom] - tsub, t_mom]
            mom0 = np.concatenate([m0_full[:, g_mom], mom0], axis=1)
            n_guard = (len(sg), len(g_mom))
            pre = [ir.rf[i] for i in _pulses_between(t_rf, t_ref, be[w.core[0]])]
            rf_c = [r.t_center_s - tsub for r in pre] + rf_c
            rf_u = [r.use for r in pre] + rf_u
            if wi in k_end:  # the part's end: one more k row (weighted as an ADC sample)
                t_adc = np.r_[t_adc, be[w.core[1]] - tsub]
                k0 = np.concatenate([k0, k_end[wi][:, None]], axis=1)
                row_w = np.r_[row_w, 1.0]
            sk = sc.k[:, None] * row_w[None, :]  # (3, rows)
            k0 = k0 - carry_sign(t_adc, rf_c, rf_u)[None, :] * k_in[:, None]
            mom0 = mom0 - carry_sign(t_mom, rf_c, rf_u)[None, :] * k_in[:, None]
            rf_c, rf_u = [t_ref - tsub] + rf_c, ["excitation"] + rf_u
        rfm = np.zeros(m1 - m0 + 1, dtype=bool)
        tf = np.arange(m1 - m0 + 1) * dtf
        for i in w.rfterm_rf:
            r = ir.rf[i]
            rfm |= (tf >= r.t_start_s - tsub - 1e-12) & (tf <= r.t_start_s + r.duration_s - tsub + 1e-12)
        g0_sub = base_fine[:, m0 : m1 + 1]

        def T(a):
            return torch.as_tensor(a, dtype=dtype, device=device)

        residual = window_residual(
            hardware, dtf, torch.as_tensor(fmask), T(fine_sub), T(g0_sub), t_adc, T(k0), t_mom, T(mom0),
            rf_c, rf_u, rfm, sc, T(sc.k if w.starts_period else sk), T(sc.m), realizer,
        )  # fmt: skip

        tt["setup"] += time.time() - t0
        t0 = time.time()
        with torch.no_grad():
            r0 = residual(T(x_sub)[None])[0]
        tt["residual"] += time.time() - t0
        tc = be[w.core[0]] - tsub  # the core's start in the window; the Jacobian does not depend on the history
        key = _structure_key(
            fr[:, ec0 - e0 :],
            fmask[:, 2 * (ec0 - e0) :],
            t_adc - tc,
            [c_ - tc for c_ in rf_c],
            rf_u,
            t_mom - tc,
            rfm[2 * (ec0 - e0) :],
            m1 - 2 * ec1,
            *([] if w.starts_period else [sk]),
        )
        c = cache.get(key)
        if c is None:
            t0 = time.time()
            c = _factor(hardware, dtf, fr, fmask, t_adc, t_mom, rf_c, rf_u, rfm, sc, dtype, device,
                        None if w.starts_period else sk)  # fmt: skip
            cache.put(key, c)
            tt["jacobian"] += time.time() - t0
        t0 = time.time()
        r0n = r0.cpu().numpy()
        if any(n_guard):  # guarded rows hold what is committed there: residual 0 now, the change is penalised
            _zero_guard_rows(r0n, n_guard, len(sc.k_axes), t_adc.size, t_mom.size)
        nd = c["J"].shape[0]
        r0d, r0r = r0n[:nd], r0n[nd:]
        grad0 = c["J"].T @ r0d + c["ST"] @ r0r
        # the core's own rows (a part's guarded rows come first, its end row last: not the core's samples)
        core_adc = slice(n_guard[0], n_guard[0] + len(sel_adc))
        unconstrained.add(key, c, r0d, grad0, t_adc.size, t_mom.size, sel_adc, core_adc, w.moment_rf, n_guard[1])
        # a window whose problem is an earlier one's (same structure; residual to 1e-6 of its largest entry and
        # edges to 1e-4 mT/m: identical repetitions, averages, slices that differ only in RF frequency or labels)
        # takes its change of the edges, if that is within the limits here
        skey = _solve_key(key, r0n, x_sub)
        st.groups.setdefault(skey, []).append(wi)
        if reuse and skey in solved:
            x_p = x_sub + solved[skey]
            solved.move_to_end(skey)
            if P.is_feasible(x_p[:, rs]):
                st.reused += 1
                tt["solve"] += time.time() - t0
                edges[:, e0 : e1 + 1] = x_p
                _commit_errors(st, sc, r0d + c["J"] @ (x_p[fr] - x_sub[fr]), t_adc.size, t_mom.size, sel_adc, core_adc,
                               w.moment_rf, n_guard[1])  # fmt: skip
                if progress is not None:
                    progress("windows", wi + 1, len(windows), float((r0**2).sum()))
                continue
        x_p = x_sub.copy()
        rd: np.ndarray | None = None  # the window's k-space residual rows at its solution (if computed on the way)
        # the window's unconstrained optimum, tried unless the structure's last windows all needed the limits (then
        # only every DIRECT_RETRY-th: ADMM reaches that optimum too when it is within the limits)
        streak = c.get("limited", 0)
        try_direct = streak % DIRECT_RETRY == 0
        if try_direct:
            x_p[fr] = x_sub[fr] - _symv(c["Hinv"], grad0)
        if try_direct and P.is_feasible(x_p[:, rs]):
            st.direct += 1
            c["limited"] = 0
        else:  # a limit is active: the same quadratic within the limits (ADMM, matrices cached per structure)
            c["limited"] = streak + 1
            x_p[:, rs], its = _admm(c, grad0, P, fr_r, x_sub[:, rs], max_iter=ADMM_MAX_ITER)
            st.admm_iters += its
            if k_tol_dk is not None and its < ADMM_MAX_ITER:
                # a window still above a share of the k tolerance runs on from where it stopped, until its k errors
                # are within that share or ADMM meets the tighter tolerance: what is left is then the quadratic's
                # optimum within the limits, not ADMM's slack
                share = REFINE_SHARE * k_tol_dk
                core = (sc, r0d, c["J"], t_adc.size, t_mom.size, core_adc, n_guard[1])
                rd = r0d + c["J"] @ (x_p[fr] - x_sub[fr])
                if _core_max_dk(core, rd=rd) > share:
                    x_p[:, rs], its = _admm(
                        c, grad0, P, fr_r, x_sub[:, rs], max_iter=ADMM_MAX_ITER, tol=ADMM_TOL_REFINE,
                        done=_KStop(core, share),
                    )  # fmt: skip
                    st.admm_iters += its
                    st.refined += 1
                    rd = None
            st.admm_capped += its >= ADMM_MAX_ITER
        dx = x_p[fr] - x_sub[fr]
        if rd is None:
            rd = r0d + c["J"] @ dx
        rr = r0r + c["S"] @ dx  # the window's residual at the solution
        if float(rd @ rd + rr @ rr) > float(r0n @ r0n):  # never worse than unchanged
            x_p, rd = x_sub, r0d
        tt["solve"] += time.time() - t0
        solved[skey] = x_p - x_sub
        if len(solved) > SOLVES_KEPT:
            solved.popitem(last=False)
        edges[:, e0 : e1 + 1] = x_p
        _commit_errors(st, sc, rd, t_adc.size, t_mom.size, sel_adc, core_adc, w.moment_rf, n_guard[1])
        if progress is not None:
            progress("windows", wi + 1, len(windows), float((r0**2).sum()))
    unconstrained.flush()
    st.structures = cache.distinct
    tt["total"] = time.time() - t_all
    st.times_s = tt
    return edges, st


def carry_sign(t_s: np.ndarray, rf_c: list[float], rf_u: list[str]) -> np.ndarray:
    """(Q,) the factor of the k carried into a part at the query times ``t_s``: -1 per refocusing pulse before
    the query, 0 after an excitation (or an 'undefined' pulse) -- what :func:`dtoc.seq.kspace.kspace_at` does
    to k at those events (``rf_c`` window-relative centres, ascending)."""
    out = np.ones(np.size(t_s))
    t = np.asarray(t_s, dtype=np.float64)
    for tc, u in zip(rf_c, rf_u):
        if u == "refocusing":
            out[t >= tc] *= -1.0
        elif u in ("excitation", "undefined"):
            out[t >= tc] = 0.0
    return out


def part_reference_s(ir: SequenceIR, w: Window, lookahead_s: float, t_exc: float) -> float:
    """The time from which a part of a period integrates its own k (its carried k is the realized k there): one
    raster step and the hardware's acausal memory before the core's start (a change of the core's first edge moves
    the waveform from one raster step before it, realized up to ``lookahead_s`` earlier), not before its period's
    excitation ``t_exc`` (k resets there) nor the window's start.  Non-decreasing along a period's parts."""
    be = ir.block_edges_s
    return max(be[w.core[0]] - ir.raster_s - lookahead_s, t_exc, be[w.sub[0]])


def _pulses_between(t_rf: np.ndarray, t0: float, t1: float) -> list[int]:
    """Indices of the pulses whose centres are in ``[t0, t1)`` (``t_rf``: the centres, ascending)."""
    return list(range(int(np.searchsorted(t_rf, t0, side="left")), int(np.searchsorted(t_rf, t1, side="left"))))


def carried_k(
    ir: SequenceIR,
    hardware,
    edges: np.ndarray,
    base_fine: np.ndarray,
    free: np.ndarray,
    act: np.ndarray,
    t_from: float,
    t_to: float,
    k_from: np.ndarray,
    ec: int,
    horizon_s: float,
    lookahead_s: float,
) -> np.ndarray:
    """(3,) the realized k (rad/m) at ``t_to`` from the realized k ``k_from`` at ``t_from`` (both in one excitation
    period): ``k_from`` signed by the pulses between (:func:`carry_sign`) plus the k the waveform adds, realized on
    ``[t_from - horizon, t_to + lookahead]`` from the committed edges before edge ``ec`` and the base after -- one
    forward of one part, not of the period."""
    e0 = max(int(math.floor((t_from - horizon_s) / ir.raster_s + 1e-9)), 0)
    e1 = min(int(math.ceil((t_to + lookahead_s) / ir.raster_s - 1e-9)), edges.shape[1] - 1)
    fine = _played_window(edges, base_fine, free, act, e0, e1, ec)
    g = torch.as_tensor(fine, dtype=torch.float64)[None]
    with torch.no_grad():
        G = g if hardware is None else hardware(g, ir.dt_fine_s)[0]
    t0 = e0 * ir.raster_s
    t_rf = np.array([r.t_center_s for r in ir.rf])
    pulses = [ir.rf[i] for i in _pulses_between(t_rf, t_from, t_to)]
    rf_c = [r.t_center_s - t0 for r in pulses]
    rf_u = [r.use for r in pulses]
    t_q = np.array([t_to - t0])
    k = kspace_at(G[0], ir.dt_fine_s, t_q, [t_from - t0] + rf_c, ["excitation"] + rf_u)[:, 0].numpy()
    return k + carry_sign(t_q, rf_c, rf_u)[0] * k_from


def _nominal_k(ir: SequenceIR, times_s: list[float]) -> np.ndarray:
    """(3, Q) the nominal k (rad/m) at the given times (the base waveform, every pulse's reset / negation)."""
    if not times_s:
        return np.zeros((3, 0))
    return ir.kspace_rad_per_m(times_s=np.asarray(times_s, dtype=np.float64)).cpu().numpy()


def _zero_guard_rows(r: np.ndarray, n_guard: tuple[int, int], n_axes: int, n_k: int, n_m: int) -> None:
    """Zero a part's guarded rows in its residual (the window_residual layout: k rows axis by axis over ``n_k``
    samples, then moment rows axis by axis over ``n_m`` pulses; the guarded ones first in each axis)."""
    if n_k and n_axes:
        r[: n_axes * n_k].reshape(n_axes, n_k)[:, : n_guard[0]] = 0.0
    if n_m and n_axes:
        off = n_axes * n_k if n_k else 0
        r[off : off + n_axes * n_m].reshape(n_axes, n_m)[:, : n_guard[1]] = 0.0


def _played_window(
    edges: np.ndarray, base_fine: np.ndarray, free: np.ndarray, act: np.ndarray, e0: int, e1: int, ec0: int
) -> np.ndarray:
    """(3, 2 (e1 - e0) + 1) the waveform played on the window's raster edges ``[e0, e1]`` so far: the fine samples
    that follow the committed free edges (those before the core's first edge ``ec0``; the windows run in time
    order) interpolate the edges, the rest are the base's -- what a whole-sequence copy updated window by window
    would hold, built from the edges and the base alone (O(window) memory)."""
    fr = free[:, e0 : e1 + 1] & act[None, e0 : e1 + 1]
    fr[:, max(ec0 - e0, 0) :] = False
    return edges_to_played(edges[:, e0 : e1 + 1], base_fine[:, 2 * e0 : 2 * e1 + 1], fine_free_mask(fr))


class _StructureCache:
    """Per-structure Jacobians and factors, least recently used dropped beyond ``max_bytes`` (at least the one in
    use is kept): a sequence of many distinct period timings stays bounded; a dropped structure that comes back is
    built again (its ADMM warm start then starts afresh)."""

    def __init__(self, max_bytes: int):
        self.max_bytes = max_bytes
        self.items: OrderedDict[str, dict] = OrderedDict()
        self.seen: set[str] = set()

    @property
    def distinct(self) -> int:
        return len(self.seen)

    def get(self, key: str) -> dict | None:
        c = self.items.get(key)
        if c is not None:
            self.items.move_to_end(key)
        return c

    def put(self, key: str, c: dict) -> None:
        self.items[key] = c
        self.seen.add(key)
        while len(self.items) > 1 and sum(_nbytes(v) for v in self.items.values()) > self.max_bytes:
            self.items.popitem(last=False)


def _nbytes(c: dict) -> int:
    """Bytes of a structure's arrays (dense and sparse, the ADMM's included)."""
    n = 0
    for v in c.values():
        if isinstance(v, np.ndarray):
            n += v.nbytes
        elif sp.issparse(v):
            n += v.data.nbytes + getattr(v, "indices", v.data).nbytes + getattr(v, "indptr", v.data).nbytes
        elif isinstance(v, dict):
            n += _nbytes(v)
        elif isinstance(v, tuple):
            n += sum(x.nbytes for x in v if isinstance(x, np.ndarray))
    return n


def _commit_errors(st: WindowStats, sc: _Scales, rd, n_adc, n_mom, sel_adc, core_adc, moment_rf, n_guard_mom) -> None:
    """Record a committed window's k errors (its residual rows ``rd``) of its own ADC samples and moments."""
    assert st.window_adc_dk is not None and st.window_moment_dk is not None
    st.window_adc_dk[sel_adc], st.window_moment_dk[moment_rf] = _own_errors_dk(
        sc, rd, n_adc, n_mom, core_adc, n_guard_mom
    )


def _core_max_dk(core: tuple, d: np.ndarray | None = None, rd: np.ndarray | None = None) -> float:
    """The largest k error (dk) of a window's own ADC samples and moments at the change ``d`` of its free edges
    (or at its residual rows ``rd``); ``core``: (scales, residual rows r0d, J, ADC count, moment count, the core's
    ADC rows, guarded moments)."""
    sc, r0d, J, n_adc, n_mom, core_adc, n_guard_mom = core
    ka, km = _own_errors_dk(sc, r0d + J @ d if rd is None else rd, n_adc, n_mom, core_adc, n_guard_mom)
    return float(np.nanmax(np.r_[ka, km, 0.0]))


class _KStop:
    """ADMM's early stop of a refined window, asked every 10th iteration: its own k errors (:func:`_core_max_dk`)
    within ``share`` dk, or no longer falling (less than :data:`REFINE_MIN_GAIN` of the largest over the last
    :data:`REFINE_PATIENCE` checks: ADMM's slack is gone or shrinks too slowly to matter)."""

    def __init__(self, core: tuple, share: float):
        self.core, self.share = core, share
        self.seen: list[float] = []

    def __call__(self, d: np.ndarray) -> bool:
        e = _core_max_dk(self.core, d=d)
        self.seen.append(e)
        if e <= self.share:
            return True
        return len(self.seen) > REFINE_PATIENCE and e > (1 - REFINE_MIN_GAIN) * self.seen[-1 - REFINE_PATIENCE]


def window_residual(
    hardware, dtf, fmask_t, fine_t, g0_t, t_adc, k0_t, t_mom, mom0_t, rf_c, rf_u, rfm, sc, sk_t, sm_t, realizer=None
):
    """The window's weighted residual vector as a function of edge arrays: (B, 3, Ne) -> (B, R).  ``realizer``
    (:class:`dtoc.optimize.window_jacobian.RangeRealizer` of ``hardware``): the realized gradient only on the fine
    samples the rows read (:func:`_rows_range`), else the chain on the whole window."""
    ka = torch.as_tensor(sc.k_axes)
    rng = None if realizer is None else _rows_range(dtf, fine_t.shape[-1], t_adc, t_mom, rf_c, rf_u, rfm)
    if rng is not None:  # the rows' times and samples relative to the range's first sample
        n_lo, n_hi, first = rng
        t0 = n_lo * dtf
        t_adc, t_mom = t_adc - t0, t_mom - t0
        rf_c, rf_u = [c - t0 for c in rf_c[first:]], rf_u[first:]
        g0_rf = g0_t[..., n_lo:n_hi][..., rfm[n_lo:n_hi]]
    else:
        g0_rf = g0_t[..., rfm]
    t_q = np.r_[np.asarray(t_adc, dtype=np.float64), np.asarray(t_mom, dtype=np.float64)]

    def residual(xe: torch.Tensor) -> torch.Tensor:
        g = torch.where(fmask_t, edges_to_fine(xe), fine_t)
        if rng is not None:
            G = realizer(g, rng[0], rng[1])
            G_rf = G[..., rfm[rng[0] : rng[1]]]
        else:
            G = g if hardware is None else hardware(g, dtf)[0]
            G_rf = G[..., rfm]
        parts = []
        if (t_adc.size or t_mom.size) and ka.numel():  # one pass for both sets of queries (each query on its own)
            km = kspace_at(G, dtf, t_q, rf_c, rf_u)
            k, mm = km[..., : t_adc.size], km[..., t_adc.size :]
        if t_adc.size and ka.numel():
            parts.append(((k - k0_t) * (sk_t if sk_t.dim() == 2 else sk_t[:, None]))[:, ka].flatten(1))
        if t_mom.size and ka.numel():
            parts.append(((mm - mom0_t) * sm_t[:, None])[:, ka].flatten(1))
        if rfm.any():
            parts.append(((G_rf - g0_rf) * sc.rf).flatten(1))
        parts.append((g - g0_t)[:, fmask_t] * sc.reg)  # only samples that can change: the rest is a constant
        return torch.cat(parts, dim=1)

    return residual


def _rows_range(dtf, T, t_adc, t_mom, rf_c, rf_u, rfm) -> tuple[int, int, int] | None:
    """The fine samples ``[n_lo, n_hi)`` of a window that its rows read, and the first RF event that counts: k at a
    query is the integral from the last pulse that resets k (excitation, undefined) before it
    (:func:`dtoc.seq.kspace.kspace_at`), so the range starts at the last such pulse at or before every query
    (the events before it are dropped) and ends after the last query and the last RF row's sample.  None: no query,
    or a query before every reset (the whole window, from its start)."""
    tq = np.r_[np.asarray(t_adc, dtype=np.float64), np.asarray(t_mom, dtype=np.float64)]
    if not tq.size:
        return None
    rf_i = np.flatnonzero(rfm)
    resets = [i for i, (c, u) in enumerate(zip(rf_c, rf_u)) if u in ("excitation", "undefined") and c <= tq.min()]
    if not resets:
        return None
    first = resets[-1]
    n_lo = int(math.floor(rf_c[first] / dtf + 1e-9))
    n_hi = int(math.floor(tq.max() / dtf + 1e-9)) + 2
    if rf_i.size:
        n_lo, n_hi = min(n_lo, int(rf_i[0])), max(n_hi, int(rf_i[-1]) + 1)
    n_lo, n_hi = max(n_lo, 0), min(n_hi, T)
    return (n_lo, n_hi, first) if n_hi - n_lo >= 2 else None


def _solve_key(structure: str, r0: np.ndarray, x_sub: np.ndarray, rel: float = 1e-6, edge_q: float = 1e-4) -> str:
    """Key of a window's whole problem: its structure, its residual to ``rel`` of its largest entry and its edges
    to ``edge_q`` mT/m (far below the writer's 6 digits; repeated periods differ by rounding in their times and
    in the history the earlier windows committed)."""
    h = hashlib.sha256(structure.encode())
    scale = max(float(np.abs(r0).max()) if r0.size else 0.0, 1e-300)
    h.update(np.round(r0 / (scale * rel)).astype(np.int64).tobytes())
    h.update(np.round(x_sub / edge_q).astype(np.int64).tobytes())
    return h.hexdigest()


def _structure_key(*parts) -> str:
    h = hashlib.sha256()
    for p in parts:
        if isinstance(p, np.ndarray):
            a = np.round(p, 10) if p.dtype.kind == "f" else p
            h.update(str(a.shape).encode())
            h.update(np.ascontiguousarray(a).tobytes())
        elif isinstance(p, (list, tuple)):
            h.update(repr([round(v, 10) if isinstance(v, float) else v for v in p]).encode())
        else:
            h.update(repr(p).encode())
    return h.hexdigest()


def _factor(hardware, dtf, fr, fmask, t_adc, t_mom, rf_c, rf_u, rfm, sc, dtype, device, k_scale=None) -> dict:
    """The structure's Jacobian J (dense rows, :mod:`dtoc.optimize.window_jacobian`), change-penalty rows S
    (sparse), the normal matrix ``J^T J + S^T S`` and its inverse.  ``k_scale``: (3, rows) weights of the k rows
    (a part's guarded samples), else ``sc.k`` per axis."""
    R = WJ.impulse_responses(hardware, dtf, fmask.shape[1], dtype, device)
    ks = sc.k if k_scale is None else k_scale
    J = WJ.lti_jacobian(R, dtf, fr, fmask, t_adc, t_mom, rf_c, rf_u, rfm, sc.k_axes, ks, sc.m, sc.rf)
    S = WJ.reg_rows(fr, fmask, sc.reg)
    H = J.T @ J
    H += (S.T @ S).toarray()  # in place: the same sums as ``J.T @ J + (S.T @ S).toarray()``, one n^2 fewer
    return {"J": J, "S": S, "ST": S.T.tocsr(), "Hinv": _spd_inverse(H), "normal": H}


def _spd_inverse(H: np.ndarray) -> np.ndarray:
    """Inverse of a symmetric positive (semi-)definite matrix by Cholesky (a tiny ridge if singular: no change
    penalty and an unobservable variable).  An explicit inverse: each window's solve is then one
    matrix-vector product, several times faster than two triangular solves.

    Memory: ``H`` and one n x n matrix (the factor, inverted and symmetrised in place, returned as its C-ordered
    transpose view), where ``np.tril(inv) + np.tril(inv, -1).T`` held five (4,806 free variables: 185 MB each); the
    same numbers bit for bit: every entry is the lower triangle's plus 0.0, as that sum made it."""
    n = H.shape[0]
    c, info = sla.lapack.dpotrf(H, lower=True, clean=False)
    if info != 0:
        ridge = 1e-12 * (np.trace(H) / max(n, 1) + 1e-300)
        c, info = sla.lapack.dpotrf(H + ridge * np.eye(n), lower=True, clean=False)
    if info != 0:
        raise np.linalg.LinAlgError(f"normal matrix not positive definite (dpotrf info {info})")
    inv, info = sla.lapack.dpotri(c, lower=True, overwrite_c=True)
    if info != 0:
        raise np.linalg.LinAlgError(f"normal matrix not invertible (dpotri info {info})")
    _symmetrize_lower(inv)
    return inv.T if inv.flags.f_contiguous and not inv.flags.c_contiguous else inv


#: rows per block of :func:`_symmetrize_lower` (its temporary: this many rows of the matrix)
SYMMETRIZE_BLOCK = 256


def _symmetrize_lower(a: np.ndarray) -> None:
    """In place: the strict upper triangle of the square ``a`` := the transpose of its lower triangle, then every
    entry + 0.0 (a -0.0 becomes 0.0, as ``np.tril(a) + np.tril(a, -1).T`` makes it); by blocks of rows."""
    n = a.shape[0]
    for r0 in range(0, n, SYMMETRIZE_BLOCK):
        r1 = min(r0 + SYMMETRIZE_BLOCK, n)
        a[r0:r1, r1:] = a[r1:, r0:r1].T
        blk = a[r0:r1, r0:r1]
        iu = np.triu_indices(r1 - r0, 1)
        blk[iu] = blk.T[iu]
    a += 0.0


def _symv(K: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``K @ v`` for a symmetric ``K`` (both triangles held, as :func:`_spd_inverse` makes it) by BLAS ``dsymv``: it
    reads one triangle, about half the time of the general product (which is bound by reading ``K``); the same
    figures up to the summation order."""
    return sla.blas.dsymv(1.0, K.T, v)  # K.T: the Fortran-ordered view of the same memory (no copy)


def _shifted_normal(H: np.ndarray, A, rho: float) -> np.ndarray:
    """``H + rho * (A.T @ A).toarray()`` (ADMM's normal matrix) built in one n x n array instead of three: the same
    products and sums (IEEE multiplication and addition commute), bit for bit."""
    K = (A.T @ A).toarray()
    K *= rho
    K += H
    return K


def _admm(
    c: dict,
    grad0: np.ndarray,
    P: EdgeProjector,
    fr: np.ndarray,
    xb: np.ndarray,
    rho_rel: float = 0.01,
    max_iter: int = 2000,
    tol: float | None = None,
    done: Callable[[np.ndarray], bool] | None = None,
) -> tuple[np.ndarray, int]:
    """min 1/2 d^T H d + grad0^T d over the free edges with ``xb + d`` within ``P``'s limits (box ``lo..hi``,
    ``|x[n+1] - x[n]| <= step`` on free pairs), by ADMM (over-relaxed, OSQP's splitting) with the normal
    matrix ``H + rho A^T A`` inverted once per structure (again when rho is rebalanced), warm-started from the
    last window of the structure; the result goes through ``P.project`` (exact).  ``done(d)``, asked every 10th
    iteration, stops it early (a k tolerance met).  ``tol`` None: :data:`ADMM_TOL`.  Returns (edges, iterations)."""
    tol = ADMM_TOL if tol is None else tol
    idx = np.flatnonzero(fr.ravel())
    n = idx.size
    col = np.full(fr.size, -1, dtype=np.int64)
    col[idx] = np.arange(n)
    pa, pj = np.nonzero(P.pair_free)
    i0 = col[pa * fr.shape[1] + pj]
    i1 = col[pa * fr.shape[1] + pj + 1]
    key = ("admm", rho_rel)
    if key not in c:
        Hd = c["normal"]
        rho = rho_rel * float(np.trace(Hd)) / max(n, 1)
        D = sp.csr_matrix(
            (
                np.r_[np.ones(i1.size), -np.ones(i0.size)],
                (np.r_[np.arange(i1.size), np.arange(i0.size)], np.r_[i1, i0]),
            ),
            shape=(i1.size, n),
        )
        A = sp.vstack([sp.identity(n, format="csr"), D]).tocsr()
        c[key] = {"rho": rho, "A": A, "Kinv": _spd_inverse(_shifted_normal(Hd, A, rho))}
    m = c[key]
    A, rho, Kinv = m["A"], m["rho"], m["Kinv"]
    x0 = xb.ravel()[idx]
    l = np.r_[P.lo.ravel()[idx] - x0, P.dlo[pa, pj] - (x0[i1] - x0[i0])]
    u = np.r_[P.hi.ravel()[idx] - x0, P.dhi[pa, pj] - (x0[i1] - x0[i0])]
    alpha = 1.6
    if "admm_zy" in m:  # the last window of this structure: nearly the same active constraints
        z, y = m["admm_zy"]
        z = np.clip(z, l, u)
    else:
        z = np.clip(A @ -(_symv(c["Hinv"], grad0)), l, u)
        y = np.zeros_like(z)
    d = np.zeros(n)
    it = refactor = 0
    for it in range(1, max_iter + 1):
        d = _symv(Kinv, -grad0 + A.T @ (rho * z - y))
        Ad = A @ d
        Ad_relaxed = alpha * Ad + (1 - alpha) * z
        z_new = np.clip(Ad_relaxed + y / rho, l, u)
        y = y + rho * (Ad_relaxed - z_new)
        dz = z_new - z
        z = z_new
        # the stopping rule each iteration: one more sparse product, cheap beside the dense one above
        r_p = np.abs(Ad - z).max()
        r_d = rho * np.abs(A.T @ dz).max()
        if r_p <= tol * max(1.0, np.abs(z).max()) and r_d <= tol * max(1.0, np.abs(grad0).max()):
            break
        if done is not None and it % 10 == 0 and done(d):
            break
        if it % 50 == 0 and refactor < 3:  # OSQP's rule: balance the scaled primal and dual residuals
            Hd = c["normal"] @ d
            rp_n = r_p / max(np.abs(Ad).max(), np.abs(z).max(), 1e-300)
            rd_n = r_d / max(np.abs(Hd).max(), np.abs(A.T @ y).max(), np.abs(grad0).max(), 1e-300)
            scale = math.sqrt(rp_n / max(rd_n, 1e-300))
            if scale > 5 or scale < 0.2:
                rho *= float(np.clip(scale, 1e-3, 1e3))
                Kinv = _spd_inverse(_shifted_normal(c["normal"], A, rho))
                m.update(rho=rho, Kinv=Kinv)
                refactor += 1
    m["admm_zy"] = (z, y)
    x = xb.copy()
    x.ravel()[idx] = x0 + d
    return P.project(x), it
