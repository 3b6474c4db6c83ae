"""Certificates of unreachable k (dtoc/optimize/certificate.py): a group of samples a slew-limited waveform
cannot reach is proven unreachable with the analytic lower bound; a reachable one is not, and its witness
reaches it."""

from __future__ import annotations

import numpy as np
import pytest

from dtoc.constants import GAMMA_RAD_PER_S_PER_MT
from dtoc.optimize import certificate as C
from dtoc.optimize.limits import EdgeProjector, Limits

RAS = 10e-6
N_EDGES = 401  # 4 ms
DK = 30.0  # rad/m


def _case(k_target_rad_per_m: float, t_s: float):
    """An ideal chain, the edge at t = 0 held at 0 (nothing before it), every other edge free, one ADC sample at
    ``t_s`` on x whose target is ``k_target``; the solver's edges: all zero (k = 0 there)."""
    free = np.zeros((3, N_EDGES), dtype=bool)
    free[0, 1:] = True
    lim = Limits(gmax_mT_per_m=1000.0, smax_T_per_m_per_s=100.0)
    P = EdgeProjector(np.zeros((3, N_EDGES)), free, RAS, lim)
    x = np.zeros((3, N_EDGES))
    k_now = np.zeros((3, 1))
    k0 = np.array([[k_target_rad_per_m], [0.0], [0.0]])
    dk = np.array([DK, np.inf, np.inf])
    err = np.abs(k0[0] - k_now[0]) / DK
    certs = C.certify(None, RAS / 2, P, x, k_now, k0, dk, np.array([t_s]), [], [], err, 0.01, n_groups=1, half=0)
    return P, certs


def test_a_target_beyond_the_slew_limit_is_proven_unreachable_by_the_analytic_margin():
    # from g = 0 at t = 0 the most k at T = N raster steps: g rising at the step bound S per edge, k = gamma T S N / 2
    n = 150
    t = n * RAS
    P, _ = _case(0.0, t)
    k_max = GAMMA_RAD_PER_S_PER_MT * RAS * P.step * n * n / 2
    P, certs = _case(k_max + 2.0 * DK, t)  # 2 dk beyond what the limits allow
    (c,) = certs
    assert c.status == "proven"
    assert c.lower_bound_dk == pytest.approx(2.0, abs=1e-4)
    assert c.binding == "slew"  # without the slew bound the target is reachable
    assert c.active.get("slew x", 0) >= n - 1  # the ramp at its slew bound


def test_a_reachable_target_is_not_certified_and_its_witness_reaches_it():
    n = 150
    t = n * RAS
    P, _ = _case(0.0, t)
    k_max = GAMMA_RAD_PER_S_PER_MT * RAS * P.step * n * n / 2
    _, certs = _case(0.4 * k_max, t)  # reachable, and its area given back within the window
    (c,) = certs
    assert not c.proven and c.status == "reachable"
    assert c.lower_bound_dk <= 0.01
    assert c.witness_dk <= 1e-6


def _k_ideal(e, t_s: float):
    """(3, 1) k at ``t_s`` (on an edge) of the ideal chain: gamma times the trapezoidal integral of the edges."""
    n = round(t_s / RAS)
    return GAMMA_RAD_PER_S_PER_MT * RAS * (e[:, 1:n].sum(1) + 0.5 * (e[:, 0] + e[:, n]))[:, None]


def _record(k_target_rad_per_m: float, t_s: float, groups: int = 4) -> dict:
    """:func:`dtoc.optimize.run.certify_stop` on the case of :func:`_case` (a plan's parts, ideal chain), from a
    solver record that stopped above the tolerance."""
    from types import SimpleNamespace

    import torch

    from dtoc.optimize.run import certify_stop

    P, _ = _case(0.0, t_s)
    x = torch.zeros((3, N_EDGES), dtype=torch.float64)
    k0 = torch.tensor([[k_target_rad_per_m], [0.0], [0.0]], dtype=torch.float64)
    plan = SimpleNamespace(
        hardware=None,
        projector=P,
        cfg=SimpleNamespace(k_tol_dk=0.01, certify_groups=groups),
        ir=SimpleNamespace(dt_fine_s=RAS / 2, adc_times_s=np.array([t_s]), rf=[]),
        ctx=SimpleNamespace(k0_rad_per_m=k0, dk_rad_per_m=torch.tensor([DK, np.inf, np.inf], dtype=torch.float64)),
        twin=SimpleNamespace(forward_edges=lambda e: SimpleNamespace(kspace_rad_per_m=_k_ideal(e, t_s))),
    )
    err = abs(k_target_rad_per_m) / DK
    rec = {"k_tol_dk": 0.01, "stop_reason": "converged", "achieved_max_dk": err, "summary": "solver: converged"}
    certify_stop(plan, x, rec)
    return rec


def test_the_manifest_names_a_proven_stop_and_keeps_the_solvers_own():
    n = 150
    P, _ = _case(0.0, n * RAS)
    k_max = GAMMA_RAD_PER_S_PER_MT * RAS * P.step * n * n / 2
    rec = _record(k_max + 2.0 * DK, n * RAS)
    assert rec["stop_reason"] == "unreachable (proven)" and rec["solver_stop_reason"] == "converged"
    c = rec["certificates"]
    assert (c["groups"], c["proven"], c["reachable"], c["not_proven"]) == (1, 1, 0, 0)
    assert c["each"][0]["lower_bound_dk"] == pytest.approx(2.0, abs=1e-4)
    assert "1 proven unreachable" in rec["summary"]


def test_the_manifest_keeps_the_solvers_stop_when_nothing_is_proven():
    n = 150
    P, _ = _case(0.0, n * RAS)
    k_max = GAMMA_RAD_PER_S_PER_MT * RAS * P.step * n * n / 2
    rec = _record(0.4 * k_max, n * RAS)
    assert rec["stop_reason"] == "converged" and "solver_stop_reason" not in rec
    assert rec["certificates"]["reachable"] == 1
    assert rec["certificates"]["each"][0]["witness_max_dk"] <= 1e-6  # the witness applied: the sample reached
    assert "1 reachable (the solve stopped short" in rec["summary"]


def test_certificates_are_off_by_default_and_the_manifest_says_so():
    """certify_groups 0 (the default): nothing is certified, the stop is the solver's, and the record says the
    samples are named, not proven."""
    from dtoc.optimize.config import OptimizeConfig

    assert OptimizeConfig().certify_groups == 0
    n = 150
    P, _ = _case(0.0, n * RAS)
    rec = _record(GAMMA_RAD_PER_S_PER_MT * RAS * P.step * n * n / 2 + 2.0 * DK, n * RAS, groups=0)
    assert rec["stop_reason"] == "converged" and "solver_stop_reason" not in rec
    assert "not certified" in rec["certificates"]["note"]
