"""`dtoc optimize` as a library call: inputs -> pre-compensated sequence, manifest, report.

:func:`optimize_sequence` validates every input and output path first (bad input: one-line error,
nothing written), runs the chosen method, projects onto the hard limits a last time, verifies the
exported waveform (:func:`dtoc.seq.check.check_ir_limits`), then writes the ``.seq`` (and checks the
written file with the full validator before it replaces the destination), the manifest and the PNG.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from dtoc.constants import AXES, BASE_HASH_DEFINITION
from dtoc.errors import InputError, LimitError, ValidationFailed
from dtoc.optimize import loss as L
from dtoc.optimize import optimizer as O
from dtoc.optimize.config import OptimizeConfig
from dtoc.optimize.limits import (
    EdgeProjector,
    Limits,
    base_physical_warnings,
    check_area_reachable,
    limit_violations,
    physical_violations,
    waveform_extremes,
)
from dtoc.optimize.report import plotted_span
from dtoc.optimize.solver import SolveReport, explain_unreachable
from dtoc.optimize.twin import EdgeTwin
from dtoc.seq.check import (
    SafetyChecks,
    base_timing_refusal,
    check_file_pieces,
    check_ir_limits,
    inherited_text,
    settle_inherited,
)
from dtoc.seq.ir import SequenceIR
from dtoc.seq.seqtext import shared_parse
from dtoc.seq.system import SystemSpec
from dtoc.seq.versions import check_writable, version_str
from dtoc.seq.write import output_version, preflight_write, verify_and_check, write_seq_text
from dtoc.sim import metrics
from dtoc.sim.imager import Imager
from dtoc.util.atomic import (
    atomic_move_file,
    atomic_write_bytes,
    atomic_write_text,
    check_outputs,
    outputs_together,
    sha256_bytes,
    sha256_file,
    unused_path,
)
from dtoc.util.cplx import cabs
from dtoc.util.interrupt import deferred, fault_point
from dtoc.util.jsonout import strict_json
from dtoc.util.replay import totals as replay_totals
from dtoc.version import package_versions


# ---------------------------------------------------------------------------------------------------
# set-up helpers
# ---------------------------------------------------------------------------------------------------
def limits_and_sources(ir, cfg: OptimizeConfig) -> tuple[Limits, dict[str, str]]:
    """Hard limits and where each came from: the config (``--gmax`` / ``--smax``), else the sequence's
    definitions ``MaxGrad_mT_per_m`` / ``MaxSlew_T_per_m_per_s``.  Never assumed: a limit given by neither
    is a one-line InputError (pypulseq and Pulseq MATLAB files carry no limits)."""
    d = ir.definitions or {}

    def num(key):
        v = d.get(key)
        if isinstance(v, (list, tuple)):
            v = v[0] if v else None
        try:
            x = float(v)
        except (TypeError, ValueError):
            return None
        if not (math.isfinite(x) and x > 0):
            raise InputError(f"the sequence's definition {key} = {v!r} is not a positive number")
        return x

    values, sources = {}, {}
    for name, given, key, opt in (
        ("gmax_mT_per_m", cfg.gmax_mT_per_m, "MaxGrad_mT_per_m", "--gmax"),
        ("smax_T_per_m_per_s", cfg.smax_T_per_m_per_s, "MaxSlew_T_per_m_per_s", "--smax"),
    ):
        if given:
            values[name], sources[name] = float(given), opt
        elif (x := num(key)) is not None:
            values[name], sources[name] = x, f"file definition {key}"
        else:
            raise InputError(
                f"no {opt.lstrip('-')} limit: the sequence defines no {key}; give {opt} (limits are never assumed)"
            )
    lim = Limits(
        values["gmax_mT_per_m"], values["smax_T_per_m_per_s"], amp_margin=cfg.amp_margin, slew_margin=cfg.slew_margin
    )
    return lim, sources


def system_limits(ir, cfg: OptimizeConfig) -> Limits:
    """The hard limits of :func:`limits_and_sources`."""
    return limits_and_sources(ir, cfg)[0]


def free_edges(ir) -> np.ndarray:
    """(3, N+1) optimizer variables: free raster edges on axes whose base waveform is not all zero
    (the paper optimizes the readout and phase axes of the GRE; an idle axis stays idle)."""
    free = np.asarray(ir.free_mask[:, ::2], dtype=bool).copy()
    idle = ~np.any(np.abs(ir.grad_mT_per_m) > 0, axis=1)
    free[idle] = False
    return free


def make_phantoms(ir, cfg: OptimizeConfig, phantom=None) -> list:
    """The phantom and its rotated copies (data augmentation).

    ``phantom``: a :class:`~dtoc.sim.phantom.Phantom`; or a spec of
    :func:`~dtoc.sim.phantom.resolve_phantom` ('brain', 'brain-noscalp', 'brain:N', a ``.npz`` path);
    None = 'brain'.  Built-in phantoms are made at the sequence's matrix (``cfg.phantom_size``
    overrides it) and FOV, with the tissue values at ``cfg.b0_T``.
    """
    from dtoc.sim.phantom import Phantom, phantom_for, rotate

    if not isinstance(phantom, Phantom):
        spec = "brain" if phantom is None else str(phantom)
        phantom = phantom_for(ir, spec, size=cfg.phantom_size, field_T=cfg.b0_T)
    out = [phantom]
    if cfg.augment_rotations > 0:
        rng = np.random.default_rng(cfg.seed)
        for a in rng.uniform(-cfg.augment_max_deg, cfg.augment_max_deg, size=cfg.augment_rotations):
            out.append(rotate(phantom, float(a)))
    return out


# ---------------------------------------------------------------------------------------------------
# metrics
# ---------------------------------------------------------------------------------------------------
def quality(
    twin: EdgeTwin, imager: Imager | None, ctx, played, keep_mask=None, waveform_samples: int | None = None
) -> dict:
    """Figures of one demanded waveform: nrmse, ghost_ratio (EPI), k-space errors, discards.

    ``played``: the (3, 2N+1) fine demanded waveform, mT/m (the base as given, limits ignored; or the exported
    waveform).  ``waveform_samples``: keep only the first n fine samples of the demanded and realized waveforms (``_g``,
    ``_G``: the report's panel, :func:`dtoc.optimize.report.plotted_span`) instead of the whole sequence's.
    """
    with torch.no_grad():
        n_head = waveform_samples
        streamed = None if imager is not None or n_head is None else _stream_realization(twin, played)
        if streamed is None or n_head is None:
            r = twin.forward(twin.demanded(played), moments=False)
            g, G, b0, k = r.demanded_grad_mT_per_m, r.realized_grad_mT_per_m, r.b0_uT, r.kspace_rad_per_m
        else:  # a long sequence without an image: played through the chain piece by piece, never whole
            g, G, b0_phase, k = streamed(n_head)
            b0 = None
        dk = ctx.dk_rad_per_m.cpu().numpy()
        ke = metrics.kspace_errors(k, ctx.k0_rad_per_m, dk)
        out = {
            "kspace_rmse_rad_per_m": ke["kspace_rmse_rad_per_m"],
            "kspace_max_dk": ke["kspace_max_err_dk"],
            "kspace_max_err_rad_per_m": ke["kspace_max_err_rad_per_m"],
            "nrmse": None,
            "ghost_ratio": None,
        }
        if keep_mask is not None and not np.all(keep_mask):
            kk = metrics.kspace_errors(k, ctx.k0_rad_per_m, dk, mask=keep_mask)
            out["kspace_rmse_kept_rad_per_m"] = kk["kspace_rmse_rad_per_m"]
            out["kspace_max_kept_dk"] = kk["kspace_max_err_dk"]
        out["samples_discarded"] = int(0 if keep_mask is None else np.sum(~np.asarray(keep_mask)))
        if imager is not None:
            sig = imager.signal(G, b0, 0)
            km = None if keep_mask is None else torch.as_tensor(np.asarray(keep_mask))
            im = imager.image(sig, keep_mask=km)
            m = metrics.image_metrics(
                im, imager.targets[0], epi=twin.ir.kind == "epi", phase_dim=twin.ir.phase_image_dim,
                rf_flips_rad=[r.flip_angle_rad for r in twin.ir.rf],
            )  # fmt: skip
            out["nrmse"] = m["nrmse"]
            if m.get("image_reason"):
                out["image_reason"] = m["image_reason"]  # no signal: no image figure (dtoc.sim.metrics)
            if m["ghost_ratio"] is not None:
                out["ghost_ratio"] = m["ghost_ratio"]
                out["ghost_ratio_ideal"] = m["ghost_ratio_ideal"]
                out["ghost_ratio_excess"] = m["ghost_ratio"] - m["ghost_ratio_ideal"]  # what the hardware adds
            out["_image"] = cabs(im).cpu().numpy()
        out["_k"] = k.cpu().numpy()
        out["_G"] = _head(G, waveform_samples)
        out["_g"] = _head(g, waveform_samples)
        out["_b0"] = None if b0 is None else b0.cpu().numpy()
        if streamed is not None:
            out["_b0_phase_adc"] = b0_phase  # the whole B0 waveform is not kept
    return out


def _stream_realization(twin: EdgeTwin, played) -> Callable[[int], tuple] | None:
    """The figures' realization of a long sequence piece by piece (:func:`dtoc.sim.predict.realized_pieces`: the
    chain's memory on either side of each piece), k at the ADC samples integrated across the pieces
    (:func:`dtoc.seq.kspace.kspace_at_streamed`): memory bounded by a piece, not the sequence.  None when it does
    not apply (a chain that is not affine or whose memory is unbounded: played whole).

    Returns ``f(n)`` -> (the first n demanded and realized fine samples (torch), the B0 term's phase at the ADC
    samples (numpy, rad; None without one) instead of the whole B0 waveform, k (3, N_adc), torch).
    Equal to the whole realization up to the chain's truncation at ``memory_s``'s 1e-6 and rounding; a sequence
    of one piece gives it bit for bit."""
    from dtoc.sim.predict import realized_pieces, stream_kspace, streamable

    if not streamable(twin):
        return None
    ir = twin.ir

    def run(n: int) -> tuple:
        heads_g: list = []
        heads_G: list = []

        def pieces():
            for p in realized_pieces(twin, played):
                if p.s < n:
                    heads_g.append(p.g[:, : min(p.own, n) - p.s].clone())
                    heads_G.append(p.G[:, : min(p.own, n) - p.s].clone())
                yield p.s, p.channels()

        kb = stream_kspace(ir, pieces())
        phase = None if kb.shape[0] == 3 else -kb[3].cpu().numpy() * 1e-3  # uT = 1e-3 mT, as b0_phase_at_adc_rad
        k = kb if kb.shape[0] == 3 else kb[:3].clone()  # k held alone (24 bytes per ADC sample), not with the B0 row
        return torch.cat(heads_g, dim=-1), torch.cat(heads_G, dim=-1), phase, k

    return run


def _head(w: torch.Tensor, n: int | None) -> np.ndarray:
    """(3, n) first fine samples of a waveform as numpy (n None: all of it, without a copy)."""
    return w.cpu().numpy() if n is None else w[:, :n].cpu().numpy().copy()  # copied: the rest is not kept


def solver_record(solves: list) -> dict:
    """The manifest's ``solver`` record of the warm start's solves (the first, then one per IRLS round):
    the last solve's figures, the evaluations of all, and the stderr line."""
    last = solves[-1]
    rec = last.as_dict()
    rec["evaluations"] = sum(r.evaluations for r in solves)
    rec["solves"] = len(solves)
    rec["summary"] = last.line().replace(
        f"after {last.evaluations} evaluations", f"after {rec['evaluations']} evaluations"
    )
    return rec


def certify_stop(plan: Plan, x: torch.Tensor, rec: dict) -> None:
    """The whole solve stopped above the tolerance on an affine chain: certify the worst ``cfg.certify_groups``
    (0, the default: none, the record says so) groups of samples (:mod:`dtoc.optimize.certificate`, one
    small LP each) into ``rec`` (the manifest's ``solver`` record, in place): ``certificates``, and the stop reason
    'unreachable (proven)' when a group is proven (no waveform within the limits meets the tolerance; the solver's
    own stop is kept as ``solver_stop_reason``); the summary line says which groups were certified and how."""
    from dtoc.hardware.memory import is_affine
    from dtoc.optimize import certificate as CE

    tol = float(rec.get("k_tol_dk", plan.cfg.k_tol_dk))
    if not (rec.get("achieved_max_dk", 0.0) > tol) or rec.get("stop_reason") == "interrupted":
        return
    if plan.cfg.certify_groups == 0:
        rec["certificates"] = {
            "note": "not certified (certify_groups 0, the default): the samples above the tolerance are named, not "
            "proven unreachable (docs/optimize.md, 'Certificates')"
        }
        return
    if not is_affine(plan.hardware):
        rec["certificates"] = {"note": "not certified: the hardware chain is not affine"}
        return
    ir, ctx = plan.ir, plan.ctx
    with torch.no_grad():
        k = plan.twin.forward_edges(x).kspace_rad_per_m
    err = O.kspace_error_dk(k, ctx)
    certs = CE.certify(
        plan.hardware, ir.dt_fine_s, plan.projector, x.detach().cpu().numpy(), k.detach().cpu().numpy(),
        ctx.k0_rad_per_m.detach().cpu().numpy(), ctx.dk_rad_per_m.detach().cpu().numpy(), ir.adc_times_s,
        [r.t_center_s for r in ir.rf], [r.use for r in ir.rf], err, tol, n_groups=plan.cfg.certify_groups,
    )  # fmt: skip
    xn = x.detach().cpu().numpy()
    for c in certs:  # the witness applied to the whole waveform: does it keep every other sample as good?
        if c.witness_change is not None and not c.proven:
            e, a, v = c.witness_change
            xw = xn.copy()
            xw[a, e] += v
            with torch.no_grad():
                kw = plan.twin.forward_edges(torch.as_tensor(xw, dtype=x.dtype, device=x.device)).kspace_rad_per_m
            c.witness_max_dk, c.stop_max_dk = float(O.kspace_error_dk(kw, ctx).max()), float(err.max())
    n = {s: sum(c.status == s for c in certs) for s in ("proven", "reachable", "not proven")}
    rec["certificates"] = {
        "groups": len(certs),
        "most_groups": plan.cfg.certify_groups,
        "group_samples_max": 2 * CE.GROUP_HALF + 1,
        **{k_.replace(" ", "_"): v for k_, v in n.items()},
        "each": [c.as_dict() for c in certs],
    }
    if n["proven"]:
        rec["solver_stop_reason"] = rec["stop_reason"]
        rec["stop_reason"] = "unreachable (proven)"
    if certs:
        rec["summary"] = rec.get("summary", "") + (
            f"; certified the worst {len(certs)} groups of samples: {n['proven']} proven unreachable, "
            f"{n['reachable']} reachable (the solve stopped short: a change within the limits brings the group within "
            f"the tolerance and no sample beyond the stop's maximum), {n['not proven']} not proven; "
            + "; ".join(c.line() for c in certs[:2])
        )


def streamed_k_errors(twin: EdgeTwin, ctx, played) -> tuple[np.ndarray, np.ndarray]:
    """Per ADC sample and per moment (k just before every RF pulse after the first), the k error of
    the demanded waveform ``played`` (3, 2N+1) against the nominal, dk: the norm over the encoded axes (axes without a k unit left out), the whole
    solve's convention (:func:`dtoc.optimize.optimizer.kspace_error_dk`): the chain
    played piece by piece (:func:`dtoc.sim.predict.realized_pieces`), k integrated across the pieces, so memory is
    bounded by a piece; played whole where the chain cannot be streamed."""
    from dtoc.seq.kspace import kspace_at_streamed
    from dtoc.sim.predict import realized_pieces, streamable

    ir = twin.ir
    t_adc = ir.adc_times_s
    t_mom = np.array([r.t_center_s - 1e-9 for r in ir.rf[1:]], dtype=np.float64)
    with torch.no_grad():
        if streamable(twin):
            pieces = ((p.s, p.G) for p in realized_pieces(twin, played))
            k = kspace_at_streamed(
                pieces, ir.n_fine, ir.dt_fine_s, np.r_[t_adc, t_mom], [r.t_center_s for r in ir.rf],
                [r.use for r in ir.rf],
            )  # fmt: skip
            k_adc, k_mom = k[:, : t_adc.size], k[:, t_adc.size :]
        else:
            r = twin.forward(twin.demanded(played), moments=True)
            k_adc = r.kspace_rad_per_m
            k_mom = r.moments_rad_per_m if r.moments_rad_per_m is not None else torch.zeros((3, 0))
    dk = ctx.dk_rad_per_m.cpu().numpy()
    ax = np.flatnonzero(np.isfinite(dk) & (dk > 0))

    def err(k, k0) -> np.ndarray:
        if k0 is None or k.shape[1] == 0 or ax.size == 0:
            return np.zeros(k.shape[1])
        d = (k.cpu().numpy() - k0.cpu().numpy())[ax] / dk[ax, None]
        return np.sqrt((d**2).sum(axis=0))

    return err(k_adc, ctx.k0_rad_per_m), err(k_mom, ctx.k0_moment_rad_per_m)


def windowed_solver_record(plan: Plan, x: torch.Tensor, fine, st) -> dict:
    """The manifest's ``solver`` record of a windowed solve, in the whole solve's vocabulary
    (:class:`dtoc.optimize.solver.SolveReport`): the exported waveform's k error at every ADC sample and moment
    (streamed: memory bounded by a piece), 'tolerance' when all are within ``k_tol_dk``, else 'converged' (every
    window at its optimum within the limits; 'rounds' if a window's ADMM stopped at its cap) with the samples and
    moments above it named by :func:`dtoc.optimize.solver.explain_unreachable`."""
    ir, tol = plan.ir, plan.cfg.k_tol_dk
    e_adc, e_mom = streamed_k_errors(plan.twin, plan.ctx, fine)
    P, xe = plan.projector, x.detach().cpu().numpy()
    nan = np.full(0, np.nan)
    u_adc = st.unconstrained_adc_dk if st.unconstrained_adc_dk is not None else np.full(e_adc.size, np.nan)
    u_mom = st.unconstrained_moment_dk[1:] if st.unconstrained_moment_dk is not None else nan
    if u_mom.size != e_mom.size:
        u_mom = np.full(e_mom.size, np.nan)
    t_mom = np.array([r.t_center_s for r in ir.rf[1:]], dtype=np.float64)
    un = explain_unreachable(xe, e_adc, u_adc, tol, P, ir.adc_times_s)
    um = explain_unreachable(xe, e_mom, u_mom, tol, P, t_mom)
    um.indices = um.indices + 1  # the moment before RF pulse i (0-based; the first pulse has none)
    worst = float(max(e_adc.max(initial=0.0), e_mom.max(initial=0.0)))
    rep = SolveReport(method="windowed", k_tol_dk=tol, achieved_max_dk=worst, unreachable=un)
    rep.stop_reason = "tolerance" if worst <= tol else ("rounds" if st.admm_capped else "converged")
    rep.evaluations = st.windows
    rep.unconstrained_max_dk = float(np.nanmax(np.r_[u_adc, u_mom, 0.0]))
    rec = rep.as_dict()
    rec.pop("cg_iterations", None)
    rec.pop("active_set_rounds", None)
    rec.pop("fallback_stop_reason", None)
    rec.pop("evaluations", None)
    rec.pop("unconstrained_within_limits", None)
    rec["windows"] = st.windows
    rec["windows_solved_directly"] = st.direct
    rec["admm_iterations"] = st.admm_iters
    rec["windows_admm_at_cap"] = st.admm_capped
    rec["achieved_max_adc_dk"] = float(e_adc.max(initial=0.0))
    rec["achieved_max_moment_dk"] = float(e_mom.max(initial=0.0))
    if st.window_adc_dk is not None and np.isfinite(st.window_adc_dk).any():
        rec["window_model_max_adc_dk"] = float(np.nanmax(st.window_adc_dk))  # what the windows saw when committing
    # the windows' per-sample figures end here (8 bytes per ADC sample each): not held through the write
    st.unconstrained_adc_dk = st.window_adc_dk = st.unconstrained_moment_dk = st.window_moment_dk = None
    md = um.as_dict()
    for w in md["worst"]:
        w["rf_pulse"] = int(w.pop("sample"))
    rec["unreachable_moments"] = md
    line = (
        f"solver: windowed, {rep.stop_reason} after {st.windows} windows ({st.direct} solved directly, "
        f"{st.admm_iters} ADMM iterations); max k error {worst:.3g} dk (ADC samples {rec['achieved_max_adc_dk']:.3g}, "
        f"moments {rec['achieved_max_moment_dk']:.3g}; norm over the encoded axes; tolerance {tol:g} dk)"
    )
    if un.indices.size:
        line += "; " + un.summary()
    if um.indices.size:
        line += "; moments: " + um.summary().replace("samples above", "moments above").replace(
            "sample ", "before RF pulse "
        )
    rec["summary"] = line
    return rec


def why_not_windowed(ir, hardware, cfg: OptimizeConfig, free, parts: bool = False) -> str | None:
    """Why this sequence cannot be solved period by period (None: it can).  ``parts``: periods longer than a dense
    window may be cut in parts whatever the kind ('auto' asks so when the cost rule holds, :func:`window_plan`)."""
    from dtoc.hardware.memory import is_affine

    if cfg.method not in ("dto", "warmstart"):
        return f"method {cfg.method!r} has no windowed form"
    if not is_affine(hardware):
        return "the hardware chain is not affine (e.g. slew_limit)"
    if not any(r.excites for r in ir.rf):
        return "the sequence has no excitation to cut it at"
    from dtoc.optimize.windowed import DENSE_MAX, core_free_counts, period_free_counts

    n = int(core_free_counts(ir, free).max())
    if n > DENSE_MAX:  # a period is cut at block boundaries: one block is too long
        return f"a single block has {n} free variables (> {DENSE_MAX}: the sequence is solved whole)"
    n = int(period_free_counts(ir, free).max())
    # parts of periods: measured better than the base at every sample on spin-echo trains (TSE, HASTE; the KCL 7 T
    # GIRF and a causal chain, docs/optimize.md); other long periods (EPI trains) not yet measured: solved whole
    if n > DENSE_MAX and cfg.windowed != "on" and ir.kind != "tse" and not parts:
        return (
            f"an excitation period has {n} free variables (> {DENSE_MAX}: long periods other than spin-echo "
            "trains are solved whole; windowed: on solves them in parts, docs/optimize.md)"
        )
    return None


def image_in_loss(cfg: OptimizeConfig) -> bool:
    """Whether the run's optimization uses the image: its full-loss stage runs (dto / adam-paper with ``iters`` > 0)
    with an image weight.  Otherwise (warmstart, ``iters`` 0 as for the GRE kind, no image weight) the image is
    only the report's NRMSE and the discarding's, and a long sequence may be solved period by period."""
    return cfg.method in ("dto", "adam-paper") and cfg.iters > 0 and cfg.weights.image > 0


#: 'auto' also windows a sequence shorter than ``window_auto_s`` whose whole solve is estimated at this many seconds
#: or more (:func:`dtoc.util.cost.optimize_cost`) and at least :data:`WINDOW_AUTO_GAIN` times the windowed solve's
#: estimate: many short periods (the corpus's 256-line GREs and bSSFPs of 1-3 s: ~320-380 s), not the goldens'
#: 16-32 TRs (~13-21 s) nor a 128-line GRE that the whole solve finishes (gre_v15: ~80 s estimated, 0.0022 dk
#: whole, tighter than the windows' ADMM leaves, docs/optimize.md).  Assumed, not a measured break-even.
WINDOW_AUTO_WHOLE_S = 120.0
WINDOW_AUTO_GAIN = 3.0


def window_plan(ir, hardware, cfg: OptimizeConfig, free, with_image: bool | None) -> dict | None:
    """Whether to solve period by period (:mod:`dtoc.optimize.windowed`) and with which horizon; None = whole.

    'auto' windows a sequence longer than ``window_auto_s``, or one whose whole solve is estimated to cost far more
    than the windowed one (:data:`WINDOW_AUTO_WHOLE_S`, :data:`WINDOW_AUTO_GAIN`), unless an image asked for
    (``with_image`` True) would enter the optimization (:func:`image_in_loss`): the windowed solve has no image
    term.  An image kept for the report only does not prevent it."""
    from dtoc.hardware.memory import memory_s
    from dtoc.optimize.windowed import period_starts

    if cfg.windowed == "off" or (cfg.windowed == "auto" and with_image and image_in_loss(cfg)):
        return None
    if cfg.windowed == "auto" and ir.duration_s <= cfg.window_auto_s and len(period_starts(ir)) < 3:
        return None  # short, and nothing to cut: not even estimated
    why = why_not_windowed(ir, hardware, cfg, free)
    # long periods other than spin-echo trains (EPI trains): in parts only when the cost rule below says so, for a
    # sequence up to window_auto_s (measured on a 3 s 4-slice EPI: docs/optimize.md; longer ones not yet measured)
    parts = (
        why is not None
        and cfg.windowed == "auto"
        and ir.duration_s <= cfg.window_auto_s
        and why_not_windowed(ir, hardware, cfg, free, True) is None
    )
    if why is not None and not parts:
        if cfg.windowed == "on":
            raise InputError(f"windowed optimization impossible: {why}")
        return None
    causal, acausal = memory_s(hardware)
    cap = cfg.window_horizon_max_s
    horizon, lookahead = min(causal, cap), min(acausal, cap)
    sizes = window_sizes(ir, free, horizon, lookahead)
    rule = f"longer than {cfg.window_auto_s:g} s"
    by_cost = cfg.windowed == "auto" and (ir.duration_s <= cfg.window_auto_s or parts)
    if by_cost:
        from dtoc.util.cost import optimize_cost

        n_fine, n_adc = ir.grad_mT_per_m.shape[1], ir.n_adc_samples
        whole_s, win_s = optimize_cost(n_fine, n_adc)[1], optimize_cost(n_fine, n_adc, sizes)[1]
        if whole_s < WINDOW_AUTO_WHOLE_S or whole_s < WINDOW_AUTO_GAIN * win_s:
            return None
        rule = (
            f"{sizes['n_windows']} {'parts of ' if parts else ''}periods, whole solve estimated ~{whole_s:.0f} s "
            f"against ~{win_s:.0f} s"
        )
    elif cfg.windowed == "on":
        rule = "windowed: on"
    # by the cost rule, a run whose full loss would use the image keeps the image for the report (plan_run: iters 0)
    report_image = with_image is not False and cfg.weights.image > 0 and (not image_in_loss(cfg) or by_cost)
    image = "k-space terms only" + (", the image for the report" if report_image else ", no image term")
    if by_cost and image_in_loss(cfg):
        image += " (the full-loss stage is not run: its image term has no windowed form; windowed: off runs it)"
    note = (
        f"{'long ' if ir.duration_s > cfg.window_auto_s else ''}sequence ({ir.duration_s:.3g} s; {rule}): optimized "
        f"one excitation period at a time, history {horizon * 1e3:.3g} ms / lookahead {lookahead * 1e3:.3g} ms "
        f"(hardware memory {causal * 1e3:.3g} / {acausal * 1e3:.3g} ms); {image} (docs/optimize.md)"
    )
    return {
        "horizon_s": horizon,
        "lookahead_s": lookahead,
        "memory_s": [causal, acausal],
        "note": note,
        "sizes": sizes,
        "by_cost": by_cost,
    }


def window_sizes(ir, free, horizon_s: float, lookahead_s: float) -> dict:
    """The windowed plan's sizes for :func:`dtoc.util.cost.optimize_cost`: windows, the most free variables and the
    most fine samples of one window."""
    from dtoc.optimize.windowed import core_free_counts, plan_windows

    ws = plan_windows(ir, horizon_s, lookahead_s, free)
    be = ir.block_edges_s
    return {
        "n_windows": len(ws),
        "max_free": int(core_free_counts(ir, free).max()),
        "max_fine": int(max(be[w.sub[1]] - be[w.sub[0]] for w in ws) / ir.dt_fine_s) + 1 if ws else 0,
    }


# ---------------------------------------------------------------------------------------------------
# checkpoints
# ---------------------------------------------------------------------------------------------------
def save_checkpoint(path, edges, it: int, stage: str, history: list, config: OptimizeConfig, force=True) -> Path:
    """Atomic ``.npz`` checkpoint: edges (3, N+1) mT/m, iteration, stage, history, config JSON."""
    import io

    buf = io.BytesIO()
    e = edges.detach().cpu().numpy() if isinstance(edges, torch.Tensor) else np.asarray(edges)
    np.savez(
        buf,
        edges_mT_per_m=e,
        it=np.int64(it),
        stage=np.array(stage),
        history=np.array(json.dumps(history)),
        config=np.array(config.model_dump_json()),
    )
    return atomic_write_bytes(path, buf.getvalue(), force=force)


def load_checkpoint(path, n_edges: int) -> dict:
    """Read a checkpoint written by :func:`save_checkpoint` (InputError when unusable)."""
    p = Path(path)
    try:
        with np.load(p, allow_pickle=False) as z:
            edges = np.asarray(z["edges_mT_per_m"], dtype=np.float64)
            out = {
                "edges": edges,
                "it": int(z["it"]),
                "stage": str(z["stage"]),
                "history": json.loads(str(z["history"])),
            }
    except FileNotFoundError:
        raise InputError(f"{p}: checkpoint not found") from None
    except Exception as e:  # noqa: BLE001
        raise InputError(f"{p}: not a dtoc optimize checkpoint ({type(e).__name__})") from None
    if edges.shape != (3, n_edges):
        raise InputError(
            f"{p}: key 'edges_mT_per_m' has shape {edges.shape}, expected (3, {n_edges}) for this sequence"
        )
    return out


def require_hardware(girf, model, ideal: bool) -> None:
    """A hardware model is never silently ideal: --girf or --model, or an explicit --ideal (not both)."""
    if ideal and (girf is not None or model is not None):
        raise InputError("give --ideal or a hardware model (--girf / --model), not both")
    if not ideal and girf is None and model is None:
        raise InputError("no hardware model: give --girf or --model, or --ideal to optimize for ideal hardware")


def check_run_paths(
    base,
    out,
    manifest_path,
    png_path,
    force,
    girf,
    model,
    config_path,
    resume,
    checkpoint,
    trajectory=None,
    other_inputs: dict | None = None,
) -> None:
    """Refuse, before any work, outputs that exist (without ``force``), coincide, or resolve to an input (any
    ``force``); the checkpoint may be the file resumed from, never the base, a model or another output.
    ``other_inputs``: {option: path} of further inputs (e.g. a scanner profile and the files it names)."""
    inputs = {"BASE": base, "--girf": girf, "--model": model, "--config": config_path, **(other_inputs or {})}
    check_outputs(
        {"-o": out, "--json": manifest_path, "--png": png_path, "--trajectory": trajectory},
        {**inputs, "--resume": resume, "--checkpoint": checkpoint},
        force,
    )
    check_outputs({"--checkpoint": checkpoint}, inputs, True)


# ---------------------------------------------------------------------------------------------------
# main entry
# ---------------------------------------------------------------------------------------------------
@dataclass
class RunOutputs:
    manifest: dict
    ir_out: SequenceIR
    figures: dict


def optimize_sequence(
    base,
    *,
    out=None,
    girf=None,
    model=None,
    config: OptimizeConfig | None = None,
    config_path=None,
    manifest_path=None,
    png_path=None,
    force: bool = False,
    resume=None,
    checkpoint_path=None,
    device: str = "cpu",
    phantom=None,
    progress: Callable | None = None,
    hardware=None,
    with_image: bool | None = None,
    base_path=None,
    ideal: bool = False,
    trajectory_path=None,
    orientation=None,
    limit_sources: dict | None = None,
    scanner_path=None,
    safety=None,
    offset_m=None,
    format_version: str | None = None,
    notes: Callable | None = None,
) -> RunOutputs:
    """Run `dtoc optimize` (see the module doc).

    Args:
        base: base sequence (``.seq`` path, spec ``.yaml`` path, or a SequenceIR).
        out / manifest_path / png_path: outputs (None: not written).
        girf / model: hardware model files (``--girf`` / ``--model``); ``hardware`` overrides both
            with a ready callable.
        config: :class:`OptimizeConfig` (default: built from ``config_path`` and the sequence kind).
        resume: checkpoint to continue from.  checkpoint_path: where to save checkpoints (default:
            ``<out>.ckpt.npz`` on Ctrl-C only).
        phantom: a :class:`~dtoc.sim.phantom.Phantom` or a phantom spec (see :func:`make_phantoms`);
            None = the built-in head 'brain'.
        with_image: simulate images (default: when the image weight is > 0 or for reporting).
        ideal: optimize for ideal hardware (required when neither ``girf``, ``model`` nor ``hardware`` is given).
        trajectory_path: write the realized-trajectory side-car here (:mod:`dtoc.optimize.sidecar`; None: not written).
        orientation: (3, 3) logical -> physical rotation the file will be played at
            (:mod:`dtoc.hardware.orientation`; None = transverse, the file's axes are the scanner's).
        limit_sources: where limits given in ``config`` came from, when not the command line (e.g. a profile).
        scanner_path: the scanner profile the limits / model came from (recorded in the manifest).
        safety: PNS and acoustic checks the output must pass (:class:`dtoc.seq.check.SafetyChecks`; their
            rotation is set to ``orientation``).
        offset_m: (3,) physical off-centre position of the slice / FOV, m: the interpreter's FOV-shift phase is
            corrected per ADC event as far as the format allows (:mod:`dtoc.optimize.offcentre`).
        format_version: Pulseq format of the output (default: the base file's; :func:`dtoc.seq.write.preflight_write`
            writes the base in it and reads it back before any work).
        notes: ``notes(line)`` receives the cost estimate of a long run before the work (:mod:`dtoc.util.cost`).
    Returns:
        :class:`RunOutputs` (manifest dict, output IR, arrays for plots).
    """
    t_start = time.time()
    io = RunIO(
        out=out,
        manifest_path=manifest_path,
        png_path=png_path,
        force=force,
        resume=resume,
        checkpoint_path=checkpoint_path,
        trajectory_path=trajectory_path,
        base_path=base_path if base_path is not None else base,
        girf=girf,
        model=model,
        config_path=config_path,
        scanner_path=scanner_path,
        safety=safety,
        offset_m=offset_m,
        format_version=format_version,
        notes=notes,
    )
    plan = plan_run(
        base, io, config=config, hardware=hardware, ideal=ideal, device=device, phantom=phantom,
        with_image=with_image, orientation=orientation, limit_sources=limit_sources,
    )  # fmt: skip
    sol = start_solution(plan, io)
    report = _reporter(progress)
    try:  # an interrupt between or inside the stages keeps the best-so-far (each stage keeps its own)
        sol.x = warm_start_stage(plan, sol, report)
        if not sol.final:
            sol.x = full_loss_stage(plan, sol, io, report)
        if not sol.final or plan.window is not None:  # a windowed solve's image kept for the report: discarding too
            discard_stage(plan, sol)
    except KeyboardInterrupt:
        sol.state.interrupted = True
        if sol.x is None:
            sol.x = sol.state.best_edges.detach().clone()
    return export_stage(plan, sol, io, t_start)


# ---------------------------------------------------------------------------------------------------
# the stages: plan -> warm start -> full loss -> discard -> export
# ---------------------------------------------------------------------------------------------------
@dataclass
class RunIO:
    """What one run reads besides the base and where its outputs go (checked before any work)."""

    out: Any = None
    manifest_path: Any = None
    png_path: Any = None
    force: bool = False
    resume: Any = None
    checkpoint_path: Any = None
    trajectory_path: Any = None
    base_path: Any = None
    girf: Any = None
    model: Any = None
    config_path: Any = None
    scanner_path: Any = None
    safety: SafetyChecks | None = None
    offset_m: Any = None
    format_version: str | None = None  # Pulseq format of the output (None: the base's)
    notes: Callable | None = None  # notes(line): the run's estimate for a long file (dtoc.util.cost)


@dataclass
class Plan:
    """The output of :func:`plan_run`: everything the stages read, fixed for the run.

    ``limits``: the logical-axis limits the waveform is held to (``phys_limits``: the physical ones they came
    from); ``free``: (3, N+1) optimizable edges; ``window``: the period-by-period plan (None: whole);
    ``n_wave``: the fine samples of the report's waveform panel kept (None: all); ``before``: the base's figures.
    """

    ir: SequenceIR
    cfg: OptimizeConfig
    hardware: Any
    R: np.ndarray | None
    limits: Limits
    phys_limits: Limits
    limit_sources: dict
    free: np.ndarray
    projector: EdgeProjector
    twin: EdgeTwin
    ctx: Any
    imager: Imager | None
    window: dict | None
    with_image: bool
    phantom: Any
    warnings: list
    dtype: torch.dtype
    device: str
    n_wave: int | None
    before: dict


@dataclass
class Solution:
    """The stages' running result: the edges ``x`` (None before the first stage), the kept samples and their
    threshold, the optimizer state, times, the manifest's extra records, and where a checkpoint goes."""

    state: O.StageState
    keep: np.ndarray
    x: torch.Tensor | None = None
    thr: float = math.inf
    start_it: int = 0
    final: bool = False  # preemphasis / windowed: no full-loss stage and no discarding
    stage_times: dict = dataclasses.field(default_factory=dict)
    extra: dict = dataclasses.field(default_factory=dict)
    resumed_from: dict | None = None
    ckpt_target: Any = None
    window_stats: Any = None  # the windowed solve's WindowStats (its report is made on the exported waveform)


def plan_run(
    base, io: RunIO, *, config=None, hardware=None, ideal=False, device="cpu", phantom=None, with_image=None,
    orientation=None, limit_sources=None,
) -> Plan:  # fmt: skip
    """Stage 1: check the paths, read the base, resolve config, hardware, limits, variables, twin, loss context,
    windowing and imager, and evaluate the base (one-line InputError / LimitError on bad input, nothing written)."""
    from dtoc.optimize.config import load_config
    from dtoc.seq.load import load_sequence

    check_run_paths(
        base if isinstance(base, (str, os.PathLike)) else None,
        io.out,
        io.manifest_path,
        io.png_path,
        io.force,
        io.girf,
        io.model,
        io.config_path,
        io.resume,
        io.checkpoint_path,
        io.trajectory_path,
    )
    if isinstance(base, (str, os.PathLike)):
        bp = Path(base)
        if not bp.exists():
            raise InputError(f"{bp}: base sequence not found")
        ir = load_sequence(bp)
    else:
        ir = base
    if not ir.adc:
        raise InputError(
            f"{base if isinstance(base, (str, os.PathLike)) else 'sequence'}: has no ADC event: nothing to optimize for"
        )
    if io.out is not None:  # timing rules the output would inherit (cheap); its format's pre-flight: after the cost
        version_in = ir.meta.get("format_version") or "1.5.0"
        why = None if ir.source is None else base_timing_refusal(ir.source, version_in, ir.meta.get("path"))
        if why:  # a rule the output would inherit unchanged: refused now, not after the optimization
            raise InputError(f"{base if isinstance(base, (str, os.PathLike)) else io.base_path or 'sequence'}: {why}")
        check_writable(output_version(ir, io.format_version))  # a version dtoc does not write: by name, now
    cfg = config if config is not None else load_config(ir.kind, io.config_path)
    O.set_deterministic(cfg.seed, cfg.threads, device)
    if hardware is None:
        from dtoc.hardware.model import resolve_model

        require_hardware(io.girf, io.model, ideal)
        hardware = resolve_model(girf=io.girf, model=io.model)
    R = None if orientation is None else np.asarray(orientation, dtype=np.float64)
    if R is not None:
        from dtoc.hardware.orientation import RotatedChain

        hardware = RotatedChain(hardware, R)  # the model acts on the physical axes
    if hasattr(hardware, "frozen"):
        hardware = hardware.frozen()  # the model is fixed here: no parameter gradients, cached GIRF spectra
    if torch.device(device).type != "cpu" and hasattr(hardware, "to"):
        hardware = hardware.to(device)  # its parameters on the device once, not copied there at every evaluation
    limits, sources = limits_and_sources(ir, cfg)
    limit_sources = {**sources, **(limit_sources or {})}
    phys_limits = limits
    limits = limits.rotated(R)  # oblique: the limits hold on the physical axes too (dtoc.optimize.limits)
    if limits.rotation is not None:
        limit_sources = {k: f"{v}, on the physical and the logical axes (oblique)" for k, v in limit_sources.items()}
    free = free_edges(ir)
    if not free.any():
        raise InputError(
            "nothing to optimize: every gradient sample is held (inside RF blocks, on the slice-select axis, in "
            "soft-delay blocks, or on axes that play no gradient)"
        )
    # the cost decision from sizes alone (the IR, the free mask, the window plan), before the reachability check
    # (nominal k over the whole sequence), the projector, the twin, the loss context, the phantoms and the
    # simulations are built: a run that cannot fit fails in seconds
    from dtoc.sim.phantom import check_phantom_matches

    # a given phantom of the wrong dimension: one line, never ignored
    phantom_3d = phantom is not None and check_phantom_matches(ir, phantom)
    if with_image is None and ir.meta.get("grid3d") is not None:
        # a 3D-encoded sequence: the image term when a 3D phantom is given (then not windowed), else k-space only
        with_image = phantom_3d
    window = window_plan(ir, hardware, cfg, free, with_image)
    phantoms, graph, image_reason = None, None, None  # the report image's, when its cost was estimated from its graph
    if window is not None and image_in_loss(cfg):  # period by period, k-space terms only: no full loss to use it
        if with_image:
            raise InputError(
                "a windowed (long-sequence) optimization has no image term; give windowed: off in --config"
            )
        if window.get("by_cost"):  # windowed by the cost rule: no full-loss stage, the image for the report only
            cfg = cfg.model_copy(update={"iters": 0})
        else:
            with_image = False
    if with_image is None:
        with_image = ir.geometry is not None  # no grid (non-Cartesian): the k-space term alone
        if with_image and window is not None and cfg.weights.image <= 0:
            with_image = False  # windowed and no image weight: k-space only (the way to skip the report's simulation)
        elif with_image and window is not None:  # the image for the report only: dropped, not refused, if it cannot fit
            try:
                check_run_cost(ir, cfg, free, window, True, str(io.base_path or "sequence"))
            except InputError as e:
                with_image = False
                if io.notes is not None:
                    io.notes(f"no image for the report (k-space figures only): {e}")
            else:  # its simulation from the graph's emitting states: an unspoiled steady state's are many
                phantoms = make_phantoms(ir, cfg, phantom)
                graph, image_reason = report_image_reason(ir, cfg, phantoms)
                if image_reason is not None:
                    with_image, phantoms, graph = False, None, None
                    if io.notes is not None:
                        io.notes(f"no image for the report (k-space figures only): {image_reason}")
    if not with_image:
        cfg = cfg.model_copy(update={"weights": cfg.weights.model_copy(update={"image": 0.0})})
    whole_why = None  # a long sequence solved whole: why (the refusal's way out must not offer the windowed solve)
    if window is None and ir.duration_s > cfg.window_auto_s and not with_image and cfg.windowed != "off":
        whole_why = why_not_windowed(ir, hardware, cfg, free)
    check_run_cost(ir, cfg, free, window, with_image, str(io.base_path or "sequence"), io.notes, whole_why)
    check_area_reachable(ir, limits)
    base_extremes = waveform_extremes(ir.grad_mT_per_m, ir.dt_fine_s)  # one pass: the refusal and the warnings
    held_limit_refusal(ir, free, limits, base_extremes)
    if io.out is not None:  # the base written in the output's format and read back: once the run is known to fit
        ir.meta["output_format_version"] = version_str(preflight_write(ir, io.format_version))
    projector = EdgeProjector(ir.edge_grad_mT_per_m, free, ir.raster_s, limits)
    warnings_out = base_limit_warnings(ir, limits, base_extremes) + base_physical_warnings(
        ir.grad_mT_per_m, ir.dt_fine_s, limits
    )
    dtype = torch.float64
    twin = EdgeTwin(ir, hardware, projector, dtype=dtype, device=device)
    ctx = L.build_context(ir, limits, dtype=dtype, device=device)
    imager = None
    if with_image:
        phantoms = phantoms or make_phantoms(ir, cfg, phantom)
        imager = O.memo_signal(Imager(ir, phantoms, n_dummies=cfg.n_dummies, dtype=dtype, device=device, graph=graph))

    # a long (windowed) sequence keeps only the report's span of its whole-sequence waveforms
    n_wave = None if window is None else plotted_span(ir)[0]
    before = quality(twin, imager, ctx, ir.grad_mT_per_m, waveform_samples=n_wave)
    if image_reason is not None:  # a figure that is not computed: its reason, never a number
        before["image_reason"] = image_reason
    fault_point("setup")
    return Plan(
        ir, cfg, hardware, R, limits, phys_limits, limit_sources, free, projector, twin, ctx, imager, window,
        bool(with_image), phantom, warnings_out, dtype, device, n_wave, before,
    )  # fmt: skip


def held_limit_refusal(ir, free: np.ndarray, limits: Limits, extremes: dict | None = None) -> None:
    """One-line InputError, before any work, when the base itself exceeds the slew or amplitude limit where dtoc may
    not change it (a fine segment between two held raster edges: inside RF blocks, on the slice-select axis, at held
    block boundaries), e.g. a base's step between two blocks beyond smax x raster: its output would too, and dtoc
    never writes beyond the limits (the projection could only fail at export).  ``extremes``: the base's
    :func:`waveform_extremes` (within the limits everywhere: nothing to look for); the waveform is read in pieces of
    :data:`~dtoc.optimize.limits.EXTREMES_CHUNK` fine samples, no whole-length temporaries."""
    from dtoc.optimize.limits import EXTREMES_CHUNK

    ext = extremes if extremes is not None else waveform_extremes(ir.grad_mT_per_m, ir.dt_fine_s)
    g_lim, s_lim = limits.gmax_mT_per_m * (1 + 1e-6), limits.smax_T_per_m_per_s * (1 + 1e-6)
    if max(ext["gmax_mT_per_m"]) <= g_lim and max(ext["smax_T_per_m_per_s"]) <= s_lim:
        return
    g = np.asarray(ir.grad_mT_per_m, dtype=np.float64)
    held = ~np.asarray(free, dtype=bool)  # (3, N+1) raster edges; fine segment j depends on edges j // 2, j // 2 + 1
    # per axis, the largest value beyond the limit and its first index: fine segment (slew), raster edge (amplitude)
    worst_s, at_s = np.full(3, -1.0), np.zeros(3, dtype=np.int64)
    worst_g, at_g = np.full(3, -1.0), np.zeros(3, dtype=np.int64)
    n_seg = g.shape[1] - 1
    for s0 in range(0, max(n_seg, 0), EXTREMES_CHUNK):
        k = np.arange(s0, min(s0 + EXTREMES_CHUNK, n_seg))
        j = k // 2
        seg = held[:, j] & held[:, np.minimum(j + 1, held.shape[1] - 1)]
        slew = np.abs(np.diff(g[:, s0 : k[-1] + 2], axis=1)) / ir.dt_fine_s * 1e-3  # T/m/s
        worst_s, at_s = _keep_worst(worst_s, at_s, np.where(seg & (slew > s_lim), slew, -1.0), k)
    ge = ir.edge_grad_mT_per_m  # amplitude on the held raster edges themselves: a fine midpoint next to a free edge
    for e0 in range(0, ge.shape[1], EXTREMES_CHUNK):  # is not held
        e = np.arange(e0, min(e0 + EXTREMES_CHUNK, ge.shape[1]))
        amp = np.abs(np.asarray(ge[:, e], dtype=np.float64))
        worst_g, at_g = _keep_worst(worst_g, at_g, np.where(held[:, e] & (amp > g_lim), amp, -1.0), e)
    if worst_s.max() < 0 and worst_g.max() < 0:
        return
    edges = np.asarray(ir.block_edges_s)
    ids = ir.meta.get("block_ids") or list(range(1, len(edges)))
    if worst_s.max() >= 0:
        a = int(np.argmax(worst_s))
        m = int(at_s[a])
        what = f"{worst_s[a]:.4g} T/m/s, above smax {limits.smax_T_per_m_per_s:g}"
    else:
        a = int(np.argmax(worst_g))
        m = 2 * int(at_g[a])  # the edge's fine sample
        what = f"{worst_g[a]:.4g} mT/m, above gmax {limits.gmax_mT_per_m:g}"
    b = int(np.clip(np.searchsorted(edges, m * ir.dt_fine_s, side="right") - 1, 0, len(ids) - 1))
    raise InputError(
        f"the base itself needs {what} on {AXES[a]} at {m * ir.dt_fine_s * 1e3:.4f} ms (block {ids[b]}), where dtoc "
        "may not change the waveform (RF blocks, the slice-select axis, held block boundaries): its output would "
        "too, and dtoc never writes beyond the limits; correct the base (e.g. a step between blocks: at most smax x "
        "the gradient raster) or give limits it meets"
    )


def _keep_worst(worst: np.ndarray, at: np.ndarray, v: np.ndarray, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per axis, the running largest of ``worst`` and this piece's values ``v`` (3, n) and where it is (``at``, the
    piece's indices ``idx``): the first occurrence is kept on ties."""
    i = np.argmax(v, axis=1)
    best = v[np.arange(3), i]
    better = best > worst
    return np.where(better, best, worst), np.where(better, idx[i], at)


def report_image_reason(ir, cfg: OptimizeConfig, phantoms: list) -> tuple[Any, str | None]:
    """The graph of the report image's simulation (a windowed run: the image is for the report only) and why it is
    not simulated, or None: its estimate from the graph's emitting states (:func:`dtoc.util.cost.emission_cost`;
    the base's and every phantom's target, the base, the discarding and the output: 3 + phantoms simulations) above
    :data:`dtoc.util.cost.REPORT_IMAGE_MAX_SECONDS` or beyond the memory available."""
    from dtoc.sim.pdg import PDGConfig, build_graph
    from dtoc.util.cost import FIT_FRACTION, PROCESS_BYTES, REPORT_IMAGE_MAX_SECONDS, emission_cost
    from dtoc.util.validate import available_memory_bytes, gib

    graph = build_graph(ir, PDGConfig(), phantoms[0])
    vox = int(np.asarray(phantoms[0].pd).size)
    mem, sec, per = emission_cost(graph, vox, len(phantoms), n_runs=1)
    sec *= (3 + len(phantoms)) / len(phantoms)
    fits = PROCESS_BYTES + mem <= FIT_FRACTION * available_memory_bytes()
    if sec <= REPORT_IMAGE_MAX_SECONDS and fits:
        return graph, None
    beyond = [f"the report image's {REPORT_IMAGE_MAX_SECONDS:.0f} s"] if sec > REPORT_IMAGE_MAX_SECONDS else []
    beyond += [] if fits else [f"{FIT_FRACTION:.0%} of the memory available"]
    return None, (
        f"its simulation ({vox} voxels; {per:.3g} signal pathways emit at each ADC sample on average) needs "
        f"~{sec:.0f} s or more and about {gib(PROCESS_BYTES + mem)} (estimate, beyond {' and '.join(beyond)}): image "
        "figures not computed; a smaller phantom (phantom_size in --config) may fit"
    )


def check_run_cost(
    ir, cfg: OptimizeConfig, free, window: dict | None, with_image: bool, name: str, notes=None, whole_why=None
):
    """The run's memory and time from its sizes (:func:`dtoc.util.cost.check_optimize_cost`), before any work:
    the windowed plan's window sizes (windows, the most free variables and fine samples of one window) or the
    whole solve, and the image term's simulation with its dummy train; one line refused, one noted."""
    from dtoc.util.cost import check_optimize_cost, dummy_cost, fine_per_repetition, simulation_cost

    sizes = None
    if window is not None:
        sizes = window.get("sizes") or window_sizes(ir, free, window["horizon_s"], window["lookahead_s"])
    sim = (0.0, 0.0)
    geo = getattr(ir, "geometry", None)
    if with_image and geo is not None:
        vox = cfg.phantom_size**2 if cfg.phantom_size else int(geo.matrix_xy[0]) * int(geo.matrix_xy[1])
        n_ph = 1 + cfg.augment_rotations
        mem, sec = simulation_cost(vox, ir.n_adc_samples, n_ph, n_runs=2 * max(cfg.iters, 1))
        dmem, dsec = dummy_cost(cfg.n_dummies, fine_per_repetition(ir), vox)
        sim = (max(mem, dmem), sec + dsec * n_ph)
    check_optimize_cost(f"{name}: optimize", ir.grad_mT_per_m.shape[1], ir.n_adc_samples, sizes, sim, notes, whole_why)


def start_solution(plan: Plan, io: RunIO) -> Solution:
    """The stages' starting state: the base edges as best-so-far, or the checkpoint resumed from."""
    sol = Solution(
        state=O.StageState(best_edges=plan.twin.base_edges()),
        keep=np.ones(plan.ir.n_adc_samples, dtype=bool),
        # the default checkpoint never replaces an unrelated file (a free name beside it)
        ckpt_target=io.checkpoint_path
        or (None if io.out is None else unused_path(str(io.out) + ".ckpt.npz", keep=io.resume)),
    )
    if io.resume is not None:
        ck = load_checkpoint(io.resume, plan.projector.n_edges)
        sol.x = plan.projector.project(torch.as_tensor(ck["edges"], dtype=plan.dtype))
        sol.start_it = ck["it"] if ck["stage"] == "full" else 0
        sol.state.history = list(ck["history"])
        sol.resumed_from = {
            "path": str(io.resume),
            "sha256": sha256_file(io.resume),
            "stage": ck["stage"],
            "iteration": ck["it"],
        }
    return sol


def _reporter(progress: Callable | None) -> Callable:
    def report(stage, it, n, loss):
        fault_point({"warm": "warm_start", "full": "full_loss"}.get(stage, stage))
        if progress is not None:
            progress(stage, it, n, loss)

    return report


def warm_start_stage(plan: Plan, sol: Solution, report: Callable) -> torch.Tensor:
    """Stage 2: the starting waveform: pre-emphasis (``--method preemphasis``: final), the period-by-period solve
    of a long sequence (final), the robust linear warm start (dto / warmstart), or the projected base; a resumed
    checkpoint is kept as it is."""
    cfg, ir, stage_times, extra = plan.cfg, plan.ir, sol.stage_times, sol.extra
    if cfg.method == "preemphasis":
        from dtoc.optimize import preemphasis as PE

        t0 = time.time()
        pe = PE.run_preemphasis(ir, plan.twin, plan.ctx, plan.imager, plan.limits)
        stage_times["preemphasis_s"] = time.time() - t0
        sol.keep = pe["keep_mask"]
        extra["preemphasis"] = pe["report"]
        sol.final = True
        return torch.as_tensor(pe["edges"], dtype=plan.dtype)
    if plan.window is not None:
        from dtoc.optimize.windowed import windowed_warm_start

        window = plan.window
        t0 = time.time()
        e, wst = windowed_warm_start(
            ir,
            plan.hardware,
            plan.limits,
            plan.free,
            cfg.weights,
            plan.ctx,
            horizon_s=window["horizon_s"],
            lookahead_s=window["lookahead_s"],
            dtype=plan.dtype,
            device=plan.device,
            progress=report,
            k_tol_dk=cfg.k_tol_dk,
        )
        stage_times["windowed_s"] = time.time() - t0
        extra["windowed"] = {"note": window["note"], "memory_s": window["memory_s"], **wst.as_dict()}
        sol.window_stats = wst
        sol.final = True  # no full-loss stage (the discarding still runs when the image is kept: optimize_sequence)
        return torch.as_tensor(e, dtype=plan.dtype, device=plan.device)
    if sol.x is not None:
        return sol.x
    if cfg.method not in ("dto", "warmstart"):
        return plan.projector.project(plan.twin.base_edges())
    t0 = time.time()
    solves: list = []
    x = O.robust_warm_start(
        plan.twin,
        plan.ctx,
        cfg.weights,
        cfg.warm_iters,
        rounds=cfg.robust_rounds,
        scale_dk=cfg.robust_scale_dk,
        state=sol.state,
        progress=report,
        k_tol_dk=cfg.k_tol_dk,
        budget=cfg.solve_budget,
        reports=solves,
        minimax_rounds=cfg.minimax_rounds,
        minimax_budget=cfg.minimax_budget,
    )
    stage_times["warm_start_s"] = time.time() - t0
    if solves:
        extra["solver"] = solver_record(solves)
        certify_stop(plan, x, extra["solver"])
    return x


def full_loss_stage(plan: Plan, sol: Solution, io: RunIO, report: Callable) -> torch.Tensor:
    """Stage 3: the full loss through the simulator (dto / adam-paper, ``iters`` > 0), checkpointed to
    ``io.checkpoint_path`` every ``checkpoint_every`` iterations; otherwise the warm start unchanged."""
    cfg, state = plan.cfg, sol.state
    assert sol.x is not None
    if cfg.method not in ("dto", "adam-paper") or state.interrupted or cfg.iters <= 0:
        return sol.x

    def ckpt(edges, it):
        if io.checkpoint_path is not None:
            save_checkpoint(io.checkpoint_path, edges, it, "full", state.history, cfg)

    t0 = time.time()
    state.best_loss = math.inf
    opt_imager = loop_imager(plan.imager, cfg) if cfg.weights.image > 0 else None
    sol.stage_times["loop_imager_s"] = time.time() - t0
    x = O.full_loss(
        plan.twin,
        opt_imager,
        plan.ctx,
        cfg,
        sol.x,
        state,
        report,
        start_it=sol.start_it,
        paper=cfg.method == "adam-paper",
        checkpoint=ckpt,
    )
    sol.stage_times["full_loss_s"] = time.time() - t0
    return x


def discard_stage(plan: Plan, sol: Solution) -> None:
    """Stage 4: the post-hoc discarding threshold (``sol.keep``, ``sol.thr``) when an image is simulated."""
    if plan.cfg.discard and plan.imager is not None and not sol.state.interrupted:
        t0 = time.time()
        assert sol.x is not None
        sol.keep, sol.thr, _ = O.choose_discard(plan.twin, plan.imager, plan.ctx, sol.x, floor_dk=plan.cfg.k_tol_dk)
        sol.stage_times["discard_s"] = time.time() - t0


def export_stage(plan: Plan, sol: Solution, io: RunIO, t_start: float) -> RunOutputs:
    """Stage 5: the final projection and verification, the figures, the manifest, and the outputs written
    together.  A signal stops the stage at once, nothing written (the outputs are staged in temporaries, which go
    with it), until the outputs are committed: during their renames it waits until they are complete, then exits
    130/143."""
    ir, cfg, twin, ctx, imager, limits = plan.ir, plan.cfg, plan.twin, plan.ctx, plan.imager, plan.limits
    state, keep, thr, extra, R, free = sol.state, sol.keep, sol.thr, sol.extra, plan.R, plan.free
    before, warnings_out = plan.before, plan.warnings
    assert sol.x is not None
    commit = deferred(held=False)  # a signal waits only while the outputs are committed (commit.hold() below)
    with commit:
        # final projection (feasible by construction) and verification
        x = plan.projector.project(sol.x, n_iter=60, exact=True)
        sol.x = x  # the solution is the projected edges from here on (the unprojected ones released: 12 B per sample)
        fine = twin.export_fine(x)
        viol = limit_violations(fine, ir.dt_fine_s, limits)
        if viol:
            raise LimitError(f"internal: projected waveform violates limits ({viol[0]}); nothing written")
        ir_out = ir.with_grad(fine)
        _check_system_limits(ir_out, limits)
        # the exported waveform itself (bit for bit what twin.played(x) gives): no second whole-sequence copy
        after = quality(twin, imager, ctx, fine, keep_mask=keep, waveform_samples=plan.n_wave)
        if imager is None and before.get("image_reason"):
            after["image_reason"] = before["image_reason"]
        if sol.window_stats is not None:  # what the windowed solve achieved against the tolerance, named
            extra["solver"] = windowed_solver_record(plan, x, fine, sol.window_stats)
        if state.interrupted and sol.ckpt_target is not None:
            done = max([h["it"] for h in state.history if h.get("stage") == "full"] or [sol.start_it])
            save_checkpoint(sol.ckpt_target, x, done, "full", state.history, cfg, force=True)
            extra["checkpoint"] = str(sol.ckpt_target)
        if sol.resumed_from is not None:
            extra["resumed_from"] = sol.resumed_from
        adc_offsets = None
        if io.offset_m is not None:
            from dtoc.optimize.offcentre import offcentre_correction
            from dtoc.seq.read import slice_axes

            if any(free[a].any() for a in slice_axes(ir)):
                raise InputError("--offset with a freed slice axis: the interpreter's RF frequency would be wrong")
            oc = offcentre_correction(ir, ir_out, before["_k"], after["_k"], io.offset_m, R)
            adc_offsets = {a.block: (float(p), float(f)) for a, p, f in zip(ir.adc, oc.adc_phase_rad, oc.adc_freq_hz)}
            extra["offcentre"] = {"offset_m": [float(x) for x in io.offset_m], **oc.summary()}
        nb, na = before.get("nrmse"), after.get("nrmse")
        if nb is not None and na is not None and na > nb * (1 + 1e-6) + 1e-9:  # not float noise (1e-13 % vs 0)
            warnings_out.append(
                f"the output's image NRMSE ({100 * na:.3g} %) is worse than the base's ({100 * nb:.3g} %): "
                "the limits or the model leave no better waveform; do not upload it without review"
            )

        manifest = {
            "dtoc_optimize": 1,
            "inputs": {
                **_inputs(io.base_path, io.girf, io.model, io.config_path, io.resume),
                "scanner": None
                if io.scanner_path is None
                else {"path": str(io.scanner_path), "sha256": sha256_file(io.scanner_path)},
            },
            "options": json.loads(cfg.model_dump_json()),
            "orientation": None if R is None else {"R_logical_to_physical": R.tolist(), "name": _orient_name(R)},
            "limits": {
                "physical_gmax_mT_per_m": plan.phys_limits.gmax_mT_per_m,
                "physical_smax_T_per_m_per_s": plan.phys_limits.smax_T_per_m_per_s,
                "gmax_mT_per_m": limits.gmax_mT_per_m,
                "smax_T_per_m_per_s": limits.smax_T_per_m_per_s,
                "amp_margin": limits.amp_margin,
                "slew_margin": limits.slew_margin,
                "source": plan.limit_sources,
            },
            "sequence": {
                "kind": ir.kind,
                "n_adc_samples": ir.n_adc_samples,
                "raster_s": ir.raster_s,
                "n_free_variables": int(free.sum()),
                "duration_s": ir.duration_s,
                "notes": list(ir.meta.get("notes", [])),
                "rf_use": ir.meta.get("rf_use"),  # per [RF] event: use and how decided (dtoc.seq.rfuse)
                "image_term": plan.with_image,
                "dk_rad_per_m": [float(x) for x in ctx.dk_rad_per_m.cpu().numpy()],
                "dk_source": "grid (2 pi / FOV)" if ir.dk_rad_per_m is not None else "sampling step of the readouts",
            },
            "versions": package_versions(),
            "device": str(plan.device),
            # on CUDA: the steps replayed as CUDA graphs in this process so far (dtoc.util.replay; docs/optimize.md)
            **({"cuda_graphs": replay_totals()} if str(plan.device).startswith("cuda") else {}),
            "phantom": _phantom_record(plan.phantom),
            "before": metrics.report_figures(before),
            "after": metrics.report_figures(after),
            "n_samples_discarded": int(np.sum(~keep)),
            "samples_discarded_percent": 100.0 * float(np.mean(~keep)),
            "discard_threshold_dk": None if not math.isfinite(thr) else thr,
            "discarded_sample_indices": np.flatnonzero(~keep).tolist(),
            "exported_extremes": _extremes(fine, ir.dt_fine_s),
            "limit_violations": 0,
            "loss_history": state.history,
            "interrupted": state.interrupted,
            "stage_times_s": sol.stage_times,
            "warnings": warnings_out,
            "run_time_s": None,
            **extra,
        }
        figures = {"before": before, "after": after, "keep": keep, "ir": ir, "imager": imager, "history": state.history}
        with outputs_together():  # the .seq, manifest, PNG and side-car appear together, or none of them
            if io.trajectory_path is not None:
                manifest["trajectory"] = _write_sidecar(
                    io.trajectory_path, ir, after, keep, ctx, io.girf or io.model, io.force
                )
            _write_outputs(
                ir_out,
                io.out,
                io.force,
                limits,
                manifest,
                io.manifest_path,
                io.png_path,
                figures,
                t_start,
                None if io.safety is None else dataclasses.replace(io.safety, rotation=R),
                adc_offsets,
            )
            commit.hold()  # the renames of outputs_together: from here on a signal waits until they are complete
            fault_point("export")
    return RunOutputs(manifest=manifest, ir_out=ir_out, figures=figures)


def _write_sidecar(path, ir, after: dict, keep, ctx, model_file, force: bool) -> dict:
    """The realized-trajectory side-car (:mod:`dtoc.optimize.sidecar`); its manifest record."""
    from dtoc.hardware.npzio import npz_bytes
    from dtoc.optimize.sidecar import sidecar_arrays
    from dtoc.sim.predict import b0_phase_at_adc_rad

    b0 = after.get("_b0")
    phase = after.get("_b0_phase_adc")  # streamed (a long sequence): the phase itself
    if phase is None:
        phase = np.zeros(ir.n_adc_samples) if b0 is None else b0_phase_at_adc_rad(ir, b0)
    sha = sha256_file(model_file) if isinstance(model_file, (str, os.PathLike)) else None
    arrays = sidecar_arrays(ir, after["_k"], phase, keep, ctx.dk_rad_per_m.cpu().numpy(), sha)
    data = npz_bytes(arrays)
    atomic_write_bytes(path, data, force=force)
    return {
        "path": str(path),
        "sha256": sha256_bytes(data),
        "n_samples": int(ir.n_adc_samples),
        "n_discarded": int(arrays["discarded"].sum()),
    }


def _write_outputs(
    ir_out,
    out,
    force,
    limits,
    manifest,
    manifest_path,
    png_path,
    figures,
    t_start,
    safety=None,
    adc_offsets=None,
) -> None:
    """The .seq (checked after writing), the manifest and the PNG report, in one :func:`outputs_together`."""
    if out is not None:
        definitions: dict = {"DtocInterrupted": 1} if manifest["interrupted"] else {}
        if manifest.get("orientation"):  # the orientation the file was compiled for (dtoc check --orientation)
            definitions["DtocOrientation"] = manifest["orientation"]["R_logical_to_physical"]
        base_sha = (manifest["inputs"].get("base") or {}).get("sha256")
        if base_sha:  # the base it was compiled from (--reference BASE verifies it; dtoc.sim.reference)
            definitions[BASE_HASH_DEFINITION] = base_sha
        manifest["output"] = write_checked(ir_out, out, force, limits, definitions, safety, adc_offsets)
        if manifest["output"]["check_inherited"]:
            manifest["warnings"].append(
                "the output keeps the base's own gradient steps (inherited: the base has each at the same block and "
                f"axis, not smaller, within the slew limit): {inherited_text(manifest['output']['check_inherited'])}"
            )
    manifest["run_time_s"] = time.time() - t_start
    if manifest_path is not None:
        atomic_write_text(manifest_path, strict_json(manifest), force=force)
    if png_path is not None:
        from dtoc.optimize.report import write_report_png

        write_report_png(png_path, figures, manifest, force=force)


def _orient_name(R) -> str:
    from dtoc.hardware.orientation import orientation_name

    return orientation_name(R)


def base_limit_warnings(ir, limits: Limits, extremes: dict | None = None) -> list[str]:
    """Warnings when the base sequence itself needs more amplitude or slew than the limits allow: the output
    then cannot reproduce the base's k-space (it is still written within the limits).  ``extremes``: the base's
    :func:`waveform_extremes`, if already computed."""
    ext = extremes if extremes is not None else waveform_extremes(ir.grad_mT_per_m, ir.dt_fine_s)
    out = []
    g, sl = max(ext["gmax_mT_per_m"]), max(ext["smax_T_per_m_per_s"])
    if g > limits.gmax_mT_per_m * (1 + 1e-6):
        out.append(
            f"the base sequence needs {g:.4g} mT/m, above gmax {limits.gmax_mT_per_m:g} mT/m: "
            "the output cannot follow its k-space everywhere"
        )
    if sl > limits.smax_T_per_m_per_s * (1 + 1e-6):
        out.append(
            f"the base sequence needs {sl:.4g} T/m/s, above smax {limits.smax_T_per_m_per_s:g} T/m/s "
            f"({sl / limits.smax_T_per_m_per_s:.3g}x): the output cannot follow its k-space everywhere"
        )
    return out


def loop_imager(imager, cfg: OptimizeConfig):
    """The imager of the full-loss loop: ``cfg.sim_preset`` / ``cfg.sim_dtype`` (shares phantoms and steady state)."""
    if imager is None or (cfg.sim_preset == "default" and cfg.sim_dtype == "float64"):
        return imager
    from dtoc.sim.pdg import PDGConfig

    presets: dict[str, Callable[[], PDGConfig]] = {
        "fast": PDGConfig.fast,
        "default": PDGConfig,
        "strict": PDGConfig.strict,
    }
    preset = presets[cfg.sim_preset]()
    return imager.with_config(preset, {"float32": torch.float32, "float64": torch.float64}[cfg.sim_dtype])


def _extremes(fine, dt):
    return waveform_extremes(fine, dt)


def _check_system_limits(ir_out: SequenceIR, limits: Limits) -> None:
    """The validator's IR limit check (per axis and vector) before anything is written."""
    sysspec = SystemSpec(
        max_grad_mT_per_m=limits.gmax_mT_per_m,
        max_slew_T_per_m_per_s=limits.smax_T_per_m_per_s,
        grad_raster_s=ir_out.raster_s,
    )
    v = [x.message for x in check_ir_limits(ir_out, sysspec)]
    v += physical_violations(ir_out.grad_mT_per_m, ir_out.dt_fine_s, limits)  # what the scanner checks (oblique)
    if v:
        raise LimitError(f"exported waveform fails the validator: {v[0]}; nothing written")


def write_checked(
    ir_out: SequenceIR,
    out,
    force: bool,
    limits: Limits,
    definitions: dict | None = None,
    safety: SafetyChecks | None = None,
    adc_offsets=None,
) -> dict:
    """Write via the seq writer (Pulseq format ``ir_out.meta['output_format_version']``, default the base's) into
    a temporary file, validate it, then move it into place.
    ``definitions``: extra [DEFINITIONS] entries (e.g. ``DtocInterrupted 1`` on a best-so-far)."""
    outp = Path(out)
    version = ir_out.meta.get("output_format_version")
    with tempfile.TemporaryDirectory(dir=outp.parent if str(outp.parent) else ".") as d, shared_parse():
        tmp = Path(d) / outp.name
        write_seq_text(ir_out, tmp, definitions, adc_offsets, version)  # a private folder; never whole in memory
        sysspec = SystemSpec(
            max_grad_mT_per_m=limits.gmax_mT_per_m,
            max_slew_T_per_m_per_s=limits.smax_T_per_m_per_s,
            grad_raster_s=ir_out.raster_s,
            block_raster_s=_block_raster(ir_out),
        )
        # read back (it plays ir_out) and checked (the format's rules and the limits, as given) on one parse and one
        # reading of each piece of the text (a long text in pieces: its parse and reading are ~570 bytes per raster
        # step), with the whole check's result (dtoc.seq.write.verify_and_check)
        lim_rules = {"grad_amplitude", "slew_rate", "grad_vector", "slew_vector", "pns", "acoustic"}
        settled: list = []

        def judge(res) -> None:
            bad = [v for v in res.violations if v.rule in lim_rules]
            if bad:
                raise ValidationFailed(f"written file fails dtoc check: {bad[0].message}; nothing written")
            settled.append(settle_inherited(res, ir_out.source, sysspec))  # the base's steps: reported; new: raise

        v_out = output_version(ir_out, version)
        res = verify_and_check(ir_out, tmp, v_out, sysspec, safety, check_file_pieces, judge)
        inherited = settled[0]
        result: dict[str, Any] = {
            "path": str(outp),
            "check_ok": res.ok,
            "check_other_rules": sorted(res.rules() - lim_rules),
            "format_version": version_str(v_out),
            "check_failed": res.summary() if not res.ok else None,  # by kind, with the worst values
            "checks": list(res.checks),
            "check_not_checked": list(res.not_checked),
            "check_inherited": inherited,  # the base's own steps the output keeps (dtoc.seq.check.settle_inherited)
        }
        result["sha256"] = sha256_file(tmp)
        atomic_move_file(tmp, outp, force=force)  # (the text is not read whole: a long sequence's is ~300 MB)
    return result


def _block_raster(ir) -> float:
    v: Any = (ir.definitions or {}).get("BlockDurationRaster")
    try:
        return float(v[0] if isinstance(v, (list, tuple)) else v)
    except (TypeError, ValueError):
        return ir.raster_s


def _inputs(base, girf, model, config_path, resume) -> dict:
    out = {}
    for key, p in (("base", base), ("girf", girf), ("model", model), ("config", config_path), ("resume", resume)):
        if p is None or not isinstance(p, (str, os.PathLike)):
            out[key] = None if p is None else {"path": "<in-memory>", "sha256": None}
            continue
        out[key] = {"path": str(p), "sha256": sha256_file(p)}
    return out


def _phantom_record(phantom) -> dict:
    """What the manifest says of the phantom: a built-in spec, a file (with sha256) or an in-memory object."""
    from dtoc.sim.phantom import Phantom, is_builtin_spec

    if phantom is None:
        return {"builtin": "brain"}
    if isinstance(phantom, Phantom):
        return {"builtin": None, "path": "<in-memory>"}
    spec = str(phantom)
    if is_builtin_spec(spec):
        return {"builtin": spec}
    return {"builtin": None, "path": spec, "sha256": sha256_file(spec)}
