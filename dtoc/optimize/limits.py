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


@dataclass(frozen=True)
class Limits:
    """Per-axis hardware limits.

    Attributes:
        gmax_mT_per_m: maximum gradient amplitude per axis, mT/m.
        smax_T_per_m_per_s: maximum slew rate per axis, T/m/s (= mT/m/ms).
        amp_margin: relative safety margin applied to free samples' amplitude (0.005 = 0.5 %).
        slew_margin: relative safety margin applied to free segments' slew.
    """

    gmax_mT_per_m: float
    smax_T_per_m_per_s: float
    amp_margin: float = 0.005
    slew_margin: float = 0.01

    def __post_init__(self):
        if not (np.isfinite(self.gmax_mT_per_m) and self.gmax_mT_per_m > 0):
            raise LimitError(f"gmax must be a positive number of mT/m, got {self.gmax_mT_per_m}")
        if not (np.isfinite(self.smax_T_per_m_per_s) and self.smax_T_per_m_per_s > 0):
            raise LimitError(f"smax must be a positive number of T/m/s, got {self.smax_T_per_m_per_s}")
        if not (0 <= self.amp_margin < 0.5 and 0 <= self.slew_margin < 0.5):
            raise LimitError("limit safety margins must lie in [0, 0.5)")

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
    amp = np.abs(g).max(axis=-1) if g.shape[-1] else np.zeros(g.shape[0])
    slew = (np.abs(np.diff(g, axis=-1)).max(axis=-1) / dt_fine_s * 1e-3) if g.shape[-1] > 1 else np.zeros(g.shape[0])
    return {"gmax_mT_per_m": amp.tolist(), "smax_T_per_m_per_s": slew.tolist()}


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


def _greedy_pass(y: np.ndarray, lo: np.ndarray, hi: np.ndarray, step: float) -> np.ndarray:
    """Sequential clip: x[n] = clip(y[n], [lo[n], hi[n]] & [x[n-1]-step, x[n-1]+step]) (1-D)."""
    yl, lol, hil = y.tolist(), lo.tolist(), hi.tolist()
    out = [0.0] * len(yl)
    prev = None
    for n, v in enumerate(yl):
        a, b = lol[n], hil[n]
        if prev is not None:
            a = max(a, prev - step)
            b = min(b, prev + step)
        if a > b:  # cannot happen with Lipschitz envelopes; keep the bound nearest to feasibility
            b = a
        prev = a if v < a else (b if v > b else v)
        out[n] = prev
    return np.asarray(out)


class EdgeProjector:
    """Projection of raster-edge gradient samples onto the hard-limit set of one sequence.

    Args:
        base_edges_mT_per_m: (3, N+1) base demanded gradient at raster edges (fixed values), mT/m.
        free_edges: (3, N+1) bool, True where the optimizer may change the sample.
        raster_s: gradient raster time, s.
        limits: :class:`Limits`.
    Raises:
        LimitError: when a fixed sample or a fixed-fixed segment already breaks the limits, or when
            the fixed samples leave no waveform that meets them (empty reachability envelope).
    """

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
        bad = fixed & (np.abs(e0) > limits.gmax_mT_per_m * (1 + fixed_tol))
        if bad.any():
            a, n = np.argwhere(bad)[0]
            raise LimitError(
                f"fixed (non-optimizable) gradient on {AXES[a]} at t={n * raster_s * 1e3:.3f} ms is "
                f"{e0[a, n]:.4g} mT/m, beyond gmax {limits.gmax_mT_per_m:.4g} mT/m"
            )
        ff = fixed[:, 1:] & fixed[:, :-1]
        badslew = ff & (np.abs(np.diff(e0, axis=1)) > S_true * (1 + fixed_tol) + 1e-12)
        if badslew.any():
            a, n = np.argwhere(badslew)[0]
            raise LimitError(
                f"fixed (non-optimizable) gradient on {AXES[a]} at t={n * raster_s * 1e3:.3f} ms slews "
                f"{abs(e0[a, n + 1] - e0[a, n]) / raster_s * 1e-3:.4g} T/m/s, beyond smax "
                f"{limits.smax_T_per_m_per_s:.4g} T/m/s"
            )
        # reachability envelopes (exact distance transform, two sweeps per direction)
        n_e = e0.shape[1]
        lo = np.full(e0.shape, -G)
        hi = np.full(e0.shape, G)
        lo[fixed] = e0[fixed]
        hi[fixed] = e0[fixed]
        for a in range(3):
            if not fixed[a].any():
                continue
            lo[a], hi[a] = self._envelope(e0[a], fixed[a], G, S)
        self.lo, self.hi = lo, hi
        empty = free & (lo > hi + 1e-12)
        if empty.any():
            a, n = np.argwhere(empty)[0]
            raise LimitError(
                f"no waveform on {AXES[a]} meets gmax {limits.gmax_mT_per_m:.4g} mT/m and smax "
                f"{limits.smax_T_per_m_per_s:.4g} T/m/s between the fixed samples near t={n * raster_s * 1e3:.3f} ms"
            )
        # free-free neighbour pairs (fixed neighbours are folded into the envelopes)
        self.pair_free = free[:, 1:] & free[:, :-1]
        self.n_edges = n_e

    @staticmethod
    def _envelope(c: np.ndarray, fixed: np.ndarray, G: float, S: float):
        n = c.size
        idx = np.arange(n)
        big = 1e300
        # upper: min_j (c_j + S|n-j|), lower: max_j (c_j - S|n-j|), via forward/backward running extrema
        up = np.where(fixed, c, big)
        dn = np.where(fixed, c, -big)
        # forward: min over j<=n of c_j + S(n-j) = S n + min(c_j - S j)
        f_up = np.minimum.accumulate(np.where(fixed, c - S * idx, big)) + S * idx
        f_dn = np.maximum.accumulate(np.where(fixed, c + S * idx, -big)) - S * idx
        # backward: min over j>=n of c_j + S(j-n)
        b_up = np.minimum.accumulate(np.where(fixed, c + S * idx, big)[::-1])[::-1] - S * idx
        b_dn = np.maximum.accumulate(np.where(fixed, c - S * idx, -big)[::-1])[::-1] + S * idx
        hi = np.minimum(np.minimum(f_up, b_up), G)
        lo = np.maximum(np.maximum(f_dn, b_dn), -G)
        hi = np.where(fixed, c, np.minimum(hi, up))
        lo = np.where(fixed, c, np.maximum(lo, dn))
        return lo, hi

    # ---- projection ----------------------------------------------------------------------------
    def _pair_project(self, x: np.ndarray, start: int) -> np.ndarray:
        """Exact projection onto {|x[n+1]-x[n]| <= S for free pairs n = start, start+2, ...}."""
        S = self.step
        y = x.copy()
        a = y[:, start:-1:2]
        b = y[:, start + 1 :: 2]
        m = min(a.shape[1], b.shape[1])
        a, b = a[:, :m], b[:, :m]
        mask = self.pair_free[:, start::2][:, :m]
        d = b - a
        excess = np.where(mask, np.clip(np.abs(d) - S, 0.0, None), 0.0) * np.sign(d)
        y[:, start : start + 2 * m : 2] = a + 0.5 * excess
        y[:, start + 1 : start + 1 + 2 * m : 2] = b - 0.5 * excess
        return y

    def _box(self, x: np.ndarray) -> np.ndarray:
        return np.clip(x, self.lo, self.hi)

    def project(self, edges, n_iter: int = 30, exact: bool = True):
        """Project edge samples onto the limit set.

        Args:
            edges: (3, N+1) numpy array or torch tensor, mT/m.
            n_iter: Dykstra iterations (the approximation of the Euclidean projection).
            exact: apply the feasibility repair, which makes the result meet the (margin) limits
                by construction; without it the result is only approximately feasible (cheap, for
                inner iterations).
        Returns:
            the projected samples, same type/dtype/device as ``edges`` (detached for tensors).
        """
        is_t = isinstance(edges, torch.Tensor)
        x = edges.detach().cpu().numpy().astype(np.float64) if is_t else np.asarray(edges, dtype=np.float64)
        x = np.where(self.free, x, self.base)
        if self.is_feasible(x, tol=0.0):  # already in the set: the projection is the identity (bit for bit)
            return torch.as_tensor(x, dtype=edges.dtype, device=edges.device) if is_t else x
        x = self._dykstra(x, n_iter)
        if exact:
            x = self.repair(x)
        if is_t:
            return torch.as_tensor(x, dtype=edges.dtype, device=edges.device)
        return x

    def _dykstra(self, x: np.ndarray, n_iter: int) -> np.ndarray:
        sets = (self._box, lambda v: self._pair_project(v, 0), lambda v: self._pair_project(v, 1))
        incr = [np.zeros_like(x) for _ in sets]
        for _ in range(n_iter):
            for i, P in enumerate(sets):
                z = x + incr[i]
                x_new = P(z)
                incr[i] = z - x_new
                x = x_new
        return self._box(x)

    def is_feasible(self, x: np.ndarray, tol: float = 1e-9) -> bool:
        """True if ``x`` (3, N+1) meets the margin limits and the fixed values."""
        x = np.asarray(x, dtype=np.float64)
        if np.any(x < self.lo - tol) or np.any(x > self.hi + tol):
            return False
        d = np.abs(np.diff(x, axis=1))
        return not np.any(self.pair_free & (d > self.step + tol))

    def repair(self, x: np.ndarray) -> np.ndarray:
        """Feasible-by-construction correction (mean of forward and backward greedy passes)."""
        x = np.where(self.free, np.asarray(x, dtype=np.float64), self.base)
        if self.is_feasible(x, tol=0.0):
            return x
        out = x.copy()
        for a in range(3):
            if not self.free[a].any():
                continue
            fw = _greedy_pass(x[a], self.lo[a], self.hi[a], self.step)
            bw = _greedy_pass(x[a, ::-1], self.lo[a, ::-1], self.hi[a, ::-1], self.step)[::-1]
            out[a] = 0.5 * (fw + bw)
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
    return np.where(fine_mask, fine, base_fine)


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
