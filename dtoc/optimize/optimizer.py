"""Digital-twin optimization of the demanded gradient (paper Methods 3.1-3.2) with hard limits.

Stages (all on the raster-edge samples of the free segments, projected onto the hard-limit set after
every step, see :mod:`dtoc.optimize.limits`):

1. **Linear warm start** (``warm_start``): the k-space, RF-period and a tiny Tikhonov term are
   quadratic in the demanded gradient when the hardware model is linear (exponential eddy currents,
   GIRF).  Conjugate gradients on the normal equations (Hessian-vector products as differences of
   autograd gradients, exact for a quadratic) give the unconstrained least-squares
   pre-compensation; projected accelerated gradient (FISTA with adaptive restart, step 1/L from a
   power iteration) then solves the constrained problem.  No Bloch simulation is needed.
2. **Full loss** (``full_loss``): image + k-space + RF (+ soft amplitude/slew) terms through the
   PDG simulator, projected Adam (or the paper's Adam with restarts, ``adam-paper``), optionally
   cycling through rotated phantoms (data augmentation).  The best iterate is kept.
3. **Post-hoc discarding** (``choose_discard``): samples whose k-space error exceeds a threshold are
   left out of the reconstruction; the threshold minimises the image NRMSE (paper Section 3.1).

Everything is seeded and deterministic for fixed ``threads``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import numpy as np
import torch

from dtoc.optimize import loss as L
from dtoc.optimize.config import PAPER_RESTARTS, OptimizeConfig
from dtoc.optimize.solver import free_gradient
from dtoc.sim import metrics
from dtoc.util.replay import Replay

ProgressFn = Callable[[str, int, int, float], None]


class _Stop(Exception):
    """Internal: stop the current stage (Ctrl-C)."""


def set_deterministic(seed: int, threads: int, device: str = "cpu") -> None:
    """Seed torch/numpy, fix the thread count and, on an accelerator, ask torch for deterministic kernels.

    On the CPU the kernels this package uses are deterministic for a fixed thread count (the goldens and
    the byte-identity tests hold without the switch); ``torch.use_deterministic_algorithms`` would import
    torch's compiler stack (~1.3 s CPU per process, docs/benchmarks.md "CLI start-up"), so it is only
    switched on for a non-CPU device, where scatter/index kernels use atomics.
    """
    torch.manual_seed(seed)
    np.random.seed(seed % (2**32))
    torch.set_num_threads(threads)
    if torch.device(device).type != "cpu":
        _deterministic_kernels()


def _deterministic_kernels() -> None:
    """The eager kernels' deterministic switch, without ``torch.use_deterministic_algorithms``'s import of the
    compiler's configuration (dtoc compiles nothing): that import took 3-6 s of the first run of a process on a
    GPU host (docs/optimize.md, "Execution on a GPU").  Uninitialised memory is not filled with NaN (a debugging
    aid of the switch: one extra kernel per allocation; dtoc reads no memory it has not written).  Falls back on
    the public call where torch lacks the switches."""
    set_det = getattr(torch._C, "_set_deterministic_algorithms", None)
    set_fill = getattr(torch._C, "_set_deterministic_fill_uninitialized_memory", None)
    if set_det is None or set_fill is None:
        torch.use_deterministic_algorithms(True, warn_only=True)
        return
    set_det(True, warn_only=True)
    set_fill(False)


@dataclass
class StageState:
    """Best-so-far tracking of one run (survives Ctrl-C)."""

    best_edges: torch.Tensor
    best_loss: float = math.inf
    history: list = field(default_factory=list)
    interrupted: bool = False


# ---------------------------------------------------------------------------------------------------
# linear warm start
# ---------------------------------------------------------------------------------------------------
def linear_objective(twin, ctx, weights):
    def f(x: torch.Tensor) -> tuple[torch.Tensor, Mapping[str, float]]:
        r = twin.forward_edges(x)
        w = weights.model_copy(update={"image": 0.0, "amplitude": 0.0, "slew": 0.0})
        return L.total_loss(
            w,
            ctx,
            g=r.demanded_grad_mT_per_m,
            G=r.realized_grad_mT_per_m,
            k=r.kspace_rad_per_m,
            include_reg=True,
            k_moment=r.moments_rad_per_m,
        )

    return f


class _Steps:
    """The two steps of :func:`constrained_least_squares` as :class:`~dtoc.util.replay.Replay` s (one CUDA graph
    each on a GPU; eager, the same code, on the CPU): an evaluation ``x -> (gradient on the free entries, f, terms)``
    and a projected FISTA iteration with its adaptive restart, decided on the device (nothing waits for it)."""

    def __init__(self, f, free: torch.Tensor, P):
        self.f, self.free, self.P = f, free, P
        self.keys: list[str] = []
        self.step = 0.0
        self._eval = Replay(self._value_grad)
        self._fista = Replay(self._fista_step)

    def _value_grad(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        g, val, terms = free_gradient(self.f, self.free, x)
        self.keys = list(terms)
        if isinstance(terms, L.TermValues):
            stacked = terms.stacked()
        else:  # a plain mapping of floats (an objective of the caller's): read here, eagerly
            stacked = torch.as_tensor([float(v) for v in terms.values()], dtype=torch.float64)
        return g, val, stacked

    def _fista_step(self, y: torch.Tensor, x_prev: torch.Tensor, t: torch.Tensor) -> tuple[torch.Tensor, ...]:
        gy, fy, terms = self._value_grad(y)
        x_new = self.P.project(y - self.step * gy, n_iter=8, exact=False)
        # adaptive restart (O'Donoghue & Candes): momentum off when it points uphill
        t = torch.where(((y - x_new) * (x_new - x_prev)).sum() > 0, torch.ones_like(t), t)
        t_new = 0.5 * (1 + torch.sqrt(1 + 4 * t * t))
        y_new = x_new + ((t - 1) / t_new) * (x_new - x_prev)
        return x_new, y_new, t_new, fy, terms

    def grad(self, x: torch.Tensor) -> tuple[torch.Tensor, float, L.TermValues]:
        g, val, terms = self._eval(x)
        return g, float(val), L.TermValues.from_stacked(self.keys, terms)

    def fista(self, y: torch.Tensor, x_prev: torch.Tensor, t: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """(x_new, y_new, t_new, f(y) 0-dim, terms of y stacked): one iteration."""
        return self._fista(y, x_prev, t)


def warm_start(
    twin,
    ctx,
    weights,
    iters: int,
    state: StageState | None = None,
    progress: ProgressFn | None = None,
    cg_fraction: float = 0.5,
    cg_tol: float = 1e-12,
    rel_tol: float = 1e-7,
    x_init: torch.Tensor | None = None,
) -> torch.Tensor:
    """Constrained least-squares pre-compensation of k-space (and RF-period gradient).

    Args:
        twin: :class:`~dtoc.optimize.twin.Twin`.
        ctx: :class:`~dtoc.optimize.loss.LossContext`.
        weights: loss weights (image/amplitude/slew ignored here).
        iters: total gradient evaluations (split between CG and projected FISTA).
    Returns:
        (3, N+1) projected edge samples, mT/m.
    """
    x0 = twin.base_edges() if x_init is None else x_init.detach().clone()
    f = linear_objective(twin, ctx, weights)
    return constrained_least_squares(
        f,
        x0,
        twin.projector,
        twin.free_t,
        iters,
        state,
        progress,
        cg_fraction if x_init is None else 0.0,
        cg_tol,
        rel_tol,
    )


def constrained_least_squares(
    f: Callable[[torch.Tensor], tuple[torch.Tensor, dict]],
    x0: torch.Tensor,
    P,
    free: torch.Tensor,
    iters: int,
    state: StageState | None = None,
    progress: ProgressFn | None = None,
    cg_fraction: float = 0.5,
    cg_tol: float = 1e-12,
    rel_tol: float = 1e-7,
    k_stop: Callable[[torch.Tensor], bool] | None = None,
    report=None,
    f_target: float | None = None,
) -> torch.Tensor:
    """The warm start's algorithm on any quadratic objective ``f`` of edge samples within the limits of ``P``.

    CG on the unconstrained problem from ``x0`` (``iters * cg_fraction`` evaluations; its early stop
    regularises), exact projection, then projected FISTA with adaptive restart (step from a power iteration
    on the Hessian) for the remaining evaluations.

    Args:
        f: ``x -> (loss tensor, {term: float})``, quadratic in ``x`` (Hessian-vector products are gradient
            differences), differentiable.
        x0: (3, N+1) start (the base edges).  P: an :class:`~dtoc.optimize.limits.EdgeProjector`.
        free: (3, N+1) bool tensor of the variables.
        k_stop: ``x -> bool``, checked on the projected iterate every 20 FISTA iterations: stop when True
            (the solver's k-space tolerance); ``report``: a :class:`~dtoc.optimize.solver.SolveReport` to fill.
        f_target: the objective of a solution already at hand (the active-set rounds'): FISTA stops (reason
            ``no-gain``) at a check where, at its descent over the last 20 iterations, the rest of the budget would
            not bring it down to ``f_target`` (a result above it is not kept).
    Returns:
        (3, N+1) projected edge samples, mT/m.
    """
    hist = state.history if state is not None else []
    if iters <= 0:
        return P.project(x0)
    n_cg = int(iters * cg_fraction)
    steps = _Steps(f, free, P)
    g0, f0, terms0 = steps.grad(x0)
    hist.append({"stage": "warm", "it": 0, "loss": f0, **terms0})

    def hv(v):  # exact Hessian-vector product for a quadratic objective
        gv, _, _ = steps.grad(x0 + v)
        return gv - g0

    # --- CG on H d = -g0 (unconstrained least squares) ---
    d = torch.zeros_like(x0)
    r = -g0.clone()
    p = r.clone()
    rr = float((r * r).sum())
    rr0 = rr
    it = 0
    try:
        for it in range(1, n_cg + 1):
            if rr <= cg_tol * max(rr0, 1e-300):
                break
            Hp = hv(p)
            pHp = float((p * Hp).sum())
            if pHp <= 0:
                break
            a = rr / pHp
            d = d + a * p
            r = r - a * Hp
            rr_new = float((r * r).sum())
            p = r + (rr_new / rr) * p
            rr = rr_new
            if progress:
                progress("warm", it, iters, rr)
    except KeyboardInterrupt:
        if state is not None:
            state.interrupted = True
    x = P.project(x0 + d, n_iter=60)
    f0 = f0 if n_cg == 0 else min(f0, float(f(x)[0].detach()))
    # --- projected FISTA on the constrained problem ---
    n_fista = iters - it
    j = 0
    if n_fista > 0 and not (state is not None and state.interrupted):
        # Lipschitz constant by power iteration on H (on free entries)
        v = torch.where(free, torch.ones_like(x0), torch.zeros_like(x0))
        v = v / v.norm().clamp_min(1e-30)
        lam = 1.0
        for _ in range(8):
            w = hv(v)
            lam = float(w.norm())
            if lam <= 0:
                break
            v = w / lam
        steps.step = 1.0 / (1.2 * max(lam, 1e-30))
        y = x.clone()
        x_prev = x.clone()
        t = torch.ones((), dtype=torch.float64, device=x.device)
        f_prev = math.inf
        try:
            for j in range(1, n_fista + 1):
                x_prev, y, t, fy_t, terms_t = steps.fista(y, x_prev, t)
                # the objective is read back only where it is used: every 10th iteration (history), at the
                # checks (every 20th) and for the progress line (nothing else waits for the device)
                read = j % 10 == 0 or j == n_fista or (j > 20 and j % 20 == 1)
                fy = float(fy_t) if read else math.nan
                if j > 20 and j % 20 == 1:
                    if f_prev - fy <= max(rel_tol * abs(fy), 1e-6 * f0) or fy <= 1e-14:
                        if report is not None:
                            report.stop_reason = "converged"
                        break
                    if f_target is not None and fy > f_target and (f_prev - fy) * (n_fista - j) / 20 < fy - f_target:
                        if report is not None:
                            report.stop_reason = "no-gain"
                        break
                    f_prev = fy
                    if k_stop is not None and k_stop(P.project(x_prev, n_iter=60)):
                        report.stop_reason = "tolerance"
                        break
                if progress and read:
                    progress("warm", it + j, iters, fy)
                if j % 10 == 0 or j == n_fista:
                    terms = L.TermValues.from_stacked(steps.keys, terms_t)
                    hist.append({"stage": "warm", "it": it + j, "loss": fy, **terms})
            x = x_prev
        except KeyboardInterrupt:
            if state is not None:
                state.interrupted = True
            x = x_prev
    x = P.project(x, n_iter=60)
    fx = float(f(x)[0].detach())
    hist.append({"stage": "warm", "it": iters, "loss": fx})
    if report is not None:
        report.stop_reason = report.stop_reason or "budget"
        report.evaluations = iters if report.stop_reason == "budget" else it + j
        report.cg_iterations = it
        report.rounds = 0
    return x


#: the sampled, signed path model as the solver's preconditioner for sequences with refocusing pulses: off (faster
#: unconstrained CG on a synthetic spin echo, but a worse constrained result on a ramp-sampled SE-EPI with the KCL
#: GIRF, 0.0592 vs 0.0402 dk: docs/optimize.md, "Solver")
PATH_MODEL_PRECONDITIONER = False


def path_model(twin, ctx, weights, moments: bool):
    """The :class:`~dtoc.optimize.solver.PathModel` of :func:`linear_objective` on ``twin``'s raster edges: the
    weight of k at each edge from the ADC samples (``ctx.sample_weight`` included) and, with ``moments``, the
    moments before the RF pulses there; the RF-period and Tikhonov terms' diagonal; the excitations' cuts and the
    sign flips at the refocusing pulses.  Units: objective per (mT/m)^2 (the Hessian's, without the GIRF)."""
    from dtoc.constants import GAMMA_RAD_PER_S_PER_MT
    from dtoc.optimize import solver as SV

    ir = twin.ir
    n = twin.free_t.shape[-1]
    ras = ir.raster_s
    dk = ctx.dk_rad_per_m.detach().cpu().numpy()
    inv2 = np.where(np.isfinite(dk), 1.0 / np.where(np.isfinite(dk), dk, 1.0), 0.0) ** 2  # (3,) 1/dk^2
    ck2 = (GAMMA_RAD_PER_S_PER_MT * ras) ** 2  # (rad/m per mT/m of one edge)^2

    def at(t_s):
        return np.clip(np.floor(np.asarray(t_s, dtype=np.float64) / ras + 1e-9).astype(np.int64), 0, n - 1)

    w = np.zeros(n)
    t_adc = adc_sample_times_s(ir)
    sw = np.ones(t_adc.size) if ctx.sample_weight is None else ctx.sample_weight.detach().cpu().numpy()
    np.add.at(w, at(t_adc), 2.0 * weights.kspace * sw / max(float(sw.sum()), 1e-12))
    if moments and ctx.t_moment_s is not None and weights.moment > 0:
        np.add.at(w, at(ctx.t_moment_s), 2.0 * weights.moment / ctx.t_moment_s.size)
    W = ck2 * inv2[:, None] * w[None, :]
    # the RF-period term on G and the Tikhonov term on g, per fine sample; an edge is 1 fine sample and half of
    # each neighbouring midpoint (edges_to_fine)
    M = ctx.g0_fine_mT_per_m.shape[-1]
    rf = ctx.rf_mask.detach().cpu().numpy().astype(np.float64)
    per_fine = 2.0 * weights.reg / (M * ctx.g_ref_mT_per_m**2) + rf * (
        2.0 * weights.rf / (max(float(rf.sum()), 1.0) * ctx.g_ref_mT_per_m**2)
    )
    r = per_fine[::2].copy()
    r[1:] += 0.25 * per_fine[1::2]
    r[:-1] += 0.25 * per_fine[1::2]
    cuts = np.array([round(p.t_center_s / ras) for p in ir.rf if p.excites], dtype=np.int64)
    flips = np.sort(np.array([p.t_center_s for p in ir.rf if p.refocuses], dtype=np.float64))
    sign = 1.0 - 2.0 * (np.searchsorted(flips, np.arange(n) * ras, side="left") % 2)
    return SV.PathModel(cuts=cuts, sign=sign, w=W, r=np.broadcast_to(r, (3, n)).copy())


def solve_warm_start(
    twin,
    ctx,
    weights,
    k_tol_dk: float,
    budget: int,
    state: StageState | None = None,
    progress: ProgressFn | None = None,
    x_init: torch.Tensor | None = None,
    minimax_rounds: int = 0,
    minimax_budget: int = 0,
):
    """The warm start's problem solved to a k-space tolerance (:mod:`dtoc.optimize.solver`); returns (x, report).

    An affine chain: preconditioned CG and active-set rounds (:func:`~dtoc.optimize.solver.solve_to_tolerance`).
    If they stop above the tolerance with the least-squares optimum ('converged' or 'rounds'), up to
    ``minimax_rounds`` rounds reweight the samples towards the smallest worst error (:func:`minimax_rounds`,
    within ``minimax_budget`` further evaluations; 0 rounds: the least-squares optimum, and the CG + FISTA
    fallback below, as before).  Otherwise (the first projection moved much of the waveform: 'limits-bound') CG and
    projected FISTA from the base on what is left of ``budget``.
    A chain that is not affine (e.g. a slew-rate-limited amplifier): the iterative path
    (:func:`constrained_least_squares`) with the same stopping rule, checked every 20 iterations, within ``budget``
    evaluations.
    """
    from dtoc.hardware.memory import is_affine
    from dtoc.optimize import solver as SV

    x0 = twin.base_edges() if x_init is None else x_init.detach().clone()
    f = linear_objective(twin, ctx, weights)

    use_moments = weights.moment > 0 and ctx.k0_moment_rad_per_m is not None
    n_adc = int(ctx.k0_rad_per_m.shape[-1])
    times = adc_sample_times_s(twin.ir)
    if use_moments:
        times = np.concatenate([times, np.asarray(ctx.t_moment_s, dtype=np.float64)])

    def k_error(x):  # every ADC sample and every moment before an RF pulse the objective holds, in dk
        with torch.no_grad():
            r = twin.forward_edges(x, moments=use_moments)
            e = kspace_error_dk(r.kspace_rad_per_m, ctx)
            if use_moments and r.moments_rad_per_m is not None:
                dk = ctx.dk_rad_per_m
                inv = torch.where(torch.isfinite(dk), 1.0 / dk, torch.zeros_like(dk))
                m = ((r.moments_rad_per_m - ctx.k0_moment_rad_per_m) * inv[:, None]).norm(dim=0)
                e = np.concatenate([e, m.cpu().numpy()])
            return e

    if is_affine(twin.hardware):
        cuts = np.array([round(r.t_center_s / twin.ir.raster_s) for r in twin.ir.rf if r.excites], dtype=np.int64)
        model = (
            path_model(twin, ctx, weights, use_moments)
            if PATH_MODEL_PRECONDITIONER and any(r.refocuses for r in twin.ir.rf)
            else None
        )

        def solve(start: torch.Tensor, n: int):
            return SV.solve_to_tolerance(
                f, start, twin.projector, twin.free_t, k_error, k_tol_dk=k_tol_dk, budget=n,
                sample_times_s=times, progress=progress, n_adc=n_adc, cuts=cuts, model=model,
            )  # fmt: skip

        x, rep = solve(x0, budget)
        left = budget - rep.evaluations
        above = max(rep.achieved_max_dk, rep.moment_max_dk or 0.0) > k_tol_dk
        f_ls = float(f(x)[0].detach())  # the least-squares solve's objective: the fallback's target
        # (the rounds reweight the ADC samples: not when only moments before RF pulses are above the tolerance)
        minimax = minimax_rounds > 0 and rep.achieved_max_dk > k_tol_dk and rep.stop_reason in ("converged", "rounds")
        if minimax:
            x, rep = minimax_rounds_solve(
                solve, ctx, x, rep, k_error, twin.projector, times, n_adc, minimax_rounds, minimax_budget, budget,
                state,
            )  # fmt: skip
            above = max(rep.achieved_max_dk, rep.moment_max_dk or 0.0) > k_tol_dk
        if rep.stop_reason not in ("tolerance", "interrupted") and above and left >= 40:
            # above the tolerance (limits active over much of the waveform, or active-set rounds that stopped
            # paying -- a heuristic, not a certificate): CG then projected FISTA from the start (the fixed-count
            # algorithm) on what is left of the budget, with the same rule; kept if it lowers the objective (after
            # minimax rounds: if it lowers the worst error)
            sub = SV.SolveReport(method="cg-fista")
            x2 = constrained_least_squares(
                f, x0, twin.projector, twin.free_t, left, None, progress, 0.5,
                k_stop=lambda z: bool(k_error(z).max() <= k_tol_dk), report=sub, f_target=f_ls,
            )  # fmt: skip
            rep.fallback_stop = sub.stop_reason
            rep.evaluations += sub.evaluations
            rep.method = "pcg-active-set+cg-fista"
            e2 = k_error(x2) if minimax else None  # one forward pass, kept for the report below
            better = (
                float(e2.max()) < max(rep.achieved_max_dk, rep.moment_max_dk or 0.0)
                if e2 is not None
                else float(f(x2)[0].detach()) < float(f(x)[0].detach())
            )
            if better:
                x = x2
                err = k_error(x) if e2 is None else e2
                rep.set_errors(err, n_adc)
                rep.unreachable = SV.explain_unreachable(
                    x, err, rep.unconstrained_errors, k_tol_dk, twin.projector, times, rep.unconstrained_converged,
                    n_adc,
                )  # fmt: skip
                # its 'no-gain' stop came after a last 20-iteration descent too slow to matter: 'converged'
                rep.stop_reason = {"no-gain": "converged"}.get(sub.stop_reason, sub.stop_reason)
    else:
        rep = SV.SolveReport(method="cg-fista", k_tol_dk=k_tol_dk)
        x = constrained_least_squares(
            f, x0, twin.projector, twin.free_t, budget, state, progress, 0.5 if x_init is None else 0.0,
            k_stop=lambda x: bool(k_error(x).max() <= k_tol_dk), report=rep,
        )  # fmt: skip
        rep.set_errors(k_error(x), n_adc)
    if state is not None:
        if rep.stop_reason == "interrupted":
            state.interrupted = True
        state.history.append({"stage": "warm", "it": rep.evaluations, "loss": float(f(x)[0].detach())})
    return x, rep


#: the minimax rounds stop after this many rounds in a row that did not lower the worst error by LAWSON_GAIN
LAWSON_PATIENCE = 2
#: a round counts as a gain when it lowers the best worst error by at least this fraction of it
LAWSON_GAIN = 0.01
#: each round multiplies a sample's weight by its error (floored at the tolerance) to this power (Lawson: 1; 2 measured
#: faster on the EPI rows: docs/optimize.md, "Minimax rounds")
LAWSON_POWER = 2.0
#: the weights' largest ratio (a sample no waveform moves would otherwise take every weight)
LAWSON_SPREAD = 1e6


def minimax_rounds_solve(solve, ctx, x, rep, k_error, P, times, n_adc: int, rounds: int, budget: int,
                         round_budget: int, state=None):  # fmt: skip
    """Rounds of Lawson's reweighting (docs/optimize.md, "Minimax rounds"): the least-squares optimum within the
    limits is not the waveform with the smallest worst k error; each round multiplies every ADC sample's weight
    in the k term by its error (dk, floored at the tolerance: a sample within it keeps its share), normalises the
    weights to mean 1, and solves the reweighted problem again (``solve(start, n)``, warm from the best
    waveform so far, at most ``round_budget`` evaluations, all rounds within ``budget``).  For a linear objective
    without limits the iteration converges to the minimax (Chebyshev) solution; with the limits it is a heuristic
    that is not monotone, so the waveform with the smallest worst error (ADC samples and moments, every round's
    waveform exactly within the limits) is kept.

    Stops ('minimax stop'): ``tolerance`` (every sample reachable without the limits within it), ``stalled``
    (:data:`LAWSON_PATIENCE` rounds in a row lowered the worst error by less than :data:`LAWSON_GAIN` of it),
    ``rounds``, ``budget`` (fewer than 40 evaluations left), ``interrupted``.

    Args:
        solve: ``(start (3, N+1), evaluations) -> (x, SolveReport)``, the solver on the objective that reads
            ``ctx.sample_weight``. ctx: the loss context (its ``sample_weight`` restored on return).
        x, rep: the least-squares solve's waveform and report (its unconstrained errors say which samples are
            reachable at all). k_error: ``x -> errors`` (dk; ``n_adc`` ADC samples, then the moments).
        P: the limits' projector; times: the errors' times, s (to name the active limits).
    Returns:
        (the best waveform, ``rep`` updated in place: evaluations, errors, unreachable samples, ``minimax``).
    """
    from dtoc.optimize import solver as SV

    tol = rep.k_tol_dk
    err = k_error(x)
    reach = (
        np.ones(err.size, dtype=bool)
        if rep.unconstrained_errors is None
        else SV.counted(rep.unconstrained_errors, rep.unconstrained_converged, tol)
    )
    best_x, best_err = x, err
    first = float(err.max())
    base_w = ctx.sample_weight
    w = np.ones(n_adc) if base_w is None else base_w.detach().cpu().numpy().astype(np.float64)
    spent, done, idle, stop = 0, 0, 0, "rounds"
    worst: list[float] = []  # every round's worst error (kept or not)
    try:
        for _ in range(rounds):
            n = min(round_budget, budget - spent)
            if n < 40:
                stop = "budget"
                break
            w = w * np.maximum(err[:n_adc], tol) ** LAWSON_POWER
            w = np.maximum(w, w.max() / LAWSON_SPREAD)
            w = w / w.mean()
            ctx.sample_weight = torch.as_tensor(w, dtype=x.dtype, device=x.device)
            x2, r2 = solve(best_x, n)
            spent += r2.evaluations
            done += 1
            if r2.stop_reason == "interrupted":
                stop = "interrupted"
                break
            err = k_error(x2)
            worst.append(float(err.max()))
            prev = float(best_err.max())
            if float(err.max()) < prev:
                best_x, best_err = x2, err
            idle = 0 if prev - float(err.max()) >= LAWSON_GAIN * prev else idle + 1
            if bool(np.all(best_err[reach] <= tol)):
                stop = "tolerance"
                break
            if idle >= LAWSON_PATIENCE:
                stop = "stalled"
                break
    finally:
        ctx.sample_weight = base_w
    rep.evaluations += spent
    rep.set_errors(best_err, n_adc)
    if stop == "tolerance":
        rep.stop_reason = "tolerance"
    elif stop == "interrupted":
        rep.stop_reason = "interrupted"
        if state is not None:
            state.interrupted = True
    if rep.unconstrained_errors is not None:
        rep.unreachable = SV.explain_unreachable(
            best_x, best_err, rep.unconstrained_errors, tol, P, times, rep.unconstrained_converged, n_adc
        )
    rep.minimax = {
        "rounds": done,
        "evaluations": spent,
        "stop_reason": stop,
        "max_before_dk": first,
        "max_after_dk": float(best_err.max()),
        "round_max_dk": worst,
    }
    return best_x, rep


def adc_sample_times_s(ir) -> np.ndarray:
    """(N_adc,) times of every ADC sample, s, in the order of the sequence's samples."""
    if not ir.adc:
        return np.zeros(0)
    return np.concatenate([a.sample_times_s for a in ir.adc])


def robust_warm_start(
    twin,
    ctx,
    weights,
    iters: int | None,
    rounds: int = 2,
    scale_dk: float = 0.5,
    state: StageState | None = None,
    progress: ProgressFn | None = None,
    k_tol_dk: float = 0.01,
    budget: int = 600,
    reports: list | None = None,
    minimax_rounds: int = 0,
    minimax_budget: int = 0,
) -> torch.Tensor:
    """Warm start, then ``rounds`` of iteratively reweighted least squares on the k-space term.

    Samples whose k-space error stays large (unreachable within the limits) are down-weighted with
    Cauchy weights ``1 / (1 + (err / scale_dk)^2)`` (err in dk), so the solution hits the reachable
    samples exactly instead of spreading the error over all of them (the later discarding then skips
    few samples).  Without active limits the first solve is already exact and no round runs.

    ``iters`` None: each solve to the tolerance ``k_tol_dk`` (:func:`solve_warm_start`; its
    :class:`~dtoc.optimize.solver.SolveReport` appended to ``reports``), all of them within ``budget`` evaluations
    together (a round gets what the solves before it left; none with fewer than 40 left);
    an integer: the fixed-count algorithm (:func:`warm_start`, ``iters // 2`` per round).
    """

    spent: list = []  # evaluations of the solves so far (the rounds share ``budget`` with the first solve)

    def solve(x_init=None, n=iters):
        if iters is None:
            x, rep = solve_warm_start(
                twin, ctx, weights, k_tol_dk, budget - sum(spent), state, progress, x_init,
                minimax_rounds, minimax_budget,
            )  # fmt: skip
            spent.append(rep.evaluations)
            if reports is not None:
                reports.append(rep)
            return x
        return warm_start(twin, ctx, weights, n, state, progress, x_init=x_init)

    x = solve()
    for _r in range(rounds):
        if state is not None and state.interrupted:
            break
        if iters is None and budget - sum(spent) < 40:
            break  # the budget is spent: no round
        with torch.no_grad():
            err = kspace_error_dk(twin.forward_edges(x, moments=False).kspace_rad_per_m, ctx)
        if err.max() <= scale_dk:
            break
        old = ctx.sample_weight
        ctx.sample_weight = torch.as_tensor(1.0 / (1.0 + (err / scale_dk) ** 2), dtype=x.dtype, device=x.device)
        try:
            x = solve(x, None if iters is None else iters // 2)
        finally:
            ctx.sample_weight = old
    return x


# ---------------------------------------------------------------------------------------------------
# full loss
# ---------------------------------------------------------------------------------------------------
def evaluate(twin, imager, ctx, weights, edges: torch.Tensor, idx: int = 0, keep_mask=None, with_image: bool = True):
    """Forward pass: returns (total loss tensor, term dict, dict of intermediate tensors)."""
    r = twin.forward_edges(edges)
    g, G, b0, k = r.demanded_grad_mT_per_m, r.realized_grad_mT_per_m, r.b0_uT, r.kspace_rad_per_m
    images = targets = None
    if imager is not None and with_image and weights.image > 0:
        sig = imager.signal(G, b0, idx)
        images = [imager.image(sig, keep_mask=keep_mask)]
        targets = [imager.targets[idx]]
    total, terms = L.total_loss(
        weights, ctx, g=g, G=G, k=k, images=images, targets=targets, k_moment=r.moments_rad_per_m
    )
    return total, terms, {"g": g, "G": G, "b0": b0, "k": k, "images": images}


def full_weights(cfg: OptimizeConfig):
    """Loss weights of the full-loss stage: ``cfg.weights`` with the k-space weight scaled by
    ``cfg.full_kspace_scale`` (the warm start has already placed the samples; a smaller k weight lets
    the image term trade k accuracy of unimportant samples for image fidelity, as the paper's tiny w_k)."""
    w = cfg.weights
    if cfg.full_kspace_scale == 1.0:
        return w
    return w.model_copy(update={"kspace": w.kspace * cfg.full_kspace_scale})


def full_loss(
    twin,
    imager,
    ctx,
    cfg: OptimizeConfig,
    edges0: torch.Tensor,
    state: StageState,
    progress: ProgressFn | None = None,
    start_it: int = 0,
    paper: bool = False,
    checkpoint: Callable[[torch.Tensor, int], None] | None = None,
) -> torch.Tensor:
    """Projected Adam (or L-BFGS) on the full loss; returns the best edges (projected)."""
    P = twin.projector
    free = twin.free_t
    x = edges0.detach().clone()
    n_img = len(imager.phantoms) if imager is not None else 1
    lr = cfg.lr if cfg.lr is not None else (1e-3 if paper else 0.02)
    restarts = set(cfg.restarts)
    if paper and not cfg.restarts and cfg.iters > 0:
        scale = cfg.iters / 22500.0  # the paper's schedule, compressed to this run's length
        restarts = {max(1, int(round(r * scale))) for r in PAPER_RESTARTS}
    if cfg.optimizer == "pgd" and not paper:
        try:
            x = _pgd(twin, imager, ctx, cfg, x, state, progress, start_it, n_img, lr, checkpoint)
        except KeyboardInterrupt:
            state.interrupted = True
            x = state.best_edges.detach().clone() if math.isfinite(state.best_loss) else x
        return _finish(twin, imager, ctx, cfg, x, state, n_img)
    x.requires_grad_(True)
    opt = _make_opt(cfg, x, lr)
    weights = full_weights(cfg)
    try:
        for it in range(start_it, cfg.iters):
            idx = (it // cfg.augment_every) % n_img
            if it in restarts:
                opt = _make_opt(cfg, x, lr)

            last: dict = {}  # the closure's figures of its (last) evaluation

            def closure(opt=opt, idx=idx, last=last):
                opt.zero_grad()
                total, terms, _ = evaluate(twin, imager, ctx, weights, x, idx)
                total.backward()
                with torch.no_grad():
                    x.grad.mul_(free)
                last["terms"] = terms
                last["total"] = float(total.detach())
                return total

            cur = x.detach().clone()
            opt.step(closure)
            val = last["total"]
            # the loss was evaluated at the (feasible) iterate before the step
            if n_img == 1 and val < state.best_loss:
                state.best_loss, state.best_edges = val, cur
            with torch.no_grad():
                x.copy_(P.project(x.detach(), n_iter=8, exact=False))
            state.history.append({"stage": "full", "it": it + 1, "loss": val, "phantom": idx, **last["terms"]})
            if progress:
                progress("full", it + 1, cfg.iters, val)
            if checkpoint is not None and (it + 1) % cfg.checkpoint_every == 0:
                checkpoint(x.detach().clone(), it + 1)
    except KeyboardInterrupt:
        state.interrupted = True
    return _finish(twin, imager, ctx, cfg, x.detach(), state, n_img)


def _finish(twin, imager, ctx, cfg, x, state, n_img):
    P = twin.projector
    last = x.detach().clone()
    if n_img > 1 or not math.isfinite(state.best_loss):
        state.best_edges = last  # with augmentation the losses of different phantoms do not compare
    else:
        # compare the final iterate too
        with torch.no_grad():
            val = float(evaluate(twin, imager, ctx, full_weights(cfg), last, 0)[0])
        if val < state.best_loss:
            state.best_loss, state.best_edges = val, last
    return P.project(state.best_edges, n_iter=60)


def _make_opt(cfg, x, lr):
    return torch.optim.Adam([x], lr=lr)


def _pgd(twin, imager, ctx, cfg, x, state, progress, start_it, n_img, lr, checkpoint):
    """Monotone projected gradient descent with backtracking on the full loss.

    The first trial step moves the largest coordinate by ``lr`` mT/m; a step is accepted only if it
    lowers the loss (of the current phantom); the step grows x1.5 after a success and shrinks x0.3
    after a failure; after 6 failures in a row the stage stops (no descent found).
    """
    P = twin.projector
    free = twin.free_t
    weights = full_weights(cfg)

    def val_grad(e, idx):
        e = e.detach().requires_grad_(True)
        total, terms, _ = evaluate(twin, imager, ctx, weights, e, idx)
        (g,) = torch.autograd.grad(total, e)
        return float(total.detach()), torch.where(free, g, torch.zeros_like(g)), terms

    idx = (start_it // cfg.augment_every) % n_img
    v, g, terms = val_grad(x, idx)
    eta = lr / max(float(g.abs().max()), 1e-30)
    for it in range(start_it, cfg.iters):
        new_idx = (it // cfg.augment_every) % n_img
        if new_idx != idx:
            idx = new_idx
            v, g, terms = val_grad(x, idx)
        if n_img == 1 and v < state.best_loss:
            state.best_loss, state.best_edges = v, x.detach().clone()
        accepted = False
        for _ in range(6):
            y = P.project(x - eta * g, n_iter=8, exact=False)
            vy, gy, ty = val_grad(y, idx)
            if vy < v:
                x, v, g, terms = y, vy, gy, ty
                eta *= 1.5
                accepted = True
                break
            eta *= 0.3
        state.history.append({"stage": "full", "it": it + 1, "loss": v, "phantom": idx, "step": eta, **terms})
        if progress:
            progress("full", it + 1, cfg.iters, v)
        if checkpoint is not None and (it + 1) % cfg.checkpoint_every == 0:
            checkpoint(x.detach().clone(), it + 1)
        if not accepted:
            break
    if n_img == 1 and v < state.best_loss:
        state.best_loss, state.best_edges = v, x.detach().clone()
    return x


def memo_signal(imager, keep: int = 2):
    """``imager`` with its ``signal(G, b0, idx)`` remembering its last ``keep`` results by the exact bytes of
    their inputs (no autograd): the discarding's simulation of the final waveform is the export's "after"
    simulation of the same waveform (one PDG run of the whole sequence each, the costliest step of a long file
    with an image term); a waveform that differs in any bit is simulated again.  Returns ``imager``."""
    if imager is None:
        return None
    import hashlib
    from collections import OrderedDict

    sim = imager.signal
    memo: OrderedDict = OrderedDict()

    def digest(t) -> bytes:
        if t is None:
            return b""
        a = t.detach().cpu().contiguous().numpy()
        return hashlib.sha256(a.tobytes()).digest() + repr((a.dtype.str, a.shape)).encode()

    def signal(G, b0, idx):
        if torch.is_grad_enabled() and (G.requires_grad or (b0 is not None and b0.requires_grad)):
            return sim(G, b0, idx)
        key = (idx, digest(G), digest(b0))
        if key in memo:
            memo.move_to_end(key)
            return memo[key].clone()
        out = sim(G, b0, idx)
        memo[key] = out.detach()
        while len(memo) > keep:
            memo.popitem(last=False)
        return out

    setattr(imager, "signal", signal)  # noqa: B010 (an instance attribute over the method, this run's imager only)
    return imager


# ---------------------------------------------------------------------------------------------------
# post-hoc discarding
# ---------------------------------------------------------------------------------------------------
def kspace_error_dk(k: torch.Tensor, ctx) -> np.ndarray:
    """(N_adc,) Euclidean k-space error per sample in units of dk (finite-dk axes only)."""
    dk = ctx.dk_rad_per_m
    inv = torch.where(torch.isfinite(dk), 1.0 / dk, torch.zeros_like(dk))
    return ((k - ctx.k0_rad_per_m) * inv[:, None]).norm(dim=0).detach().cpu().numpy()


def choose_discard(twin, imager, ctx, edges: torch.Tensor, n_candidates: int = 48, floor_dk: float = 0.0):
    """Pick the k-error threshold (dk) that minimises image NRMSE when samples beyond it are dropped.

    ``floor_dk``: samples within it are never dropped (the run's ``k_tol_dk``: on target by the solver's
    stopping rule; discarding is for the samples the limits leave off it).  When every sample is within it, no
    candidate is simulated (each is one reconstruction: a non-uniform DFT's operator of a radial or spiral file
    is built per mask, seconds each).

    Returns:
        (keep_mask (N_adc,) bool, threshold_dk (float, inf = keep all), nrmse at that threshold).
    """
    with torch.no_grad():
        r = twin.forward_edges(edges, moments=False)
        err = kspace_error_dk(r.kspace_rad_per_m, ctx)
        keep_all = np.ones(err.shape, dtype=bool)
        if imager is None or (floor_dk > 0 and not bool(np.any(err > floor_dk))):
            return keep_all, math.inf, float("nan")
        sig = imager.signal(r.realized_grad_mT_per_m, r.b0_uT, 0)
        target = imager.targets[0]

        def nrmse(mask):
            return float(metrics.nrmse(imager.image(sig, keep_mask=torch.as_tensor(mask)), target))

        best = (nrmse(keep_all), math.inf, keep_all)
        qs = np.unique(np.quantile(err, np.linspace(0.5, 1.0, n_candidates)))
        for thr in qs[::-1]:
            if thr < floor_dk:
                break
            mask = err <= thr
            if mask.all() or mask.sum() < 0.5 * mask.size:
                continue
            v = nrmse(mask)
            if v < best[0] - 1e-12:
                best = (v, float(thr), mask)
    return best[2], best[1], best[0]
