"""Classic first-order pre-emphasis (paper Eq. 2) as the baseline of `dtoc optimize --method preemphasis`.

``g_pre = g + sum_n a_n * (dg/dt conv H(t) exp(-t / T_n))`` with coefficients (a_n, T_n) fitted
numerically so that the hardware model maps ``g_pre`` back onto ``g`` (least squares over the base
sequence's waveform, L-BFGS on log-parameters).  For a single exponential eddy current
(``G = g - alpha * (g' conv exp(-t/tau))``) the exact inverse is ``a = alpha / (1 - alpha)``,
``T = (1 - alpha) * tau``; the fit recovers it (unit test).

When ``g_pre`` breaks the hard limits the paper offers two fallbacks:

* **variable TE** (GRE specs only): TE (and TR by the same amount) is increased on the 10 us grid,
  the base rebuilt and pre-emphasised again, until ``g_pre`` meets the limits (a spoiler too high to
  be pre-emphasised within gmax is first lowered and lengthened at constant moment, TR growing by the
  extra lobe length); the TE/TR found are
  reported (the exported file keeps the base TE, as in the paper's constant-TE comparison).
* **constant TE** (the paper's, :func:`constant_te`; GRE-like sequences): the k-space extent shrinks
  by n = 0, 1, 2, ... grid steps until the pre-emphasised waveform meets gmax: the first n samples of
  every readout and the n outermost phase-encode lines on either side are left out (zero-filled),
  the prewinder / phase-encode lobes end on the first kept sample instead of the ADC start (n dwells
  longer, so lower), the phase-encode rewinders follow, and the spoiler keeps its moment spread
  over the whole gap to the next RF pulse.  TE, TR and the ADC are those of the base.
* where that does not apply, ``g_pre`` is projected onto the limits and the samples that then miss
  their k-space target are skipped with the threshold that minimises the image error; for GRE this
  projection variant is computed too and reported beside the paper's fallback.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch

from dtoc.hardware.recursion import exp_response


def apply_preemphasis(g: torch.Tensor, dt_s: float, alphas, taus_s) -> torch.Tensor:
    """``g + sum a_n (g' conv exp(-t/T_n))`` along the last axis (exact PWL convolution)."""
    out = g
    for a, tau in zip(alphas, taus_s):
        tau_t = tau if isinstance(tau, torch.Tensor) else torch.tensor(float(tau), dtype=g.dtype)
        out = out + a * exp_response(g, dt_s, tau_t)
    return out


def fit_preemphasis(
    hardware,
    g: np.ndarray,
    dt_s: float,
    n_terms: int = 2,
    init_taus_s=(1e-3, 0.1),
    init_alpha: float = 0.05,
    iters: int = 60,
) -> dict:
    """Fit (a_n, T_n) so that ``hardware(apply_preemphasis(g)) ~ g`` in the least-squares sense.

    Args:
        hardware: callable ``(g (B,3,T), dt) -> (G, b0)``.
        g: (3, T) waveform to reproduce (the base sequence's demanded = target gradient), mT/m.
        dt_s: its sample spacing.
    Returns:
        {"alpha": [..], "tau_s": [..], "rms_before_mT_per_m", "rms_after_mT_per_m"}.
    """
    gt = torch.as_tensor(np.asarray(g, dtype=np.float64))
    taus0 = list(init_taus_s)[:n_terms] + [1e-2] * max(0, n_terms - len(init_taus_s))
    la = torch.tensor([math.log(init_alpha)] * n_terms, dtype=torch.float64, requires_grad=True)
    lt = torch.tensor([math.log(t) for t in taus0], dtype=torch.float64, requires_grad=True)
    scale = float((gt**2).mean()) or 1.0

    def resid(la_, lt_):
        gp = apply_preemphasis(gt, dt_s, torch.exp(la_), torch.exp(lt_))
        G, _ = hardware(gp[None], dt_s)
        return ((G[0] - gt) ** 2).mean() / scale

    with torch.no_grad():
        G0, _ = hardware(gt[None], dt_s)
        before = float(((G0[0] - gt) ** 2).mean().sqrt())
    opt = torch.optim.LBFGS([la, lt], lr=1.0, max_iter=iters, line_search_fn="strong_wolfe")

    def closure():
        opt.zero_grad()
        v = resid(la, lt)
        v.backward()
        return v

    opt.step(closure)
    with torch.no_grad():
        after = float((resid(la, lt) * scale).sqrt())
    order = np.argsort(torch.exp(lt).detach().numpy())
    la_d, lt_d = torch.exp(la.detach()), torch.exp(lt.detach())
    return {
        "alpha": [float(la_d[i]) for i in order],
        "tau_s": [float(lt_d[i]) for i in order],
        "rms_before_mT_per_m": before,
        "rms_after_mT_per_m": after,
    }


def run_preemphasis(ir, twin, ctx, imager, limits) -> dict:
    """Pre-emphasise the base sequence, apply the constant-TE fallback if needed.

    Returns:
        {"edges": (3, N+1) projected edges, "keep_mask": (N_adc,) bool, "report": dict}.
    """
    from dtoc.optimize.limits import edges_to_played, limit_violations
    from dtoc.optimize.optimizer import choose_discard

    P = twin.projector
    axes = [a for a in range(3) if P.free[a].any()]
    e0 = ir.edge_grad_mT_per_m
    fit = fit_preemphasis(twin.hardware, e0, ir.raster_s) if twin.hardware is not None else {"alpha": [], "tau_s": []}
    with torch.no_grad():
        pe = apply_preemphasis(torch.as_tensor(e0), ir.raster_s, fit["alpha"], fit["tau_s"]).numpy()
    edges = np.where(P.free, pe, e0)
    fine = edges_to_played(edges, twin.base_fine, twin.fine_mask)
    viol = limit_violations(fine, ir.dt_fine_s, limits)
    report = {"coefficients": fit, "axes": axes, "within_limits": not viol, "violations": viol[:6]}
    if not viol:
        return {"edges": edges, "keep_mask": np.ones(ir.n_adc_samples, bool), "report": {**report, "fallback": None}}
    proj = P.project(edges, n_iter=60)
    keep, thr, nr = choose_discard(twin, imager, ctx, torch.as_tensor(proj))
    projection = {
        "fallback": "constant-TE (projection + sample skipping)",
        "skip_threshold_dk": None if not math.isfinite(thr) else thr,
        "nrmse": nr,
        "skipped_fraction": float(np.mean(~keep)),
    }
    vte = variable_te(ir, twin, limits, fit)
    if vte is not None:
        report["variable_te"] = vte
    cte = constant_te(ir, twin, limits, fit)
    if cte is None:
        report.update(projection)
        return {"edges": proj, "keep_mask": keep, "report": report}
    report.update(
        {
            "fallback": "constant-TE (k-space extent shrink, paper)",
            "shrink_dk": cte["n"],
            "projection_variant": projection,
        }
    )
    return {"edges": P.project(cte["edges"], n_iter=60), "keep_mask": cte["keep_mask"], "report": report}


def _edge_area(e: np.ndarray) -> float:
    """Area of a piecewise-linear waveform given by its raster-edge values, mT/m x rasters."""
    return float(0.5 * (e[:-1] + e[1:]).sum())


def _emphasis_slew_T_per_m_per_s(limits, fit) -> float:
    """Slew for rebuilt lobes that pre-emphasis may still overdrive within smax: pre-emphasis raises a
    ramp's slew by (1 + sum a_n) (the paper's piecewise-constant base had no ramps to overdrive)."""
    return 0.98 * (limits.smax_T_per_m_per_s * (1.0 - limits.slew_margin)) / (1.0 + float(np.sum(fit["alpha"])))


def _trapezoid(g_start: float, g_end: float, n_raster: int, area: float, slew_step: float) -> np.ndarray | None:
    """(n_raster + 1,) raster-edge values from ``g_start`` to ``g_end`` with piecewise-linear area
    ``area`` (mT/m x rasters): ramp at ``slew_step`` mT/m per raster to a plateau P, hold, ramp to
    ``g_end``; P by bisection (the area grows with P).  None when the area does not fit."""
    if n_raster < 1:
        return None
    t = np.arange(n_raster + 1, dtype=np.float64)

    def shape(P):  # exact while both ramps fit: |P - g_start| + |P - g_end| <= slew_step * n_raster
        up = g_start + np.sign(P - g_start) * np.minimum(abs(P - g_start), slew_step * t)
        down = g_end + np.sign(P - g_end) * np.minimum(abs(P - g_end), slew_step * (n_raster - t))
        return up + down - P

    def area_of(P):
        return _edge_area(shape(P))

    if abs(g_start - g_end) > slew_step * n_raster:
        return None
    lo = 0.5 * (g_start + g_end - slew_step * n_raster)
    hi = 0.5 * (g_start + g_end + slew_step * n_raster)
    if not (area_of(lo) <= area <= area_of(hi)):
        return None
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        if area_of(mid) < area:
            lo = mid
        else:
            hi = mid
    return shape(0.5 * (lo + hi))


def constant_te(ir, twin, limits, fit, max_shrink: int | None = None, min_shrink: int = 0) -> dict | None:
    """The paper's constant-TE fallback: smallest k-space shrink n (grid steps) whose pre-emphasised
    waveform meets gmax (see the module doc).  n = 0 rebuilds the lobes with the slew headroom only
    (plain pre-emphasis of the base may break smax on its ramps, not gmax).  Returns {"n", "edges"
    (3, N+1), "keep_mask"} or None when it does not apply (no readout / phase axis, ADC samples off the raster edges, nothing fits).

    The rebuilt lobes ramp at :func:`_emphasis_slew_T_per_m_per_s`, as in :func:`variable_te`."""
    from dtoc.constants import GAMMA_RAD_PER_S_PER_MT
    from dtoc.optimize.limits import edges_to_played

    ro, pe = ir.readout_axis, ir.phase_axis
    if ir.kind != "gre" or ro is None or pe is None or not ir.adc or ir.dk_rad_per_m is None:
        return None
    P = twin.projector
    e0 = np.asarray(ir.edge_grad_mT_per_m, dtype=np.float64)
    free = np.asarray(P.free, dtype=bool)
    r = ir.raster_s
    to_area = 1.0 / (GAMMA_RAD_PER_S_PER_MT * r)  # rad/m -> mT/m x rasters
    dk = ir.dk_rad_per_m
    k0 = ir.nominal_kspace_rad_per_m()
    step = _emphasis_slew_T_per_m_per_s(limits, fit) * 1e3 * r  # mT/m per raster
    gmax = limits.gmax_eff_mT_per_m
    # per readout: edge indices of its samples, the free run around it, its phase-encode value
    both = free[ro] & free[pe]
    lines, start = [], 0
    for a in ir.adc:
        idx = a.sample_times_s / r
        if np.any(np.abs(idx - np.round(idx)) > 1e-6):
            return None
        idx = np.round(idx).astype(int)
        lo = idx[0]
        while lo > 0 and both[lo - 1]:
            lo -= 1
        hi = idx[-1]
        while hi < len(both) - 1 and both[hi + 1]:
            hi += 1
        lines.append({"idx": idx, "lo": lo - 1, "hi": hi + 1, "s": slice(start, start + a.num_samples)})
        start += a.num_samples
    if any(ln["lo"] < 0 or ln["hi"] >= e0.shape[1] for ln in lines):
        return None
    ky = np.array([np.median(k0[pe, ln["s"]]) / dk[pe] for ln in lines])
    levels = np.unique(np.round(ky, 6))
    n_samp = min(len(ln["idx"]) for ln in lines)
    top = max_shrink if max_shrink is not None else min(n_samp - 1, (len(levels) - 1) // 2)

    def build(n: int):
        e = e0.copy()
        keep = np.ones(ir.n_adc_samples, dtype=bool)
        lo_ky, hi_ky = levels[n], levels[len(levels) - 1 - n]
        for ln, kyl in zip(lines, ky):
            i_n, i_last = ln["idx"][n], ln["idx"][-1]
            keep[ln["s"].start : ln["s"].start + n] = False
            kyc = float(np.clip(kyl, lo_ky, hi_ky))
            if abs(kyc - kyl) > 1e-6:
                keep[ln["s"]] = False
            for ax in (ro, pe):
                base_pre = _edge_area(e0[ax, ln["lo"] : i_n + 1])
                base_post = _edge_area(e0[ax, i_last : ln["hi"] + 1])
                d = (kyc - kyl) * dk[pe] * to_area if ax == pe else 0.0
                seg1 = _trapezoid(e0[ax, ln["lo"]], e0[ax, i_n], i_n - ln["lo"], base_pre + d, step)
                seg2 = _trapezoid(e0[ax, i_last], e0[ax, ln["hi"]], ln["hi"] - i_last, base_post - d, step)
                if seg1 is None or seg2 is None:
                    return None, None
                e[ax, ln["lo"] : i_n + 1] = seg1
                e[ax, i_last : ln["hi"] + 1] = seg2
        return e, keep

    for n in range(min_shrink, top + 1):
        e, keep = build(n)
        if e is None:
            continue
        with torch.no_grad():
            pre = apply_preemphasis(torch.as_tensor(e), r, fit["alpha"], fit["tau_s"]).numpy()
        pre = np.where(free, pre, e0)
        fine = edges_to_played(pre, twin.base_fine, twin.fine_mask)
        if np.abs(fine).max() <= gmax:
            return {"n": n, "edges": pre, "keep_mask": keep}
    return None


def variable_te(ir, twin, limits, fit, max_steps: int = 2000) -> dict | None:
    """Variable-TE fallback for sequences built from a GRE spec: smallest TE (10 us steps, TR grown by
    the same amount) for which the pre-emphasised base meets the limits.  None when not applicable."""
    from dtoc.optimize.limits import limit_violations
    from dtoc.seq.ir import edges_to_fine

    spec_path = ir.meta.get("spec_path")
    if ir.kind != "gre" or not spec_path:
        return None
    from dtoc.errors import DtocError
    from dtoc.seq.build import build_ir
    from dtoc.seq.spec import GreSpec, load_spec

    spec = load_spec(spec_path)
    if not isinstance(spec, GreSpec):
        return None
    step_ms = spec.system.grad_raster_s * 1e3
    # the spoiler keeps its moment but is lowered to what pre-emphasis can still overdrive within gmax
    # (a step of amplitude A pre-emphasised peaks at A (1 + sum a_n)); its lobe grows longer, TR with it
    sp_amp, sp_dur = spec.spoiler_mT_per_m, spec.spoiler_duration_ms
    a_max = 0.98 * limits.gmax_eff_mT_per_m / (1.0 + float(np.sum(fit["alpha"])))
    if sp_amp > a_max:
        sp_dur = math.ceil(sp_dur * sp_amp / a_max / step_ms) * step_ms
        sp_amp = sp_amp * spec.spoiler_duration_ms / sp_dur
    extra_tr_ms = sp_dur - spec.spoiler_duration_ms
    # ramps: the rebuilt base ramps at what pre-emphasis may still overdrive within smax
    sys2 = spec.system.model_copy(
        update={
            "max_slew_T_per_m_per_s": min(spec.system.max_slew_T_per_m_per_s, _emphasis_slew_T_per_m_per_s(limits, fit))
        }
    )

    def ok(i: int) -> bool:
        s2 = spec.model_copy(
            update={
                "te_ms": spec.te_ms + i * step_ms,
                "tr_ms": spec.tr_ms + i * step_ms + extra_tr_ms,
                "spoiler_mT_per_m": sp_amp,
                "spoiler_duration_ms": sp_dur,
                "system": sys2,
            }
        )
        try:
            ir2 = build_ir(s2)
        except DtocError:
            return False
        e = ir2.edge_grad_mT_per_m
        with torch.no_grad():
            pe = apply_preemphasis(torch.as_tensor(e), ir2.raster_s, fit["alpha"], fit["tau_s"]).numpy()
        free = ir2.free_mask[:, ::2] & np.any(np.abs(e) > 0, axis=1)[:, None]
        return not limit_violations(edges_to_fine(np.where(free, pe, e)), ir2.dt_fine_s, limits)

    # exponential search, then bisection (feasibility grows with TE)
    lo, hi = 0, 1
    while hi <= max_steps and not ok(hi):
        lo, hi = hi, hi * 2
    if hi > max_steps:
        if not ok(max_steps):
            return {
                "te_ms": None,
                "tr_ms": None,
                "note": f"no TE within +{max_steps * step_ms:.2f} ms meets the limits"
                + (f" (spoiler lowered to {sp_amp:.2f} mT/m over {sp_dur:.2f} ms)" if extra_tr_ms > 0 else ""),
            }
        hi = max_steps
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if ok(mid):
            hi = mid
        else:
            lo = mid
    out: dict[str, Any] = {
        "te_ms": round(spec.te_ms + hi * step_ms, 6),
        "tr_ms": round(spec.tr_ms + hi * step_ms + extra_tr_ms, 6),
    }
    if extra_tr_ms > 0:
        out["spoiler"] = {
            "mT_per_m": round(sp_amp, 4),
            "duration_ms": round(sp_dur, 6),
            "note": "spoiler lowered to fit pre-emphasis within gmax, moment kept; TR includes its longer lobe",
        }
    return out
