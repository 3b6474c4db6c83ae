"""Hard gradient limits, guaranteed by construction.

The optimizer's variables are the demanded gradient at raster *edges* (``e[a, n]``, axis ``a``, edge
``n`` at ``t = n * raster``); the played waveform is the straight line between consecutive edges
(raster-centre samples of a free segment are the mean of their neighbours, see
``docs/conventions.md``).  For such a piecewise-linear waveform the per-axis limits are exactly

* amplitude: ``|e[a, n]| <= gmax`` (a straight segment peaks at an end point), and
* slew: ``|e[a, n+1] - e[a, n]| <= smax * raster`` (constant slew on each segment, including the
  segments touching block edges and the first/last one: every edge is a vertex),

with the non-free edges fixed at their base values.  :class:`EdgeProjector` maps any edge array onto
this convex set:

1. Exact reachability envelopes ``L[n] <= e[n] <= U[n]`` are derived from the fixed samples and the
   limits (a free sample ``j`` raster steps from a fixed value ``c`` must lie within ``c -+ j*S``).
   An empty envelope means no waveform can meet the limits -> :class:`~dtoc.errors.LimitError`.
2. Dykstra's alternating projection onto {envelope box} and the two sets of disjoint neighbour pairs
   ``{|e[n+1] - e[n]| <= S}`` (even / odd pairs; each has a closed-form projection) approximates the
   Euclidean projection.
3. A repair that is feasible by construction: the mean of a forward and a backward greedy pass
   (``e[n] = clip(y[n], e[n-1] -+ S) & [L[n], U[n]]``; both passes are feasible because the envelopes
   are S-Lipschitz, and the feasible set is convex, so their mean is feasible too).

Both run as whole-array operations, not a Python step per sample or pair: Dykstra on the axes with free samples,
its columns ordered even edges then odd ones (each pair set is two contiguous slices), into buffers made once;
the greedy passes of all axes and both directions as sweeps of one array until nothing changes
(:func:`_sequential_clip`).  The numbers are those of the per-sample algorithm, bit for bit
(tests/test_limits_vectorized.py).  A tensor on an accelerator is projected there (:meth:`EdgeProjector.project`).

At an oblique orientation (``Limits.rotation`` = R, logical -> physical, not an axis permutation) the scanner
enforces the limits on the physical axes ``R @ g``, which couple the logical axes.  The projector keeps its
per-logical-axis structure with *per-sample* bounds: every edge gets a box ``alo[:, n] <= e[:, n] <= ahi[:, n]``
and every segment a box ``dlo[:, n] <= e[:, n+1] - e[:, n] <= dhi[:, n]`` whose every corner is within the
physical limits (and each logical axis within them too: the file checks clean on its own axes).  The boxes
are chosen from the base (:func:`_physical_boxes`): the largest common half-width ``a`` around zero that still
holds the base's own value on every axis (``max(a, |b_j|)``), then each axis grown by what the physical rows
it plays on leave, so a base within the physical limits always lies
in the set and is never refused, whatever the orientation; where the base's values fit only through the signs
(no symmetric box holds them) the box is the base's own value.  Fixed samples are checked on the physical axes
(what the scanner enforces) and on the logical ones.  The envelopes then propagate the per-sample bounds
(:func:`_envelope_var`).  This replaces the conservative uniform bound ``limit / max_i sum_j |R_ij|`` on every
logical axis, which refused bases that play fine (a 20 degree EPI: 140.4 of 180 T/m/s).

The projection works with limits tightened by a small safety margin (default 0.5 % amplitude, 1 %
slew: room for the 6-digit amplitude and 1e-7 shape quantisation of the ``.seq`` writer), so the
exported file stays within the true limits.  Units: mT/m, T/m/s, s.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from dtoc.constants import AXES, GAMMA_RAD_PER_S_PER_MT
from dtoc.errors import LimitError
from dtoc.util.replay import Replay


@dataclass(frozen=True)
class Limits:
    """Per-axis hardware limits.

    Attributes:
        gmax_mT_per_m: maximum gradient amplitude per axis, mT/m.
        smax_T_per_m_per_s: maximum slew rate per axis, T/m/s (= mT/m/ms).
        amp_margin: relative safety margin applied to free samples' amplitude (0.005 = 0.5 %).
        slew_margin: relative safety margin applied to free segments' slew.
        rotation: None (the file's axes are the physical ones, or an axis permutation of them: the per-axis
            limits are the same) or the 9 numbers of the logical -> physical rotation R, row-major: the limits
            then hold on the physical axes ``R @ g`` as well as on the logical ones (:meth:`rotated`).
    """

    gmax_mT_per_m: float
    smax_T_per_m_per_s: float
    amp_margin: float = 0.005
    slew_margin: float = 0.01
    rotation: tuple | None = None

    def __post_init__(self):
        if not (np.isfinite(self.gmax_mT_per_m) and self.gmax_mT_per_m > 0):
            raise LimitError(f"gmax must be a positive number of mT/m, got {self.gmax_mT_per_m}")
        if not (np.isfinite(self.smax_T_per_m_per_s) and self.smax_T_per_m_per_s > 0):
            raise LimitError(f"smax must be a positive number of T/m/s, got {self.smax_T_per_m_per_s}")
        if not (0 <= self.amp_margin < 0.5 and 0 <= self.slew_margin < 0.5):
            raise LimitError("limit safety margins must lie in [0, 0.5)")
        if self.rotation is not None and (len(self.rotation) != 9 or not np.all(np.isfinite(self.rotation))):
            raise LimitError("the limits' rotation must be 9 finite numbers (row-major, logical -> physical)")

    def rotated(self, R) -> Limits:
        """These limits at orientation R (3x3, logical -> physical; None: unchanged).  An axis permutation with
        signs (tra, cor, sag) maps per-axis limits onto themselves: no rotation is recorded."""
        if R is None:
            return self
        R = np.asarray(R, dtype=np.float64)
        perm = np.all(np.isclose(np.abs(R), 0.0, atol=1e-12) | np.isclose(np.abs(R), 1.0, atol=1e-12))
        rot = None if perm else tuple(float(x) for x in R.ravel())
        return Limits(self.gmax_mT_per_m, self.smax_T_per_m_per_s, self.amp_margin, self.slew_margin, rot)

    @property
    def R(self) -> np.ndarray | None:
        """The logical -> physical rotation (3, 3), or None."""
        return None if self.rotation is None else np.asarray(self.rotation, dtype=np.float64).reshape(3, 3)

    @property
    def gmax_eff_mT_per_m(self) -> float:
        """Amplitude bound used for free samples (margin applied), mT/m."""
        return self.gmax_mT_per_m * (1.0 - self.amp_margin)

    def step_max_mT_per_m(self, raster_s: float, margin: bool = True) -> float:
        """Largest change between consecutive raster edges, mT/m (smax * raster)."""
        s = self.smax_T_per_m_per_s * (1.0 - self.slew_margin if margin else 1.0)
        return s * 1e3 * raster_s  # T/m/s = mT/m/ms -> mT/m/s times s


def waveform_extremes(fine_mT_per_m: np.ndarray, dt_fine_s: float) -> dict:
    """Per-axis peak amplitude (mT/m) and peak slew (T/m/s) of a PWL fine-grid waveform.

    Args:
        fine_mT_per_m: (3, M) samples on a uniform grid of spacing ``dt_fine_s`` joined by lines.
    Returns:
        {"gmax_mT_per_m": [3 floats], "smax_T_per_m_per_s": [3 floats]}.
    """
    g = np.asarray(fine_mT_per_m, dtype=np.float64)
    amp, step = np.zeros(g.shape[:-1]), np.zeros(g.shape[:-1])
    n = g.shape[-1]
    for s in range(0, max(n - 1, 1), EXTREMES_CHUNK):  # chunks overlapping by one sample: every step in one chunk
        blk = g[..., s : min(s + EXTREMES_CHUNK + 1, n)]
        if blk.shape[-1]:
            amp = np.maximum(amp, np.abs(blk).max(axis=-1))
        if blk.shape[-1] > 1:
            step = np.maximum(step, np.abs(np.diff(blk, axis=-1)).max(axis=-1))
    return {"gmax_mT_per_m": amp.tolist(), "smax_T_per_m_per_s": (step / dt_fine_s * 1e-3).tolist()}


#: :func:`waveform_extremes` reads a waveform in pieces of this many samples: no whole-length temporaries (the
#: 187 s CEST protocol's 37 million fine samples per axis: 3 x 0.9 GB of them, 4.7 -> 0.7 CPU s), same maxima
EXTREMES_CHUNK = 1 << 18


def limit_violations(fine_mT_per_m: np.ndarray, dt_fine_s: float, limits: Limits, rel_tol: float = 1e-9) -> list[str]:
    """Human-readable list of per-axis limit violations of a fine-grid waveform (empty = compliant)."""
    ex = waveform_extremes(fine_mT_per_m, dt_fine_s)
    out = []
    for a, name in enumerate(AXES):
        if ex["gmax_mT_per_m"][a] > limits.gmax_mT_per_m * (1 + rel_tol):
            out.append(f"{name}: |g| {ex['gmax_mT_per_m'][a]:.4g} mT/m > gmax {limits.gmax_mT_per_m:.4g}")
        if ex["smax_T_per_m_per_s"][a] > limits.smax_T_per_m_per_s * (1 + rel_tol):
            out.append(f"{name}: slew {ex['smax_T_per_m_per_s'][a]:.4g} T/m/s > smax {limits.smax_T_per_m_per_s:.4g}")
    return out


def physical_violations(
    fine_mT_per_m: np.ndarray, dt_fine_s: float, limits: Limits, rel_tol: float = 1e-9
) -> list[str]:
    """:func:`limit_violations` of the waveform the scanner plays, ``R @ g`` on the physical axes, at an oblique
    ``limits.rotation`` (empty without one: the logical check is the physical one)."""
    R = limits.R
    if R is None:
        return []
    g = R @ np.asarray(fine_mT_per_m, dtype=np.float64)
    return [f"physical {v}" for v in limit_violations(g, dt_fine_s, limits, rel_tol)]


def base_physical_warnings(fine_mT_per_m: np.ndarray, dt_fine_s: float, limits: Limits) -> list[str]:
    """At an oblique orientation: one warning when the base itself exceeds the limits on a physical axis (the
    output is held within them, so it cannot follow the base's k-space everywhere); empty otherwise."""
    v = physical_violations(fine_mT_per_m, dt_fine_s, limits, rel_tol=1e-6)
    if not v:
        return []
    return [
        f"the base sequence exceeds the limits at this orientation ({'; '.join(v[:2])}): the output is held within "
        "them on every physical axis and cannot follow the base's k-space everywhere"
    ]


class _NP:
    """The array operations of :func:`_dykstra` and :func:`_sequential_clip` for numpy (``out=``: in place)."""

    add, sub, mul, abs, sign, where, nonzero = np.add, np.subtract, np.multiply, np.abs, np.sign, np.where, np.nonzero

    @staticmethod
    def clip(a, lo, hi, out):
        return np.clip(a, lo, hi, out=out)

    @staticmethod
    def relu(a, out):  # = np.clip(a, 0.0, None), which numpy computes as this
        return np.maximum(a, 0.0, out=out)

    @staticmethod
    def zero_where(a, mask):
        np.copyto(a, 0.0, where=mask)

    @staticmethod
    def bits(a):
        return a.view(np.uint64)

    zeros_like, cat = np.zeros_like, np.concatenate

    @staticmethod
    def empty(shape, like):
        return np.empty(shape)

    @staticmethod
    def flip(a):
        return a[:, ::-1]

    @staticmethod
    def host(a):
        return a


class _TORCH:
    """:class:`_NP` for torch tensors (float64, on any device): the same elementwise operations, so the same bits."""

    add, sub, mul, abs, sign, where = torch.add, torch.sub, torch.mul, torch.abs, torch.sign, torch.where

    @staticmethod
    def nonzero(a):
        return torch.nonzero(a, as_tuple=True)

    @staticmethod
    def clip(a, lo, hi, out):
        return torch.clamp(a, lo, hi, out=out)

    @staticmethod
    def relu(a, out):
        return torch.clamp(a, min=0.0, out=out)

    @staticmethod
    def zero_where(a, mask):
        a.masked_fill_(mask, 0.0)

    @staticmethod
    def bits(a):
        return a.view(torch.int64)

    @staticmethod
    def zeros_like(a):
        return torch.zeros_like(a)

    @staticmethod
    def empty(shape, like):
        return torch.empty(shape, dtype=like.dtype, device=like.device)

    @staticmethod
    def cat(arrays):
        return torch.cat(list(arrays))

    @staticmethod
    def flip(a):
        return a.flip(1)

    @staticmethod
    def host(a):
        return a.cpu().numpy()


def _clip_step(prev, v, lo, hi, dl, dh):
    """One step of the sequential clip, elementwise: ``v`` clipped to ``[lo, hi] & [prev + dl, prev + dh]``; where
    that is empty (rounding of consistent envelopes only) the bound nearest feasibility.  The comparisons are the
    ones Python's ``max(lo, c)`` / ``min(hi, c)`` make, so the values are those of the scalar loop, bit for bit."""
    w = torch.where if isinstance(prev, torch.Tensor) else np.where
    c = prev + dl
    a = w(c > lo, c, lo)
    c = prev + dh
    b = w(c < hi, c, hi)
    b = w(a > b, a, b)
    return w(v < a, a, w(v > b, b, v))


def _clip_loop(x: np.ndarray, v: np.ndarray, lo: np.ndarray, hi: np.ndarray, dl: np.ndarray, dh: np.ndarray, m: int):
    """:func:`_clip_step` one sample after the other from ``m >= 1`` to the end of the 1-D ``x`` (in place)."""
    prev = float(x[m - 1])
    out = []
    for vv, a, b, d0, d1 in zip(
        v[m:].tolist(), lo[m:].tolist(), hi[m:].tolist(), dl[m - 1 :].tolist(), dh[m - 1 :].tolist()
    ):
        a = max(a, prev + d0)
        b = min(b, prev + d1)
        if a > b:
            b = a
        prev = a if vv < a else (b if vv > b else vv)
        out.append(prev)
    x[m:] = out


def _sequential_clip(xp, v, lo, hi, dl, dh):
    """Row by row, the greedy pass ``x[n] = clip(v[n], [lo[n], hi[n]] & [x[n-1] + dl[n-1], x[n-1] + dh[n-1]])``
    (``v``, ``lo``, ``hi``: (R, n); ``dl``, ``dh``: (R, n-1); float64 arrays of ``xp``, :class:`_NP` or
    :class:`_TORCH`), computed as whole-array sweeps.

    Each sample depends on the one before only, so the sequence is the unique fixed point of
    ``x[n] = step(x[n-1])`` with ``x[0] = clip(v[0], lo[0], hi[0])``.  Sweeps recompute, from the current guess, the
    samples whose predecessor changed (the first sweep: all of them) until none changes: every sweep settles at
    least the next sample of each chain, and the fixed point is the scalar loop's sequence, bit for bit (the same
    operations on the same numbers).  Where the limits are active over long chains (far from the set) a sweep
    settles few samples: past a sweep budget the rest of such a row runs as the scalar loop from its first
    unsettled sample (everything before it is settled).
    """
    b = xp.where(lo > hi, lo, hi)
    x = xp.where(v < lo, lo, xp.where(v > b, b, v))  # sample 0 (no predecessor), and the first guess of the others
    n = x.shape[1]
    if n < 2:
        return x
    new = _clip_step(x[:, :-1], v[:, 1:], lo[:, 1:], hi[:, 1:], dl, dh)
    changed = xp.bits(new) != xp.bits(x[:, 1:])
    x[:, 1:] = new
    rows, cols = xp.nonzero(changed[:, :-1])  # sample cols + 1 changed: recompute cols + 2
    cols = cols + 2
    sweeps, budget = 1, 64 + n // 64
    while rows.shape[0]:
        if sweeps >= budget:  # long active chains: the scalar loop from each row's first unsettled sample
            xh, vh, loh, hih, dlh, dhh = (xp.host(t) for t in (x, v, lo, hi, dl, dh))
            rh, ch = xp.host(rows), xp.host(cols)
            for r in np.unique(rh):
                _clip_loop(xh[r], vh[r], loh[r], hih[r], dlh[r], dhh[r], int(ch[rh == r].min()))
            x[:] = xh if xh is x else torch.as_tensor(xh, device=x.device)
            break
        prev = x[rows, cols - 1]
        new = _clip_step(prev, v[rows, cols], lo[rows, cols], hi[rows, cols], dl[rows, cols - 1], dh[rows, cols - 1])
        ch = xp.bits(new) != xp.bits(x[rows, cols])
        x[rows, cols] = new
        rows, cols = rows[ch], cols[ch] + 1
        keep = cols < n
        rows, cols = rows[keep], cols[keep]
        sweeps += 1
    return x


def _greedy_mean(xp, x, lo, hi, dlo, dhi, free_axes):
    """The repair's mean of the forward and the backward greedy pass on the axes ``free_axes`` (index array), as
    rows of one :func:`_sequential_clip` (backwards, x[n] - x[n+1] lies in -dhi..-dlo); the other axes as they are."""
    out = x.clone() if isinstance(x, torch.Tensor) else x.copy()
    k = free_axes.shape[0]
    if k:
        xa, la, ha, dla, dha = x[free_axes], lo[free_axes], hi[free_axes], dlo[free_axes], dhi[free_axes]
        f = xp.flip
        p = _sequential_clip(
            xp,
            xp.cat([xa, f(xa)]),
            xp.cat([la, f(la)]),
            xp.cat([ha, f(ha)]),
            xp.cat([dla, -f(dha)]),
            xp.cat([dha, -f(dla)]),
        )
        out[free_axes] = 0.5 * (p[:k] + f(p[k:]))
    return out


#: devices whose tensors are projected on the host with numpy (:meth:`EdgeProjector.project`); elsewhere the same
#: operations run in torch where the tensor lies (the GPU's path, which a test runs on the CPU by emptying this)
HOST_DEVICES: frozenset[str] = frozenset({"cpu"})


class _PairSet:
    """One of the two sets of disjoint neighbour pairs ``(n, n+1)``, ``n = start, start + 2, ...``, in the
    columns of :class:`_Layout` (even edges first, then odd ones: every pair's ends and every run of untouched
    columns are contiguous slices ``a``, ``b``, ``rest``); the pairs that are not free-free (``off``, left alone)
    and their step bounds ``dlo..dhi`` (oblique limits)."""

    def __init__(self, m: int, a: slice, b: slice, rest: tuple, off, dlo, dhi):
        self.m, self.a, self.b, self.rest, self.off, self.dlo, self.dhi = m, a, b, rest, off, dlo, dhi

    @classmethod
    def make(cls, start: int, n_edges: int, pair_free: np.ndarray, dlo: np.ndarray, dhi: np.ndarray) -> _PairSet:
        m = len(range(start, n_edges - 1, 2))
        n_even = (n_edges + 1) // 2  # column of edge n: n // 2 (even n), n_even + n // 2 (odd n)
        col = lambda n: n // 2 if n % 2 == 0 else n_even + n // 2  # noqa: E731
        a = slice(col(start), col(start) + m)
        b = slice(col(start + 1), col(start + 1) + m)
        used = np.zeros(n_edges, dtype=bool)
        used[a], used[b] = True, True
        edges = np.flatnonzero(np.diff(np.concatenate([[0], (~used).astype(np.int8), [0]])))
        rest = tuple(slice(int(i), int(j)) for i, j in zip(edges[::2], edges[1::2]))
        cols = slice(None), slice(start, None, 2)
        return cls(m, a, b, rest, ~pair_free[cols][:, :m], dlo[cols][:, :m], dhi[cols][:, :m])

    def to(self, convert) -> _PairSet:
        """The same set with its arrays converted (``convert``: array -> tensor on a device)."""
        return _PairSet(self.m, self.a, self.b, self.rest, convert(self.off), convert(self.dlo), convert(self.dhi))


class _Layout:
    """What :func:`_dykstra` works on: the rows (axes) with free samples, their columns in the order ``perm`` (even
    edges, then odd ones), the box ``lo..hi`` in that order and the two pair sets."""

    def __init__(self, rows, perm, lo, hi, sets: tuple[_PairSet, ...]):
        self.rows, self.perm, self.lo, self.hi, self.sets = rows, perm, lo, hi, sets

    @classmethod
    def make(cls, free, lo, hi, pair_free, dlo, dhi) -> _Layout:
        rows = np.flatnonzero(free.any(axis=1))
        n = lo.shape[1]
        perm = np.concatenate([np.arange(0, n, 2), np.arange(1, n, 2)])
        sets = tuple(_PairSet.make(start, n, pair_free[rows], dlo[rows], dhi[rows]) for start in (0, 1))
        return cls(rows, perm, np.ascontiguousarray(lo[rows][:, perm]), np.ascontiguousarray(hi[rows][:, perm]), sets)

    def to(self, convert) -> _Layout:
        return _Layout(
            convert(self.rows),
            convert(self.perm),
            convert(self.lo),
            convert(self.hi),
            tuple(p.to(convert) for p in self.sets),
        )


def _dykstra(xp, x, lay: _Layout, step, n_iter: int):
    """Dykstra's alternating projection onto the box ``lo..hi`` and the two pair sets (closed form each: a pair
    beyond its step bound moves both ends by half the excess), ``n_iter`` rounds, then the box.  ``step``: the
    uniform step bound, or None for the pair sets' own ``dlo..dhi``.  Whole-array operations on contiguous
    slices (the columns reordered, :class:`_Layout`) into buffers made once; the values are those of the plain
    expressions ``a + 0.5 * excess`` and so on, bit for bit."""
    out = x.clone() if isinstance(x, torch.Tensor) else x.copy()
    # only the rows with free samples are computed: a row without (``x`` holds its fixed values, lo = hi) ends
    # as the last box makes it, its values (a clip returns the bound it equals: a zero keeps its sign)
    lo, hi = lay.lo, lay.hi
    x = x[lay.rows][:, lay.perm]
    z = xp.empty(x.shape, x)
    incr = [xp.zeros_like(x) for _ in range(3)]
    bufs = [(xp.empty((x.shape[0], p.m), x), xp.empty((x.shape[0], p.m), x)) for p in lay.sets]
    for _ in range(n_iter):
        xp.add(x, incr[0], out=z)
        xp.clip(z, lo, hi, out=x)
        xp.sub(z, x, out=incr[0])
        for p, (d, e), inc in zip(lay.sets, bufs, incr[1:]):
            xp.add(x, inc, out=z)
            a, b = z[:, p.a], z[:, p.b]
            xp.sub(b, a, out=d)
            if step is not None:  # excess = where(pair free, max(|d| - S, 0), 0) * sign(d)
                xp.abs(d, out=e)
                xp.sub(e, step, out=e)
                xp.relu(e, out=e)
                xp.zero_where(e, p.off)
                xp.mul(e, xp.sign(d, out=d), out=e)
            else:  # excess = where(pair free, d - clip(d, dlo, dhi), 0)
                xp.sub(d, xp.clip(d, p.dlo, p.dhi, out=e), out=e)
                xp.zero_where(e, p.off)
            xp.mul(e, 0.5, out=e)
            xp.add(a, e, out=x[:, p.a])
            xp.sub(b, e, out=x[:, p.b])
            for r in p.rest:
                x[:, r] = z[:, r]
            xp.sub(z, x, out=inc)
    xp.clip(x, lo, hi, out=z)
    x[:, lay.perm] = z
    out[lay.rows] = x
    return out


def _envelope_var(alo, ahi, dlo, dhi):
    """Exact reachability envelope of one axis under per-edge boxes ``alo..ahi`` and per-segment step boxes
    ``dlo..dhi``: ``hi[n] = min_j ahi[j] + (the most the waveform can rise from j to n)``, and so on, by running
    extrema over cumulative step sums (a sample reaches n only through the segments between)."""
    Dh = np.concatenate([[0.0], np.cumsum(dhi)])
    Dl = np.concatenate([[0.0], np.cumsum(dlo)])
    hi_f = np.minimum.accumulate(ahi - Dh) + Dh
    hi_b = np.minimum.accumulate((ahi - Dl)[::-1])[::-1] + Dl
    lo_f = np.maximum.accumulate(alo - Dl) + Dl
    lo_b = np.maximum.accumulate((alo - Dh)[::-1])[::-1] + Dh
    hi = np.minimum(np.minimum(hi_f, hi_b), ahi)
    lo = np.maximum(np.maximum(lo_f, lo_b), alo)
    scale = max(1.0, float(np.abs(Dh).max()), float(np.abs(Dl).max()))
    return lo, hi, 1e-12 * scale


def _waterfill(W: np.ndarray, p_abs: np.ndarray, q_abs: np.ndarray, limit: float) -> np.ndarray:
    """Per column m: the largest ``a >= 0`` with ``p_abs[i] + sum_j W[i, j, m] max(a, q_abs[j]) <= limit`` for
    every row i (W: (3, 3, M) non-negative weights, zero for the fixed entries), -1 where even ``a = 0``
    breaks it, inf where no row bounds it.  Each row is piecewise linear and increasing in ``a`` with
    break points at the ``q_abs`` values: the crossing is found on the segment where it lies."""
    M = q_abs.shape[1]
    bp = np.concatenate([np.zeros((1, M)), np.sort(q_abs, axis=0)], axis=0)  # (4, M)
    mx = np.maximum(bp[:, None, :], q_abs[None, :, :])  # (4, 3j, M): max(bp_k, q_j)
    h = p_abs[None, :, :] + np.einsum("ijm,kjm->kim", W, mx)  # (4, 3i, M)
    below = q_abs[None, :, :] <= bp[:, None, :]  # (4, 3j, M): q_j <= bp_k
    slope = np.einsum("ijm,kjm->kim", W, below.astype(np.float64))  # slope after bp_k, (4, 3i, M)
    ok = h <= limit
    k = np.where(ok.any(axis=0), 3 - np.argmax(ok[::-1], axis=0), 0)  # last break point within, (3i, M)
    hk = np.take_along_axis(h, k[None], axis=0)[0]
    sk = np.take_along_axis(slope, k[None], axis=0)[0]
    bk = bp[k, np.arange(M)[None, :]]
    with np.errstate(divide="ignore", invalid="ignore"):
        a_i = np.where(sk > 0, bk + (limit - hk) / np.where(sk > 0, sk, 1.0), np.inf)
    a_i = np.where(ok[0], a_i, -1.0)
    return a_i.min(axis=0)


def _physical_boxes(v, fixed, R, limit: float, true_limit: float, what: str, raster_s: float):
    """Per-logical-axis boxes ``lo..hi`` (3, M) for the values ``v`` (amplitudes or steps), every corner within
    ``limit`` on the physical axes and on the logical ones, holding the base (see the module docstring).
    ``fixed``: (3, M) values that must stay.  Raises LimitError where fixed values alone exceed
    ``true_limit`` on a physical axis."""
    A = np.abs(R)
    q = np.where(fixed, v, np.clip(v, -limit, limit))  # the base, each logical axis within its own limit
    p = R @ np.where(fixed, v, 0.0)
    W = A[:, :, None] * (~fixed)[None, :, :]  # (3i, 3j, M)
    q_abs = np.where(fixed, 0.0, np.abs(q))
    a = np.minimum(_waterfill(W, np.abs(p), q_abs, limit), limit)
    half = np.where(fixed, 0.0, np.maximum(a[None, :], q_abs))
    point = np.zeros(a.shape, dtype=bool)
    cols = np.flatnonzero(a < 0)  # no symmetric box holds the base's values
    if cols.size:
        # the base's own values where they are within the true limits (they fit only through their signs)
        point[cols] = np.all(np.abs(R @ q[:, cols]) <= true_limit, axis=0)
        rest = cols[~point[cols]]  # the base's free values are beyond the limits: the box the fixed values leave
        if rest.size:
            pr = np.abs(p[:, rest])
            over = pr > true_limit * (1 + 1e-6)
            if over.any():
                i, c = np.argwhere(over)[0]
                raise _physical_error(what, "xyz"[i], int(rest[c]), float(pr[i, c]), true_limit, raster_s)
            wsum = W[:, :, rest].sum(axis=1)
            with np.errstate(divide="ignore"):
                a0 = np.where(wsum > 0, (limit - pr) / np.where(wsum > 0, wsum, 1.0), np.inf).min(axis=0)
            half[:, rest] = np.where(fixed[:, rest], 0.0, np.clip(a0, 0.0, limit)[None, :])
    # then each axis in turn takes what the physical rows it plays on leave (an axis that no tight row couples
    # to keeps its own limit), so no box can grow alone
    for j in range(3):
        used = np.abs(p) + np.einsum("ijm,jm->im", W, half)
        with np.errstate(divide="ignore", invalid="ignore"):
            room = np.where(W[:, j] > 0, (limit - used) / np.where(W[:, j] > 0, W[:, j], 1.0), np.inf).min(axis=0)
        grow = ~point & ~fixed[j] & np.isfinite(room) & (room > 0)
        half[j] = np.where(grow, np.minimum(half[j] + np.where(grow, room, 0.0), limit), half[j])
    lo = np.where(fixed, v, np.where(point[None, :], q, -half))
    hi = np.where(fixed, v, np.where(point[None, :], q, half))
    return lo, hi


def _physical_error(what: str, axis: str, n: int, value: float, limit: float, raster_s: float) -> LimitError:
    if what == "amplitude":
        return LimitError(
            f"fixed (non-optimizable) gradient at t={n * raster_s * 1e3:.3f} ms plays {value:.4g} mT/m on the "
            f"physical {axis} axis at this orientation, beyond gmax {limit:.4g} mT/m"
        )
    return LimitError(
        f"fixed (non-optimizable) gradient at t={n * raster_s * 1e3:.3f} ms slews {value / raster_s * 1e-3:.4g} "
        f"T/m/s on the physical {axis} axis at this orientation, beyond smax {limit / raster_s * 1e-3:.4g} T/m/s"
    )


#: edges per piece of the envelopes and of :meth:`EdgeProjector.is_feasible` (their temporaries: ~100 bytes per edge
#: of one piece, not of the sequence)
CHECK_CHUNK = 1 << 18

#: a sequence longer than this many edges whose waveform is outside the set in a few places only (a windowed solve's
#: results meet their windows' limits; the seams between them and the envelopes' rounding, ~1e-10 mT/m at millions
#: of edges, are what the final check at tolerance 0 can find) is projected there only (:meth:`EdgeProjector.project`)
LOCAL_MIN_EDGES = 2 * CHECK_CHUNK
#: edges on either side of such a place (beyond Dykstra's reach: two edges per round, 60 rounds at the export)
LOCAL_MARGIN = 256

_BIG = 1e300


def _first_in_pieces(n: int, mask_of) -> tuple[int, int] | None:
    """The first ``(axis, index)`` in ``np.argwhere`` order (lowest axis, then earliest) where ``mask_of(piece)``
    ((3, len) bool of the indices ``piece``, a slice of ``range(n)``) is True, piece by piece; None if nowhere."""
    first: list = [None, None, None]
    for a0 in range(0, n, CHECK_CHUNK):
        for a, i in np.argwhere(mask_of(slice(a0, min(a0 + CHECK_CHUNK, n)))):
            if first[a] is None:
                first[a] = a0 + int(i)
    return next(((a, first[a]) for a in range(3) if first[a] is not None), None)


class _Envelopes:
    """The exact reachability envelopes of the uniform limits (``|e| <= G``, every step ``<= S``), piece by piece.

    Upper: ``min(G, min_j c_j + S |n - j|)`` over the fixed samples ``j``, lower: ``max(-G, max_j c_j - S |n - j|)``,
    as forward / backward running extrema of ``c_j -+ S j``.  A piece's running extrema are its own, combined with
    one carry (the extremum of everything before it, resp. after it) per axis and direction: a minimum or maximum is
    exact, so the piece's values are those of the whole-sequence sweep, bit for bit, and nothing of the sequence's
    length is held but the base's edges (shared) and the fixed mask.
    """

    def __init__(self, c: np.ndarray, fixed: np.ndarray, G: float, S: float):
        self.c, self.fixed, self.G, self.S = c, fixed, G, S
        self.rows = [a for a in range(3) if fixed[a].any()]  # the other axes: -G..G throughout
        n = c.shape[1]
        starts = list(range(0, n, CHECK_CHUNK))
        m = np.empty((4, 3, len(starts)))  # each piece's min(c - S j), max(c + S j), min(c + S j), max(c - S j)
        for p, a0 in enumerate(starts):
            e = slice(a0, min(a0 + CHECK_CHUNK, n))
            for a in self.rows:
                v = self._terms(a, e)
                m[:, a, p] = [v[0].min(), v[1].max(), v[2].min(), v[3].max()]
        # carry into piece p: forward over the pieces before it, backward over those after it
        big = np.full((3, 1), _BIG)
        self.f_up = np.minimum.accumulate(np.concatenate([big, m[0]], axis=1), axis=1)[:, :-1]
        self.f_dn = np.maximum.accumulate(np.concatenate([-big, m[1]], axis=1), axis=1)[:, :-1]
        self.b_up = np.minimum.accumulate(np.concatenate([big, m[2][:, ::-1]], axis=1), axis=1)[:, :-1][:, ::-1]
        self.b_dn = np.maximum.accumulate(np.concatenate([-big, m[3][:, ::-1]], axis=1), axis=1)[:, :-1][:, ::-1]

    def _terms(self, a: int, e: slice) -> tuple:
        """(c - S j, c + S j, c + S j, c - S j) on the fixed samples of axis ``a`` in ``e``, +-big elsewhere."""
        fx, c, Sj = self.fixed[a, e], self.c[a, e], self.S * np.arange(e.start, e.stop)
        return (
            np.where(fx, c - Sj, _BIG),
            np.where(fx, c + Sj, -_BIG),
            np.where(fx, c + Sj, _BIG),
            np.where(fx, c - Sj, -_BIG),
        )

    def piece(self, e: slice) -> tuple[np.ndarray, np.ndarray]:
        """(lo, hi), (3, len) each, of the edges ``e`` (``e.start`` a multiple of :data:`CHECK_CHUNK`)."""
        p = e.start // CHECK_CHUNK
        ln = e.stop - e.start
        lo, hi = np.full((3, ln), -self.G), np.full((3, ln), self.G)
        G, S = self.G, self.S
        for a in self.rows:
            fx, c, Sj = self.fixed[a, e], self.c[a, e], S * np.arange(e.start, e.stop)
            t_fup, t_fdn, t_bup, t_bdn = self._terms(a, e)
            # forward: min over j<=n of c_j + S(n-j) = S n + min(c_j - S j); backward: min over j>=n of c_j + S(j-n)
            f_up = np.minimum(np.minimum.accumulate(t_fup), self.f_up[a, p]) + Sj
            f_dn = np.maximum(np.maximum.accumulate(t_fdn), self.f_dn[a, p]) - Sj
            b_up = np.minimum(np.minimum.accumulate(t_bup[::-1])[::-1], self.b_up[a, p]) - Sj
            b_dn = np.maximum(np.maximum.accumulate(t_bdn[::-1])[::-1], self.b_dn[a, p]) + Sj
            h = np.minimum(np.minimum(f_up, b_up), G)
            lw = np.maximum(np.maximum(f_dn, b_dn), -G)
            hi[a] = np.where(fx, c, np.minimum(h, np.where(fx, c, _BIG)))
            lo[a] = np.where(fx, c, np.maximum(lw, np.where(fx, c, -_BIG)))
        return lo, hi


class EdgeProjector:
    """Projection of raster-edge gradient samples onto the hard-limit set of one sequence.

    Args:
        base_edges_mT_per_m: (3, N+1) base demanded gradient at raster edges (fixed values), mT/m.
        free_edges: (3, N+1) bool, True where the optimizer may change the sample.
        raster_s: gradient raster time, s.
        limits: :class:`Limits` (with a ``rotation``: the limits hold on the physical axes too, per-sample
            boxes ``dlo``/``dhi`` bound the steps; without one every step is bounded by ``step``).
    Raises:
        LimitError: when a fixed sample or a fixed-fixed segment already breaks the limits (on the logical
            axes, and on the physical ones at an oblique orientation), or when the fixed samples leave no
            waveform that meets them (empty reachability envelope).
    """

    _local = True  # a long sequence projected only where it is outside the set (:meth:`_bad_spans`); not a span's own

    def __init__(
        self,
        base_edges_mT_per_m: np.ndarray,
        free_edges: np.ndarray,
        raster_s: float,
        limits: Limits,
        fixed_tol: float = 1e-6,
    ):
        e0 = np.asarray(base_edges_mT_per_m, dtype=np.float64)
        free = np.asarray(free_edges, dtype=bool)
        if e0.ndim != 2 or e0.shape[0] != 3 or free.shape != e0.shape:
            raise ValueError(f"edges must be (3, N+1) with a matching mask, got {e0.shape} / {free.shape}")
        self.base = e0
        self.free = free
        self.raster_s = float(raster_s)
        self.limits = limits
        G = limits.gmax_eff_mT_per_m
        S = limits.step_max_mT_per_m(raster_s)
        S_true = limits.step_max_mT_per_m(raster_s, margin=False)
        self.step = S
        fixed = ~free
        # fixed samples and fixed-fixed segments must already be within the true limits
        n_e = e0.shape[1]
        gbad = limits.gmax_mT_per_m * (1 + fixed_tol)
        hit = _first_in_pieces(n_e, lambda e: fixed[:, e] & (np.abs(e0[:, e]) > gbad))
        if hit is not None:
            a, n = hit
            raise LimitError(
                f"fixed (non-optimizable) gradient on {AXES[a]} at t={n * raster_s * 1e3:.3f} ms is "
                f"{e0[a, n]:.4g} mT/m, beyond gmax {limits.gmax_mT_per_m:.4g} mT/m"
            )
        sbad = S_true * (1 + fixed_tol) + 1e-12

        def slews(e: slice) -> np.ndarray:  # the held-held steps from the edges of ``e`` (the last edge has none)
            f = fixed[:, e.start : e.stop + 1]
            return (f[:, 1:] & f[:, :-1]) & (np.abs(np.diff(e0[:, e.start : e.stop + 1], axis=1)) > sbad)

        hit = _first_in_pieces(n_e - 1, slews)
        if hit is not None:
            a, n = hit
            raise LimitError(
                f"fixed (non-optimizable) gradient on {AXES[a]} at t={n * raster_s * 1e3:.3f} ms slews "
                f"{abs(e0[a, n + 1] - e0[a, n]) / raster_s * 1e-3:.4g} T/m/s, beyond smax "
                f"{limits.smax_T_per_m_per_s:.4g} T/m/s"
            )
        # reachability envelopes (exact distance transform, two sweeps per direction)
        R = limits.R
        self.uniform = R is None  # one step bound S for every segment (else per-segment bounds dlo..dhi)
        tol = 1e-12
        self._lohi: tuple[np.ndarray, np.ndarray] | None = None  # the whole envelopes, when held (:attr:`lo`)
        if R is None:
            # the envelopes are not held: any piece of them is computed when asked for (:meth:`_box`), from the base
            # and one carry per piece and axis (:class:`_Envelopes`); the whole arrays only for a projection
            self._env = _Envelopes(e0, fixed, G, S)
            # one bound for every step: read-only views of one value, not two whole-sequence arrays
            self.dlo = np.broadcast_to(np.float64(-S), (3, n_e - 1))
            self.dhi = np.broadcast_to(np.float64(S), (3, n_e - 1))

            def empty(e: slice) -> np.ndarray:
                lo_p, hi_p = self._env.piece(e)
                return free[:, e] & (lo_p > hi_p + tol)

            hit = _first_in_pieces(n_e, empty)
            if hit is not None:
                self._empty(*hit)
        else:  # oblique: per-sample boxes within the physical limits that hold the base (module docstring)
            alo, ahi = _physical_boxes(e0, fixed, R, G, limits.gmax_mT_per_m, "amplitude", raster_s)
            fixed_pair = fixed[:, 1:] & fixed[:, :-1]
            self.dlo, self.dhi = _physical_boxes(np.diff(e0, axis=1), fixed_pair, R, S, S_true, "slew", raster_s)
            lo, hi = np.empty_like(e0), np.empty_like(e0)
            for a in range(3):
                lo[a], hi[a], t = _envelope_var(alo[a], ahi[a], self.dlo[a], self.dhi[a])
                tol = max(tol, t)
            lo = np.where(fixed, e0, lo)
            hi = np.where(fixed, e0, hi)
            # the envelopes' sums round by ~1e-16 of their size: a box that is one value stays one value
            thin = (lo > hi) & (lo <= hi + tol)
            mid = 0.5 * (lo + hi)
            lo, hi = np.where(thin, mid, lo), np.where(thin, mid, hi)
            self._lohi = (lo, hi)
            bad_box = free & (lo > hi + tol)
            if bad_box.any():
                self._empty(*np.argwhere(bad_box)[0])
        # free-free neighbour pairs (fixed neighbours are folded into the envelopes)
        self.pair_free = free[:, 1:] & free[:, :-1]
        self.n_edges = n_e
        self._layout_made: _Layout | None = None  # Dykstra's reordered copies: made on its first use (:attr:`_layout`)
        self._on_device: dict = {}  # the arrays as float64 tensors, per torch device (:meth:`_device_arrays`)

    def _empty(self, a: int, n: int):
        lim = self.limits
        raise LimitError(
            f"no waveform on {AXES[a]} meets gmax {lim.gmax_mT_per_m:.4g} mT/m and smax "
            f"{lim.smax_T_per_m_per_s:.4g} T/m/s between the fixed samples near t={n * self.raster_s * 1e3:.3f} ms"
        )

    @property
    def lo(self) -> np.ndarray:
        """(3, N+1) lower reachability envelope (made whole on first use and kept; :meth:`_box` for a piece)."""
        return self._whole()[0]

    @property
    def hi(self) -> np.ndarray:
        """(3, N+1) upper reachability envelope (as :attr:`lo`)."""
        return self._whole()[1]

    def _whole(self) -> tuple[np.ndarray, np.ndarray]:
        if self._lohi is None:
            lo, hi = np.empty(self.base.shape), np.empty(self.base.shape)
            for a0 in range(0, self.n_edges, CHECK_CHUNK):
                e = slice(a0, min(a0 + CHECK_CHUNK, self.n_edges))
                lo[:, e], hi[:, e] = self._env.piece(e)
            self._lohi = (lo, hi)
        return self._lohi

    def _box(self, e: slice) -> tuple[np.ndarray, np.ndarray]:
        """(lo, hi) of the edges ``e`` (a slice): views of the whole envelopes when held, else computed."""
        if self._lohi is not None:
            return self._lohi[0][:, e], self._lohi[1][:, e]
        return self._env.piece(e)

    # ---- projection ----------------------------------------------------------------------------
    def project(self, edges, n_iter: int = 30, exact: bool = True):
        """Project edge samples onto the limit set.

        Args:
            edges: (3, N+1) numpy array or torch tensor, mT/m.  A tensor on an accelerator is projected there, in
                float64, with no copy to the host (with ``exact`` the repair's sweeps wait for the device, see
                :meth:`_project_device`).
            n_iter: Dykstra iterations (the approximation of the Euclidean projection).
            exact: apply the feasibility repair, which makes the result meet the (margin) limits
                by construction; without it the result is only approximately feasible (cheap, for
                inner iterations).
        Returns:
            the projected samples, same type/dtype/device as ``edges`` (detached for tensors).
        """
        is_t = isinstance(edges, torch.Tensor)
        if is_t and edges.device.type not in HOST_DEVICES:
            return self._project_device(edges, n_iter, exact)
        # (a float64 tensor's numpy view, not a copy: np.where below makes the one copy)
        x0 = np.asarray(edges.detach().cpu().numpy() if is_t else edges, dtype=np.float64)
        x = np.where(self.free, x0, self.base)
        if not self.is_feasible(x, tol=0.0):  # else already in the set: the projection is the identity (bit for bit)
            spans = self._bad_spans(x) if self._local and self.n_edges > LOCAL_MIN_EDGES else None
            if spans is None or not self._project_spans(x, spans, n_iter, exact):
                x = self._dykstra(np.where(self.free, x0, self.base), n_iter)
                if exact:
                    x = self.repair(x)
        if is_t:
            return torch.as_tensor(x, dtype=edges.dtype, device=edges.device)
        return x

    def _piece_bad(self, x: np.ndarray, a: int, b: int, tol: float) -> tuple[np.ndarray, np.ndarray]:
        """The edges ``a..b-1`` (``a`` a multiple of :data:`CHECK_CHUNK`, or the envelopes held) outside their box,
        (3, b - a), and the steps from them beyond their bound, (3, b - a) (at the sequence's end one fewer), at
        ``tol``."""
        e, s = slice(a, b), slice(a, b - 1 if b == self.n_edges else b)  # the piece's edges and steps
        xe = x[:, e]
        lo, hi = self._box(e)
        box = (xe < lo - tol) | (xe > hi + tol)
        d = np.diff(x[:, a : s.stop + 1], axis=1)
        if self.uniform:
            step = self.pair_free[:, s] & (np.abs(d) > self.step + tol)
        else:
            step = self.pair_free[:, s] & ((d > self.dhi[:, s] + tol) | (d < self.dlo[:, s] - tol))
        return box, step

    def _bad_spans(self, x: np.ndarray) -> list[tuple[int, int]] | None:
        """The spans ``[a, b)`` of edges around the places where ``x`` is outside the set at tolerance 0 (each
        :data:`LOCAL_MARGIN` edges on either side, ``a`` even, overlapping ones merged), found piece by piece;
        None when they would cover more than half the sequence (then the whole is projected)."""
        spans: list[list[int]] = []
        n, m, covered = self.n_edges, LOCAL_MARGIN, 0
        for a0 in range(0, n, CHECK_CHUNK):
            box, step = self._piece_bad(x, a0, min(a0 + CHECK_CHUNK, n), 0.0)
            s = np.flatnonzero(step.any(axis=0))
            bad = np.union1d(np.flatnonzero(box.any(axis=0)), np.r_[s, s + 1]) + a0  # a step: both its edges
            if bad.size == 0:
                continue
            cut = np.flatnonzero(np.diff(bad) > 2 * m) + 1
            for first, last in zip(bad[np.r_[0, cut]], bad[np.r_[cut - 1, bad.size - 1]]):
                lo, hi = max(int(first) - m, 0) & ~1, min(int(last) + 1 + m, n)
                if spans and lo <= spans[-1][1]:
                    covered -= spans[-1][1] - spans[-1][0]
                    spans[-1][1] = max(spans[-1][1], hi)
                else:
                    spans.append([lo, hi])
                covered += spans[-1][1] - spans[-1][0]
                if 2 * covered > n:
                    return None
        return [(a, b) for a, b in spans]

    def _project_spans(self, x: np.ndarray, spans: list[tuple[int, int]], n_iter: int, exact: bool) -> bool:
        """Project only ``spans`` of ``x`` (in place), each on its own with its first and last edge held at ``x``'s
        values (the rest of ``x`` is in the set), then check the whole result at the default tolerance (1e-9
        mT/m: the whole projection's own result is within its limits to rounding, not always at 0; the envelopes'
        ``(c - S j) + S n`` round by up to ~5e-10 mT/m at millions of edges).  False when that check fails
        (``x`` then partly projected): the caller projects the whole."""
        pieces: dict = {}  # the envelopes' pieces the spans (in order) are in: each made once
        for a, b in spans:
            for p in [p for p in pieces if p + CHECK_CHUNK <= a]:
                del pieces[p]
            x[:, a:b] = self._span(x, a, b, pieces).project(x[:, a:b], n_iter, exact)
        return self.is_feasible(x)

    def _span(self, x: np.ndarray, a: int, b: int, pieces: dict) -> EdgeProjector:
        """The projector of the edges ``a..b-1``: this one's envelopes, step bounds and fixed samples there, and
        the span's first and last edge (inside the sequence) held at ``x``'s values.  ``pieces``: {start: (lo, hi)}
        of the envelopes' pieces made so far (added to)."""
        sub = object.__new__(EdgeProjector)
        lo, hi = (np.array(v) for v in self._box_range(a, b, pieces))
        free, base = self.free[:, a:b].copy(), self.base[:, a:b].copy()
        for i, edge in ((0, a > 0), (b - a - 1, b < self.n_edges)):
            if edge:
                free[:, i] = False
                base[:, i] = lo[:, i] = hi[:, i] = x[:, a + i]
        sub.base, sub.free, sub.raster_s, sub.limits = base, free, self.raster_s, self.limits
        sub.step, sub.uniform, sub._lohi = self.step, self.uniform, (lo, hi)
        sub.dlo, sub.dhi = self.dlo[:, a : b - 1], self.dhi[:, a : b - 1]
        sub.pair_free = free[:, 1:] & free[:, :-1]
        sub.n_edges, sub._layout_made, sub._on_device, sub._local = b - a, None, {}, False
        return sub

    def _box_range(self, a: int, b: int, pieces: dict) -> tuple[np.ndarray, np.ndarray]:
        """(lo, hi) of the edges ``a..b-1``, any span (:meth:`_box` takes whole pieces; ``pieces`` keeps them)."""
        if self._lohi is not None:
            return self._lohi[0][:, a:b], self._lohi[1][:, a:b]
        p0 = a - a % CHECK_CHUNK
        for p in range(p0, b, CHECK_CHUNK):
            if p not in pieces:
                pieces[p] = self._box(slice(p, min(p + CHECK_CHUNK, self.n_edges)))
        parts = [pieces[p] for p in range(p0, b, CHECK_CHUNK)]
        lo, hi = (np.concatenate([q[i] for q in parts], axis=1)[:, a - p0 : b - p0] for i in (0, 1))
        return lo, hi

    @property
    def _layout(self) -> _Layout:
        """Dykstra's arrays (the box reordered, the pair sets' bounds: ~150 bytes per edge), made when a projection
        first needs them: a run whose waveform is already in the set (a windowed solve's) never holds them."""
        if self._layout_made is None:
            self._layout_made = _Layout.make(self.free, self.lo, self.hi, self.pair_free, self.dlo, self.dhi)
        return self._layout_made

    def _dykstra(self, x: np.ndarray, n_iter: int) -> np.ndarray:
        return _dykstra(_NP, x, self._layout, self.step if self.uniform else None, n_iter)

    def _device_arrays(self, device) -> dict:
        """lo, hi, base, free, pair_free, dlo, dhi and the pair sets as tensors on ``device`` (made once)."""
        key = str(device)
        if key not in self._on_device:

            def t(a):  # (a read-only view, e.g. a broadcast box, is copied: torch wants writable memory)
                return torch.as_tensor(
                    a if not isinstance(a, np.ndarray) or a.flags.writeable else a.copy(), device=device
                )

            self._on_device[key] = {
                **{k: t(getattr(self, k)) for k in ("lo", "hi", "base", "free", "pair_free", "dlo", "dhi")},
                "layout": self._layout.to(t),
            }
        return self._on_device[key]

    def _project_device(self, edges: torch.Tensor, n_iter: int, exact: bool) -> torch.Tensor:
        """:meth:`project` of a tensor where it lies, in float64 (the same operations as the numpy path, so the
        same numbers).  Without ``exact`` nothing waits for the device: the identity on a point already in the
        set is a select on the device, not a branch on the host.  With it, the repair's sweeps check on the host
        whether they are done (one scalar each; a long chain of active limits finishes on the host)."""
        d = self._device_arrays(edges.device)
        x = torch.where(d["free"], edges.detach().to(torch.float64), d["base"])
        key = ("dykstra", n_iter)
        if key not in d:  # its ~25 n_iter small operations as one CUDA graph (dtoc.util.replay)
            step = self.step if self.uniform else None
            d[key] = Replay(lambda z: (_dykstra(_TORCH, z, d["layout"], step, n_iter),))
        (y,) = d[key](x)
        if exact:
            y = self._repair_tensor(y, d)
        return torch.where(self._feasible_tensor(x, d, 0.0), x, y).to(edges.dtype)

    def _repair_tensor(self, x: torch.Tensor, d: dict) -> torch.Tensor:
        """:meth:`repair` of a float64 tensor where it lies (the same numbers)."""
        x = torch.where(d["free"], x, d["base"])
        if bool(self._feasible_tensor(x, d, 0.0)):
            return x
        axes = torch.nonzero(d["free"].any(dim=1)).flatten()
        out = _greedy_mean(_TORCH, x, d["lo"], d["hi"], d["dlo"], d["dhi"], axes)
        return torch.where(d["free"], torch.clamp(out, d["lo"], d["hi"]), d["base"])

    def _feasible_tensor(self, x: torch.Tensor, d: dict, tol: float) -> torch.Tensor:
        """:meth:`is_feasible` as a 0-dim bool tensor on x's device (nothing waits for it)."""
        inside = ((x >= d["lo"] - tol) & (x <= d["hi"] + tol)).all()
        s = torch.diff(x, dim=1)
        if self.uniform:
            bad = d["pair_free"] & (s.abs() > self.step + tol)
        else:
            bad = d["pair_free"] & ((s > d["dhi"] + tol) | (s < d["dlo"] - tol))
        return inside & ~bad.any()

    def is_feasible(self, x: np.ndarray, tol: float = 1e-9) -> bool:
        """True if ``x`` (3, N+1) meets the margin limits and the fixed values."""
        x = np.asarray(x, dtype=np.float64)
        for a in range(0, self.n_edges, CHECK_CHUNK):  # in pieces: the temporaries are one piece's, not the sequence's
            box, step = self._piece_bad(x, a, min(a + CHECK_CHUNK, self.n_edges), tol)
            if box.any() or step.any():
                return False
        return True

    def at_limits(self, x: np.ndarray, rtol: float = 1e-6) -> tuple[np.ndarray, np.ndarray]:
        """(amplitude, slew) masks of free edges at their bound and free segments at theirs ((3, N+1) and
        (3, N), within ``rtol`` of the step bound)."""
        x = np.asarray(x, dtype=np.float64)
        t = rtol * max(self.step, 1e-9)
        amp, slew = np.empty(self.free.shape, dtype=bool), np.empty(self.pair_free.shape, dtype=bool)
        n = self.n_edges
        for a in range(0, n, CHECK_CHUNK):  # in pieces: the envelopes are not made whole (nor kept)
            b = min(a + CHECK_CHUNK, n)
            e, s = slice(a, b), slice(a, b - 1 if b == n else b)
            lo, hi = self._box(e)
            amp[:, e] = self.free[:, e] & ((x[:, e] >= hi - t) | (x[:, e] <= lo + t))
            d = np.diff(x[:, a : s.stop + 1], axis=1)
            if self.uniform:
                slew[:, s] = self.pair_free[:, s] & (np.abs(d) >= self.step * (1 - rtol))
            else:
                slew[:, s] = self.pair_free[:, s] & ((d >= self.dhi[:, s] - t) | (d <= self.dlo[:, s] + t))
        return amp, slew

    def repair(self, x: np.ndarray) -> np.ndarray:
        """Feasible-by-construction correction (mean of forward and backward greedy passes)."""
        x = np.where(self.free, np.asarray(x, dtype=np.float64), self.base)
        if self.is_feasible(x, tol=0.0):
            return x
        out = _greedy_mean(_NP, x, self.lo, self.hi, self.dlo, self.dhi, np.flatnonzero(self.free.any(axis=1)))
        out = np.where(self.free, np.clip(out, self.lo, self.hi), self.base)
        return out

    # ---- fine grid -------------------------------------------------------------------------------
    def fine_free_mask(self) -> np.ndarray:
        """(3, 2N+1) True on fine samples that follow the edge variables (free edges and their centres)."""
        return fine_free_mask(self.free)


def fine_free_mask(free: np.ndarray) -> np.ndarray:
    """(3, 2N+1) True on fine samples that follow free edges (3, N+1): the edges and their centres."""
    m = np.zeros((3, 2 * free.shape[1] - 1), dtype=bool)
    m[:, ::2] = free
    m[:, 1::2] = free[:, 1:] | free[:, :-1]
    return m


def edges_to_played(edges, base_fine, fine_mask):
    """Fine-grid played waveform (3, 2N+1) from edge samples.

    Fine samples flagged in ``fine_mask`` (see :meth:`EdgeProjector.fine_free_mask`) follow the edges
    (raster centres = mean of neighbours); the others keep the base waveform (exactly as played,
    e.g. arbitrary-gradient centre samples).  Differentiable for torch input.
    """
    from dtoc.seq.ir import edges_to_fine

    fine = edges_to_fine(edges)
    if isinstance(fine, torch.Tensor):
        base = torch.as_tensor(np.asarray(base_fine), dtype=fine.dtype, device=fine.device)
        mask = torch.as_tensor(np.asarray(fine_mask), device=fine.device)
        return torch.where(mask, fine, base)
    base_fine = np.asarray(base_fine)
    if fine.dtype != np.result_type(fine, base_fine):
        return np.where(fine_mask, fine, base_fine)
    np.copyto(fine, base_fine, where=~np.asarray(fine_mask))  # np.where's values, without a second (3, 2N+1) array
    return fine


def check_area_reachable(ir, limits: Limits, rel_tol: float = 1e-3) -> None:
    """Raise LimitError when gmax is below the gradient the ADC sample spacing needs.

    Between two consecutive samples of one ADC the target k-space moves by ``dk_i``; any waveform
    covering it within one dwell needs a mean gradient ``|dk_i| / (gamma * dwell)`` on that axis.
    """
    if not ir.adc:
        return
    k0 = ir.nominal_kspace_rad_per_m()
    start = 0
    need = np.zeros(3)
    for adc in ir.adc:
        seg = k0[:, start : start + adc.num_samples]
        start += adc.num_samples
        if seg.shape[1] > 1:
            need = np.maximum(need, np.abs(np.diff(seg, axis=1)).max(axis=1) / (GAMMA_RAD_PER_S_PER_MT * adc.dwell_s))
    a = int(np.argmax(need))
    if need[a] > limits.gmax_mT_per_m * (1 + rel_tol):
        raise LimitError(
            f"gmax {limits.gmax_mT_per_m:.4g} mT/m is below the {need[a]:.4g} mT/m the readout on {AXES[a]} "
            "needs to move between ADC samples: no waveform can sample the target k-space"
        )
