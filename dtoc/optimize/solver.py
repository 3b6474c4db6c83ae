"""The warm start's convex problem solved to a stated k-space tolerance (docs/optimize.md, "Solver").

With an affine hardware chain (GIRF, eddy terms, delays, gains, rotations) the warm start's objective
(:func:`dtoc.optimize.optimizer.linear_objective`: k at every ADC sample, the moment before every RF pulse,
G during RF, a tiny change penalty) is a convex quadratic ``f(x) = f0 + g0.d + d.H d / 2`` of the free edges
``x = x0 + d``, and the hard limits are the polyhedron ``lo <= x <= hi``, ``|x[n+1] - x[n]| <= S``
(:class:`~dtoc.optimize.limits.EdgeProjector`).  Its Hessian is dominated by the time integral from the
gradient to k: ``H ~ c (D D^T)^-1`` with ``D`` the first difference on the raster, so its condition number
grows with the square of the number of samples, and so did the iterations of plain CG / FISTA.  Here:

1. **Preconditioned CG** on the unconstrained problem with the preconditioner ``D D^T`` (the inverse of the
   integrator: the path Laplacian of the raster edges, cut where k restarts), whose iteration count does not
   grow with the matrix; with refocusing pulses the exact inverse of the sampled, signed integrator model
   (:class:`PathModel`: k is negated at a refocusing pulse).  Every ``check_every`` iterations the iterate is
   checked: projected and within the tolerance: done; unprojected and within half of it: the CG stops and what
   is left is the limits'.  If the optimum is within the limits: done.
2. Otherwise **active-set rounds**: the CG's optimum is projected exactly onto the limits
   (:meth:`~dtoc.optimize.limits.EdgeProjector.project`); the edges the projection moved are held at their
   projected values and the CG solves again for the others, from there (warm), until no further edge is
   moved, the tolerance is met, or ``max_rounds``.  Every round's iterate is within the limits; the best
   objective is kept, unless a round's iterate meets the stopping rule: that one ends the solve, whatever its
   objective (docs/optimize.md, "An iterate within the tolerance ends the solve").  The held values are the
   projection's, not the constrained optimum's: the rounds are a fast heuristic for the few, local active
   limits (EPI blips and ramps), not a certificate.

Stop reasons (``SolveReport.stop_reason``):

* ``tolerance``: every sample reachable at all, and every moment before an RF pulse the objective holds (k before
  the pulse: a GRE's spoiler), is within ``k_tol_dk`` of its target (after the exact projection: the figure is the
  exported waveform's);
* ``converged``: the last round's CG converged and the projection moved no new edge: no further change
  (the unconstrained optimum within the limits, or the held edges' optimum); the samples still above
  tolerance are named with the reason (:func:`explain_unreachable`);
  also when a round lowered the objective by less than ``stall_rel``;
* ``limits-bound``: the first projection moved more than ``held_max`` of the free edges (a waveform at its
  slew limit throughout): the rounds do not suit it, :func:`dtoc.optimize.optimizer.solve_warm_start` runs
  CG and projected FISTA from the base instead, on the rest of the budget;
* ``rounds``: ``max_rounds`` active-set rounds ran (the samples above tolerance are named as well);
* ``budget``: ``budget`` objective evaluations were spent first.

Units: mT/m (edges), dk (k errors), s.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import numpy as np
import torch

from dtoc.constants import AXES
from dtoc.util.replay import Replay

#: at most this many samples are listed by name in a report (the count is always complete)
MAX_NAMED = 8
#: the path model's weight of k at an edge where nothing is sampled, relative to the mean sampled weight (assumed, a
#: rule of thumb: the GIRF and the fine grid spread every edge's effect a little; measured on a 16-TR version of the
#: spin-echo test of tests/test_opt_solver_moments.py: 1e-3 -> 108 CG iterations, 1e-2 -> 41, 1e-1 -> 39, 1 -> 61)
W_FLOOR = 1e-2


@dataclass
class Unreachable:
    """Samples whose k error stays above the tolerance at the solver's stop, and why.

    Attributes:
        indices: indices into the solver's errors: ADC samples (the sequence's concatenated samples) first, then,
            from ``n_adc`` on, the moments before the RF pulses the objective holds (moment ``j``: before RF pulse
            ``j + 1``, 0-based, the first pulse having none).
        error_dk: their k error, dk.
        reason: per sample: 'fixed' (not reachable even without the limits: the free edges cannot move it,
            e.g. the hardware's response to fixed RF-block gradients), 'unresolved' (the unconstrained solve did
            not converge within its budget: no claim), or 'limits' (reachable without them).
        limit: per sample, the active limit nearest before it: 'slew x', 'amplitude y', ... ('' if none).
        limit_time_s: the time of that active limit, s (nan if none).
        unconstrained_dk: per sample, its error at the unconstrained optimum (how far the limits cost).
        n_adc: the number of ADC samples among the errors (None: every error is an ADC sample's).
    """

    indices: np.ndarray
    error_dk: np.ndarray
    reason: list[str]
    limit: list[str]
    limit_time_s: np.ndarray
    unconstrained_dk: np.ndarray
    n_adc: int | None = None

    def _moment(self, i: int) -> int | None:
        """The moment index of entry ``i`` (None: an ADC sample)."""
        j = int(self.indices[i])
        return None if self.n_adc is None or j < self.n_adc else j - self.n_adc

    def _pulse(self, i: int) -> int | None:
        """The RF pulse (0-based) that entry ``i``'s moment comes before (None: an ADC sample)."""
        m = self._moment(i)
        return None if m is None else m + 1

    def name(self, i: int) -> str:
        p = self._pulse(i)
        return f"sample {int(self.indices[i])}" if p is None else f"moment before RF pulse {p}"

    def as_dict(self, max_named: int = MAX_NAMED) -> dict:
        order = np.argsort(-self.error_dk)[:max_named]
        n_mom = 0 if self.n_adc is None else int((self.indices >= self.n_adc).sum())
        return {
            "n_samples": int(self.indices.size) - n_mom,
            "n_moments": n_mom,
            "n_fixed": int(sum(r == "fixed" for r in self.reason)),
            "n_limits": int(sum(r == "limits" for r in self.reason)),
            "n_unresolved": int(sum(r == "unresolved" for r in self.reason)),
            "worst": [
                {
                    "sample": None if self._moment(i) is not None else int(self.indices[i]),
                    "moment_before_rf_pulse": self._pulse(i),
                    "error_dk": float(self.error_dk[i]),
                    "reason": self.reason[i],
                    "unconstrained_error_dk": float(self.unconstrained_dk[i]),
                    "limit": self.limit[i] or None,
                    "limit_time_ms": None if not math.isfinite(self.limit_time_s[i]) else 1e3 * self.limit_time_s[i],
                }
                for i in order
            ],
        }

    def summary(self) -> str:
        """One line: how many samples, the worst ones and why."""
        if self.indices.size == 0:
            return ""
        parts = []
        for i in np.argsort(-self.error_dk)[:3]:
            why = (
                f"not reachable by the free gradient even without limits ({self.unconstrained_dk[i]:.3g} dk)"
                if self.reason[i] == "fixed"
                else "the solve did not converge within its budget"
                if self.reason[i] == "unresolved"
                else f"{self.limit[i] or 'a'} limit active at {1e3 * self.limit_time_s[i]:.3f} ms "
                f"(without limits {self.unconstrained_dk[i]:.3g} dk)"
            )
            parts.append(f"{self.name(i)} at {self.error_dk[i]:.3g} dk: {why}")
        n_mom = 0 if self.n_adc is None else int((self.indices >= self.n_adc).sum())
        what = f"{self.indices.size - n_mom} samples" + (f" and {n_mom} moments" if n_mom else "")
        return f"{what} above tolerance; " + "; ".join(parts)


@dataclass
class SolveReport:
    """What the solver did: the manifest's ``solver`` record."""

    method: str = "pcg-active-set"
    k_tol_dk: float = 0.01
    stop_reason: str = ""
    evaluations: int = 0
    cg_iterations: int = 0
    rounds: int = 0
    achieved_max_dk: float = math.nan
    moment_max_dk: float | None = None  # the moments' (k before each RF pulse the objective holds); None: none
    unconstrained_max_dk: float = math.nan
    within_limits_unconstrained: bool = False
    unreachable: Unreachable | None = None
    history: list = field(default_factory=list)
    unconstrained_errors: np.ndarray | None = None  # (N_adc,) dk, at the unconstrained solve
    unconstrained_converged: bool = False
    fallback_stop: str | None = None  # the CG + FISTA fallback's own stop reason (None: it did not run)
    minimax: dict | None = None  # the minimax rounds' record (None: they did not run; optimizer.minimax_rounds_solve)

    def as_dict(self) -> dict:
        return {
            "method": self.method,
            "k_tol_dk": self.k_tol_dk,
            "stop_reason": self.stop_reason,
            "evaluations": self.evaluations,
            "cg_iterations": self.cg_iterations,
            "active_set_rounds": self.rounds,
            "achieved_max_dk": self.achieved_max_dk,
            "moment_max_dk": self.moment_max_dk,
            "unconstrained_max_dk": self.unconstrained_max_dk,
            "unconstrained_within_limits": self.within_limits_unconstrained,
            "unreachable": None if self.unreachable is None else self.unreachable.as_dict(),
            "fallback_stop_reason": self.fallback_stop,
            "minimax": self.minimax,
        }

    def line(self) -> str:
        """The stderr line."""
        s = (
            f"solver: {self.stop_reason} after {self.evaluations} evaluations ({self.cg_iterations} CG iterations, "
            f"{self.rounds} active-set rounds); max k error {self.achieved_max_dk:.3g} dk (norm over the encoded axes)"
            + ("" if self.moment_max_dk is None else f", moments before RF pulses {self.moment_max_dk:.3g} dk")
            + f" (tolerance {self.k_tol_dk:g} dk)"
        )
        if self.minimax is not None:
            m = self.minimax
            s += (
                f"; minimax rounds {m['rounds']} ({m['evaluations']} evaluations, {m['max_before_dk']:.3g} -> "
                f"{m['max_after_dk']:.3g} dk, stop {m['stop_reason']})"
            )
        if self.unreachable is not None and self.unreachable.indices.size:
            s += "; " + self.unreachable.summary()
        return s

    def set_errors(self, err: np.ndarray, n_adc: int | None = None) -> None:
        """``achieved_max_dk`` (the ADC samples') and ``moment_max_dk`` from the solver's errors (``n_adc`` ADC
        samples first, then the moments; None: all ADC samples)."""
        n = err.size if n_adc is None else n_adc
        self.achieved_max_dk = float(err[:n].max()) if n else 0.0
        self.moment_max_dk = None if n_adc is None or err.size == n else float(err[n:].max())


class _Stop(Exception):
    pass


class _Reached(Exception):
    """The first CG's iterate, projected, has every sample within the tolerance (:func:`solve_to_tolerance`)."""

    def __init__(self, d: torch.Tensor, it: int):
        super().__init__()
        self.d, self.it = d, it


def free_gradient(f, free: torch.Tensor, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, Mapping]:
    """One evaluation of an objective ``f`` (``x -> (loss, terms)``) and its gradient: (the gradient on the free
    entries, zero elsewhere; the loss as a detached 0-dim tensor; the terms).  Nothing waits for the device: the
    step a :class:`~dtoc.util.replay.Replay` holds (here and in :mod:`dtoc.optimize.optimizer`)."""
    x = x.detach().requires_grad_(True)
    val, terms = f(x)
    (gx,) = torch.autograd.grad(val, x)
    return torch.where(free, gx, torch.zeros_like(gx)), val.detach(), terms


class _Quadratic:
    """f, its gradient and Hessian-vector products of a quadratic objective of the free edges."""

    def __init__(self, f, x0: torch.Tensor, free: torch.Tensor, budget: int):
        self.f, self.x0, self.free, self.budget = f, x0, free, budget
        self.n = 0
        self._eval = Replay(self._step)  # one CUDA graph per evaluation on a GPU (dtoc.util.replay)
        self.g0, f0 = self.grad(x0)
        self.f0 = float(f0)

    def _step(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return free_gradient(self.f, self.free, x)[:2]

    def grad(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(gradient on the free edges, objective as a 0-dim tensor: nothing waits for the device)."""
        if self.n >= self.budget:
            raise _Stop
        self.n += 1
        g, val = self._eval(x)  # (Replay returns a tuple of any length: two here)
        return g, val

    def hv(self, v: torch.Tensor) -> torch.Tensor:
        return self.grad(self.x0 + v)[0] - self.g0

    def value(self, d: torch.Tensor, Hd: torch.Tensor) -> float:
        return self.f0 + float((self.g0 * d).sum()) + 0.5 * float((d * Hd).sum())


class _Precond:
    """The inverse of the integrator model of the Hessian, ``H ~ c (D D^T)^-1``: a free edge moves the k of
    every later sample up to the next excitation (D the first difference on the raster).  ``D D^T`` is the
    path graph's Laplacian on the raster edges (``2 r[n] - r[n-1] - r[n+1]``), cut at the excitations
    (``cuts``: edge indices where k restarts, each period its own Neumann path), plus the smallest nonzero
    eigenvalue's half of each period on the diagonal (positive definite); restricted to the variables ``act``.
    The scale c does not matter to CG.  With it the CG's iteration count depends on the chain's frequency
    response, not on the number of samples."""

    def __init__(self, act: torch.Tensor, cuts: np.ndarray | None = None):
        n = act.shape[-1]
        self.act = act
        link = torch.ones(n - 1, dtype=torch.bool, device=act.device)  # link[j]: edges j and j+1 coupled
        bounds = np.unique(np.clip(np.asarray([] if cuts is None else cuts, dtype=np.int64), 1, n - 1))
        link[torch.as_tensor(bounds - 1, dtype=torch.long, device=act.device)] = False
        starts = np.concatenate([[0], bounds])
        lengths = np.diff(np.concatenate([starts, [n]]))
        seg_eps = (2.0 - 2.0 * np.cos(np.pi / np.maximum(lengths, 2))) / 2
        self.eps = torch.as_tensor(np.repeat(seg_eps, lengths), dtype=torch.float64, device=act.device)
        self.link = link.to(torch.float64)

    def __call__(self, r: torch.Tensor) -> torch.Tensor:
        r = torch.where(self.act, r, torch.zeros_like(r))
        lk = self.link.to(r.dtype)
        d = (r[..., 1:] - r[..., :-1]) * lk  # differences across the coupled pairs
        z = self.eps.to(r.dtype) * r
        z[..., :-1] -= d
        z[..., 1:] += d
        return torch.where(self.act, z, torch.zeros_like(z))


@dataclass
class PathModel:
    """The sampled integrator model of the warm start's Hessian, per axis ``H ~ S (L^T W L + R) S``.

    ``L`` integrates the raster edges to k (a lower-triangular sum restarted at every excitation, ``cuts``), ``W``
    the objective's weight on k at each raster edge (the ADC samples and the moments before the RF pulses that
    fall there: zero where nothing is sampled), ``R`` the objective's own diagonal in the edges (the RF-period
    term, the Tikhonov term) and ``S = diag(sign)``, ``sign = (-1)^(refocusing pulses before the edge)``: k is
    negated at a refocusing pulse's centre (:func:`dtoc.seq.kspace.kspace_at`), so the path's link across one has
    weight -1.  The GIRF and eddy terms are not in it (the CG's iteration count follows their frequency response).

    Attributes:
        cuts: edge indices where k restarts (excitations).
        sign: (N+1,) +-1.
        w: (3, N+1) weight of the k at each edge, in objective units per (mT/m)^2 of the edges' sum.
        r: (3, N+1) diagonal of the Hessian in the edges, same units.
    """

    cuts: np.ndarray
    sign: np.ndarray
    w: np.ndarray
    r: np.ndarray


class _PathPrecond:
    """``M = (S (L^T W L + R) S)^-1`` of a :class:`PathModel` restricted to the variables ``act`` (the held edges
    leave the path: a sample at a held edge weighs on the last free edge before it), applied exactly in O(N): with
    ``z = S D y`` (``D = L^-1``, the first difference within a period) ``H z = r`` is the tridiagonal system
    ``(W + D^T R D) y = D^T S r``, factorised once per axis (LAPACK ``pttrf``).  Where nothing is sampled
    (``W = 0``: spoilers, prewinders before a moment) the edges' links are stiff and they move together, as only
    their sum reaches k; a moment row is one more sampled point."""

    def __init__(self, act: torch.Tensor, model: PathModel):
        from scipy.linalg import lapack

        self.act = act
        a = act.detach().cpu().numpy()
        n = a.shape[-1]
        bounds = np.unique(np.clip(np.asarray(model.cuts, dtype=np.int64), 1, n - 1))
        period = np.searchsorted(bounds, np.arange(n), side="right")
        w, r = np.asarray(model.w, dtype=np.float64), np.asarray(model.r, dtype=np.float64)
        ws = w[w > 0]
        w = np.maximum(w, W_FLOOR * float(ws.mean()) if ws.size else 0.0)
        floor = 1e-12 * max(float(w.max(initial=0.0)), float(r.max(initial=0.0)), 1e-300)
        self.axes: list[tuple | None] = []
        for ax in range(a.shape[0]):
            idx = np.flatnonzero(a[ax])
            if not idx.size:
                self.axes.append(None)
                continue
            last = np.maximum.accumulate(np.where(a[ax], np.arange(n), -1))  # the last free edge at or before
            ok = (last >= 0) & (period[np.maximum(last, 0)] == period)
            rank = np.cumsum(a[ax]) - 1
            wa = np.bincount(rank[last[ok]], weights=w[ax][ok], minlength=idx.size)
            ra = np.maximum(r[ax][idx], floor)
            link = (period[idx[1:]] == period[idx[:-1]]).astype(np.float64)
            diag = wa + ra
            diag[:-1] += ra[1:] * link
            d, e, info = lapack.dpttrf(diag, -ra[1:] * link)
            if info != 0:
                raise ValueError("the path model is not positive definite")
            self.axes.append((idx, np.asarray(model.sign)[idx], link, d, e))
        self._pttrs = lapack.dpttrs

    def __call__(self, r: torch.Tensor) -> torch.Tensor:
        rn = r.detach().cpu().numpy()
        out = np.zeros(rn.shape, dtype=np.float64)
        for ax, fac in enumerate(self.axes):
            if fac is None:
                continue
            idx, sg, link, d, e = fac
            t = rn[ax, idx] * sg
            b = t.copy()
            b[:-1] -= t[1:] * link  # D^T
            y, _ = self._pttrs(d, e, b)
            z = y.copy()
            z[1:] -= y[:-1] * link  # D
            out[ax, idx] = z * sg
        return torch.as_tensor(out, dtype=r.dtype, device=r.device)


def _pcg(op, b, M, d0, tol, max_iter, on_iter=None) -> tuple[torch.Tensor, int]:
    """Preconditioned CG for ``op(d) = b`` from ``d0``; stops when the residual's M-norm has dropped by ``tol``
    (relative to the start's residual: a warm start is refined, not re-solved)."""
    d = d0.clone()
    r = b - op(d) if bool(d0.any()) else b.clone()
    z = M(r)
    p = z.clone()
    rz = float((r * z).sum())
    bz = rz
    it = 0
    for it in range(1, max_iter + 1):
        if rz <= tol * tol * max(bz, 1e-300):
            return d, it - 1
        Hp = op(p)
        pHp = float((p * Hp).sum())
        if pHp <= 0:
            break
        a = rz / pHp
        d = d + a * p
        r = r - a * Hp
        z = M(r)
        rz_new = float((r * z).sum())
        p = z + (rz_new / rz) * p
        rz = rz_new
        if on_iter is not None:
            on_iter(d)
    return d, it


def solve_to_tolerance(
    f: Callable[[torch.Tensor], tuple[torch.Tensor, dict]],
    x0: torch.Tensor,
    P,
    free: torch.Tensor,
    k_error: Callable[[torch.Tensor], np.ndarray],
    *,
    k_tol_dk: float = 0.01,
    budget: int = 1500,
    cg_tol: float = 1e-6,
    cg_max: int = 150,
    cg_round_max: int = 40,
    max_rounds: int = 8,
    stall_rel: float = 0.02,
    held_max: float = 0.2,
    sample_times_s: np.ndarray | None = None,
    cuts: np.ndarray | None = None,
    progress: Callable[[str, int, int, float], None] | None = None,
    check_every: int = 10,
    stop_error: Callable[[torch.Tensor], np.ndarray] | None = None,
    model: PathModel | None = None,
    n_adc: int | None = None,
) -> tuple[torch.Tensor, SolveReport]:
    """Minimise the quadratic ``f`` within the limits of ``P`` to a k-space tolerance (module doc).

    Args:
        f: ``x -> (loss, terms)``, a convex quadratic of ``x`` (3, N+1) (exact for an affine chain).
        x0: (3, N+1) start (the base edges or a previous solution).  P: the run's
            :class:`~dtoc.optimize.limits.EdgeProjector`.  free: (3, N+1) bool tensor.
        k_error: ``x -> errors`` in dk: per ADC sample, then (with ``n_adc``) per moment before an RF pulse the
            objective holds; every stop and report uses all of them (a 'tolerance' stop leaves none above it).
        k_tol_dk: stop when every sample reachable at all is within it.
        budget: most objective evaluations (forward + backward passes).
        cg_tol / cg_max / cg_round_max: the CG stops when its preconditioned residual has dropped by ``cg_tol``
            or after ``cg_max`` iterations (the first solve) or ``cg_round_max`` (each later round, warm).
        max_rounds / stall_rel: most active-set rounds; stop when a round lowered the objective by less than
            ``stall_rel`` (relative).
        held_max: when the first projection moves more than this fraction of the free edges, stop with
            'limits-bound' (the caller then runs the projected-gradient path).
        sample_times_s: the errors' times (samples, moments), to name the active limit before an unreachable one.
        cuts: raster-edge indices where k restarts (excitations): the preconditioner's periods (without ``model``).
        model: the :class:`PathModel` of the objective (sampled points, moments, refocusing signs): the
            preconditioner is its exact inverse (:class:`_PathPrecond`); None: the unit path Laplacian (:class:`_Precond`).
        n_adc: how many of ``k_error``'s entries are ADC samples (None: all); the rest are moments, reported apart.
        check_every: every this many iterations of the first (unconstrained) CG its iterate is projected onto the
            limits and its k error evaluated (one forward pass, not counted in ``budget``): when every sample is
            within ``k_tol_dk`` the CG stops there (stop reason ``tolerance``; ``unconstrained_max_dk`` is then
            that iterate's, not a converged optimum's).  0: never.
        stop_error: ``x -> errors (dk)`` of that check (default ``k_error``): e.g. the ADC samples and the moments
            before the RF pulses (an echo pathway's k), so that a stop leaves neither above the tolerance.
    Returns:
        (x within the limits (exactly projected), :class:`SolveReport`).
    """
    rep = SolveReport(k_tol_dk=k_tol_dk)
    q = _Quadratic(f, x0.detach().clone(), free, max(budget, 8))
    x = P.project(q.x0, n_iter=60)
    best: dict = {"x": x, "f": float(f(x)[0].detach()), "err": k_error(x)}
    err_unc = None
    unc_converged = False
    fixed = torch.zeros_like(free)
    try:
        x = q.x0
        for rnd in range(max_rounds):
            act = free & ~fixed
            M = _Precond(act, cuts) if model is None else _PathPrecond(act, model)

            def op(u, act=act):
                return torch.where(act, q.hv(torch.where(act, u, 0.0)), 0.0)

            g = q.grad(x)[0] if rnd else q.g0
            n_max = cg_max if rnd == 0 else cg_round_max
            reached = False
            try:
                d, k = _pcg(
                    op, torch.where(act, -g, 0.0), M, torch.zeros_like(x), cg_tol, n_max,
                    on_iter=_tolerance_check(x, P, stop_error or k_error, k_tol_dk, check_every),
                )  # fmt: skip
            except _Reached as hit:  # every sample within the tolerance: no need to converge further
                d, k, reached = hit.d, hit.it, True
            rep.cg_iterations += k
            x_unc = x + d
            if rnd == 0:
                unc_converged = k < n_max and not reached
                err_unc = k_error(x_unc)
                rep.unconstrained_max_dk = float(err_unc[:n_adc].max()) if err_unc[:n_adc].size else 0.0
                rep.within_limits_unconstrained = bool(P.is_feasible(x_unc.detach().cpu().numpy()))
            x = P.project(x_unc, n_iter=60)
            err = k_error(x)
            val = float(f(x)[0].detach())
            gain = best["f"] - val
            assert err_unc is not None
            reach = counted(err_unc, unc_converged, k_tol_dk)
            within = bool(np.all(err[reach] <= k_tol_dk))
            if val < best["f"] or within:  # an iterate that meets the stopping rule ends the solve, whatever its f
                best.update(x=x, f=val, err=err)
            moved = free & ((x - x_unc).abs() > 1e-9)
            new = moved & ~fixed
            fixed = fixed | moved
            rep.rounds = rnd + 1
            rep.history.append(
                {"round": rnd + 1, "evals": q.n, "f": val, "max_dk": float(err.max()), "held": int(fixed.sum())}
            )
            if progress is not None:
                progress("warm", q.n, budget, val)
            if bool(np.all(best["err"][reach] <= k_tol_dk)):  # (a round within it is the best now)
                rep.stop_reason = "tolerance"
                break
            if rnd == 0 and float(fixed.sum()) > held_max * float(free.sum()):
                rep.stop_reason = "limits-bound"  # the limits bind over much of the waveform: not for rounds
                break
            if not bool(new.any()) and k < n_max:
                rep.stop_reason = "converged"  # no new limit became active and CG converged: no further change
                break
            if rnd > 0 and gain < stall_rel * abs(best["f"]):
                rep.stop_reason = "converged"  # the rounds stopped paying: the held edges' optimum
                break
        else:
            rep.stop_reason = "rounds"
    except _Stop:
        rep.stop_reason = "budget"
    except KeyboardInterrupt:
        rep.stop_reason = "interrupted"
    rep.evaluations = q.n
    err = best["err"]
    rep.set_errors(err, n_adc)
    rep.unconstrained_errors, rep.unconstrained_converged = err_unc, unc_converged
    if err_unc is not None:
        rep.unreachable = explain_unreachable(
            best["x"], err, err_unc, k_tol_dk, P, sample_times_s, unc_converged, n_adc
        )
    return best["x"], rep


def counted(err_unc: np.ndarray, unc_converged: bool, k_tol_dk: float) -> np.ndarray:
    """(n,) bool: the samples a 'tolerance' stop asks to be within ``k_tol_dk``.  With a converged unconstrained
    solve, those it brings within the tolerance (the others are out of reach without the limits, named 'fixed' or
    'moments'); with an unconverged one, every sample (nothing is known out of reach)."""
    if unc_converged:
        return err_unc <= k_tol_dk
    return np.ones(np.shape(err_unc), dtype=bool)


def _tolerance_check(x, P, k_error, k_tol_dk: float, every: int):
    """``on_iter`` of the first CG: raises :class:`_Reached` when the projected iterate ``x + d`` has every sample
    within ``k_tol_dk``, or when the iterate itself (not projected) has every sample within half of it: the
    unconstrained problem is solved as far as the tolerance asks, what is left is the limits' (the active-set
    rounds'), e.g. a spoiler whose pre-compensation the slew limit clips.  Checked every ``every`` iterations."""
    n = [0]

    def check(d):
        n[0] += 1
        if every > 0 and n[0] % every == 0:
            err = k_error(P.project(x + d, n_iter=60))
            if not err.size or bool(np.all(err <= k_tol_dk)) or bool(np.all(k_error(x + d) <= 0.5 * k_tol_dk)):
                raise _Reached(d, n[0])

    return check


#: a sample above the tolerance is 'fixed' (not reachable even without the limits) only when its error at the
#: unconstrained optimum is above the tolerance too AND makes up at least this share of its error at the stop; else
#: the limits cost most of it and it is named 'limits' with "without limits X dk" (a rule of ours, docs/optimize.md)
FIXED_SHARE = 0.5


def active_limits_nearest(P, x: np.ndarray, times_s: np.ndarray) -> tuple[list[str], np.ndarray]:
    """Per time, the amplitude or slew limit (per axis) at its bound nearest before it in the edges ``x`` (or, if
    none is before it, nearest after it: an acausal GIRF lets a later limit act), and that limit's time ('', nan if
    no limit is at its bound anywhere).  One (N+1,) index array at a time, no list of events (a long sequence at
    its slew limit on every ramp has millions).  Ties: the first of amplitude x, y, z, slew x, y, z."""
    amp, slew_seg = P.at_limits(np.asarray(x, dtype=np.float64))
    times_s = np.asarray(times_s, dtype=np.float64)
    n = P.free.shape[1]
    pos = np.clip(np.floor(times_s / P.raster_s + 1e-9).astype(np.int64), 0, n - 1)
    before = np.full(times_s.size, -np.inf)
    after = np.full(times_s.size, np.inf)
    nb, na = [""] * times_s.size, [""] * times_s.size
    for kind, m in (("amplitude", amp), ("slew", slew_seg)):
        for a in range(3):
            if not m[a].any():
                continue
            ar = np.arange(m.shape[1])
            p = np.minimum(pos, m.shape[1] - 1)
            last = np.maximum.accumulate(np.where(m[a], ar, -1))[p]
            nxt = np.minimum.accumulate(np.where(m[a], ar, m.shape[1])[::-1])[::-1][p]
            tb = np.where(last >= 0, last * P.raster_s, -np.inf)
            ta = np.where(nxt < m.shape[1], nxt * P.raster_s, np.inf)
            for j in np.flatnonzero(tb > before):
                nb[j] = f"{kind} {AXES[a]}"
            for j in np.flatnonzero(ta < after):
                na[j] = f"{kind} {AXES[a]}"
            before, after = np.maximum(before, tb), np.minimum(after, ta)
    name = [b or a for b, a in zip(nb, na)]
    t = np.where(np.isfinite(before), before, np.where(np.isfinite(after), after, np.nan))
    return name, t


def explain_unreachable(
    x, err, err_unc, k_tol_dk, P, sample_times_s, unc_converged: bool = True, n_adc: int | None = None
) -> Unreachable:
    """Name the samples above tolerance (one rule for the whole and the windowed solve): 'fixed' when the
    unconstrained optimum misses them too, by at least :data:`FIXED_SHARE` of their error (``err_unc`` nan: no
    free edge reaches them); 'unresolved' instead when the unconstrained solve did not reach its optimum within
    its budget (``unc_converged`` False: no claim); else 'limits' with the active limit (amplitude or slew at its
    bound, per axis) nearest before the sample (:func:`active_limits_nearest`), or 'unresolved' when no limit is at
    its bound anywhere (the solve stopped short of the constrained optimum: no claim)."""
    err, err_unc = np.asarray(err, dtype=np.float64), np.asarray(err_unc, dtype=np.float64)
    idx = np.flatnonzero(err > k_tol_dk)
    e, u = err[idx], np.where(np.isnan(err_unc[idx]), err[idx], err_unc[idx])
    miss = "fixed" if unc_converged else "unresolved"
    reason = [miss if (uu > k_tol_dk and uu >= FIXED_SHARE * ee) else "limits" for ee, uu in zip(e, u)]
    limit = [""] * idx.size
    lt = np.full(idx.size, np.nan)
    lim_i = [j for j, r in enumerate(reason) if r == "limits"]
    if lim_i and sample_times_s is not None:
        xe = x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)
        names, times = active_limits_nearest(P, xe, np.asarray(sample_times_s, dtype=np.float64)[idx[lim_i]])
        for j, nm, tt in zip(lim_i, names, times):
            if nm:
                limit[j], lt[j] = nm, tt
            else:
                reason[j] = "unresolved"
    return Unreachable(idx, e, reason, limit, lt, u, n_adc)
