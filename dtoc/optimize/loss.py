"""The digital-twin loss (paper Eq. 4A-F), normalised so the weights do not depend on scaling.

Terms (all dimensionless; each multiplied by its weight from :class:`~dtoc.optimize.config.LossWeights`):

* ``image``  (4B): ``||I - I0||_2 / ||I0||_2`` over the (possibly several, augmented) images: the
  NRMSE, independent of the simulator's signal scale.
* ``kspace`` (4C): ``mean_i sum_axes ((k_i - k0_i) / dk)^2``: k-space location error in units of dk^2
  per sample (dk = 2 pi / FOV), independent of FOV and matrix.
* ``amplitude`` (4D): ``mean_m relu(|g_m| - gmax) / gmax`` over fine samples and axes.
* ``slew`` (4E): ``mean_m relu(|g_{m+1} - g_m| / dt - smax) / smax``.
* ``moment`` (dtoc addition): the k-space moment accumulated just before every RF pulse, in dk^2 per
  pulse: it fixes the dephasing per repetition (spoiling, stimulated-echo pathways) that the k term
  at the ADC samples does not see; without it a k-only solution may cancel the spoiler.
* ``rf`` (4F): ``mean over RF-period samples of sum_axes (G - g0)^2 / g_ref^2`` with ``g_ref`` the base
  waveform's peak |g|: the realized gradient during RF pulses must be that of the base (zero in GRE,
  the slice-select plateau in EPI), because slice selection is not simulated.

Amplitude and slew are zero whenever the hard-limit projection is active; they remain for
``adam-paper`` studies with soft limits.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import dataclass

import numpy as np
import torch

from dtoc.optimize.config import LossWeights
from dtoc.sim import metrics


@dataclass
class LossContext:
    """Fixed quantities the loss needs (built once per run).

    Attributes:
        k0_rad_per_m: (3, N_adc) target k-space.
        dk_rad_per_m: (3,) k-space step per axis (axes with infinite dk, e.g. slice, are ignored).
        rf_mask: (M,) bool fine samples inside RF pulses.
        rf_index: (n,) long indices of the True samples of ``rf_mask`` (built on the host: the RF term
            gathers them without a device synchronisation; None: taken from ``rf_mask``).
        g0_fine_mT_per_m: (3, M) base demanded waveform.
        g_ref_mT_per_m: normalisation of gradient terms (base peak |g|).
        gmax_mT_per_m / smax_T_per_m_per_s: limits for the soft terms.
        dt_fine_s: fine grid spacing.
        sample_weight: (N_adc,) optional per-sample weights of the k term (default 1).
    """

    k0_rad_per_m: torch.Tensor
    dk_rad_per_m: torch.Tensor
    rf_mask: torch.Tensor
    g0_fine_mT_per_m: torch.Tensor
    g_ref_mT_per_m: float
    gmax_mT_per_m: float
    smax_T_per_m_per_s: float
    dt_fine_s: float
    sample_weight: torch.Tensor | None = None
    t_moment_s: np.ndarray | None = None
    k0_moment_rad_per_m: torch.Tensor | None = None
    rf_index: torch.Tensor | None = None


def rf_mask_fine(ir) -> np.ndarray:
    """(2N+1,) True on fine samples within an RF pulse ``[t_start, t_start + duration]``."""
    t = ir.t_fine_s
    m = np.zeros(t.shape, dtype=bool)
    for r in ir.rf:  # the samples t_start - 1 ps <= t <= t_end + 1 ps, found by bisection (linear in the duration)
        lo = np.searchsorted(t, r.t_start_s - 1e-12, side="left")
        hi = np.searchsorted(t, r.t_start_s + r.duration_s + 1e-12, side="right")
        m[lo:hi] = True
    return m


def build_context(ir, limits, dtype=torch.float64, device="cpu") -> LossContext:
    """Loss context of a sequence IR and :class:`~dtoc.optimize.limits.Limits`."""
    k0 = torch.as_tensor(ir.nominal_kspace_rad_per_m(), dtype=dtype, device=device)
    dk = ir.dk_rad_per_m
    if dk is None:
        # no grid (radial, spiral, ...): the readouts' sampling step on every axis the samples move along
        from dtoc.seq.geometry import sampling_step_dk

        k0n = ir.nominal_kspace_rad_per_m()
        step = sampling_step_dk(k0n, [a.num_samples for a in ir.adc]) or 1.0
        span = np.ptp(k0n, axis=1)
        dk = np.where(span > 1e-6 * max(float(span.max()), 1e-300), step, np.inf)  # axes the samples move along
    dk_t = torch.as_tensor(np.asarray(dk, dtype=np.float64), dtype=dtype, device=device)
    g0 = torch.as_tensor(ir.grad_mT_per_m, dtype=dtype, device=device)
    gref = float(np.abs(ir.grad_mT_per_m).max()) or 1.0
    # gradient moment accumulated up to each RF pulse (just before its centre): the dephasing per
    # repetition that spoiling and the higher-order echo pathways depend on
    t_mom = np.array(
        [r.t_center_s - 1e-9 for r in ir.rf[1:]], dtype=np.float64
    )  # before the first: no transverse state
    k0_mom = ir.kspace_rad_per_m(times_s=t_mom).to(dtype=dtype, device=device) if t_mom.size else None
    return LossContext(
        k0_rad_per_m=k0,
        dk_rad_per_m=dk_t,
        rf_mask=torch.as_tensor(rf_mask_fine(ir), device=device),
        rf_index=torch.as_tensor(np.flatnonzero(rf_mask_fine(ir)), device=device),
        g0_fine_mT_per_m=g0,
        g_ref_mT_per_m=gref,
        gmax_mT_per_m=limits.gmax_mT_per_m,
        smax_T_per_m_per_s=limits.smax_T_per_m_per_s,
        dt_fine_s=ir.dt_fine_s,
        t_moment_s=t_mom if t_mom.size else None,
        k0_moment_rad_per_m=k0_mom,
    )


def kspace_term(k: torch.Tensor, ctx: LossContext) -> torch.Tensor:
    """mean over samples of sum_axes ((k - k0)/dk)^2 (axes with infinite dk skipped)."""
    inv = torch.where(torch.isfinite(ctx.dk_rad_per_m), 1.0 / ctx.dk_rad_per_m, torch.zeros_like(ctx.dk_rad_per_m))
    e = ((k - ctx.k0_rad_per_m) * inv[:, None]) ** 2
    per = e.sum(0)
    if ctx.sample_weight is not None:
        return (per * ctx.sample_weight).sum() / ctx.sample_weight.sum().clamp_min(1e-12)
    return per.mean()


def moment_term(k_mom: torch.Tensor, ctx: LossContext) -> torch.Tensor:
    """mean over RF pulses of sum_axes ((m - m0)/dk)^2, m the k-space moment just before each pulse."""
    assert ctx.k0_moment_rad_per_m is not None, "moment term of a sequence with fewer than two RF pulses"
    inv = torch.where(torch.isfinite(ctx.dk_rad_per_m), 1.0 / ctx.dk_rad_per_m, torch.zeros_like(ctx.dk_rad_per_m))
    return (((k_mom - ctx.k0_moment_rad_per_m) * inv[:, None]) ** 2).sum(0).mean()


def image_term(images: list[torch.Tensor], targets: list[torch.Tensor]) -> torch.Tensor:
    """Mean NRMSE ||I - I0|| / ||I0|| over image pairs (complex or magnitude; magnitudes are compared)."""
    return torch.stack([metrics.nrmse(im, im0) for im, im0 in zip(images, targets)]).mean()


def amplitude_term(g: torch.Tensor, ctx: LossContext) -> torch.Tensor:
    return torch.relu(g.abs() - ctx.gmax_mT_per_m).mean() / ctx.gmax_mT_per_m


def slew_term(g: torch.Tensor, ctx: LossContext) -> torch.Tensor:
    s = (g[..., 1:] - g[..., :-1]).abs() / ctx.dt_fine_s * 1e-3
    return torch.relu(s - ctx.smax_T_per_m_per_s).mean() / ctx.smax_T_per_m_per_s


def rf_term(G: torch.Tensor, ctx: LossContext) -> torch.Tensor:
    idx = ctx.rf_index if ctx.rf_index is not None else torch.nonzero(ctx.rf_mask)[:, 0]
    if not idx.numel():  # a host-side shape: no device synchronisation
        return G.new_zeros(())
    d = (G - ctx.g0_fine_mT_per_m).index_select(1, idx)
    return (d**2).sum(0).mean() / ctx.g_ref_mT_per_m**2


def reg_term(g: torch.Tensor, ctx: LossContext) -> torch.Tensor:
    return ((g - ctx.g0_fine_mT_per_m) ** 2).mean() / ctx.g_ref_mT_per_m**2


def total_loss(
    weights: LossWeights,
    ctx: LossContext,
    *,
    g: torch.Tensor,
    G: torch.Tensor,
    k: torch.Tensor,
    images: list[torch.Tensor] | None = None,
    targets: list[torch.Tensor] | None = None,
    include_reg: bool = False,
    k_moment: torch.Tensor | None = None,
) -> tuple[torch.Tensor, Mapping[str, float]]:
    """Weighted sum of the terms and their weighted values (floats, for the history).

    Args:
        g: (3, M) demanded fine waveform, mT/m.   G: (3, M) realized, mT/m.   k: (3, N_adc) rad/m.
        k_moment: (3, N_rf) realized k just before each RF pulse (None: moment term skipped).
        images / targets: simulated and target images (None: image term skipped).
    """
    terms: dict[str, torch.Tensor] = {}
    if images is not None and targets is not None and weights.image > 0:
        terms["image"] = weights.image * image_term(images, targets)
    if weights.kspace > 0:
        terms["kspace"] = weights.kspace * kspace_term(k, ctx)
    if weights.moment > 0 and k_moment is not None:
        terms["moment"] = weights.moment * moment_term(k_moment, ctx)
    if weights.amplitude > 0:
        terms["amplitude"] = weights.amplitude * amplitude_term(g, ctx)
    if weights.slew > 0:
        terms["slew"] = weights.slew * slew_term(g, ctx)
    if weights.rf > 0:
        terms["rf"] = weights.rf * rf_term(G, ctx)
    if include_reg and weights.reg > 0:
        terms["reg"] = weights.reg * reg_term(g, ctx)
    total = torch.stack(list(terms.values())).sum() if terms else g.new_zeros(())
    return total, TermValues(terms)


class TermValues(Mapping[str, float]):
    """The weighted term values of :func:`total_loss` as floats, read from the device in ONE transfer on
    first access (after the iteration's forward and backward are queued), not one synchronisation per
    term inside the forward.  The same values as ``float(term)``."""

    def __init__(self, terms: dict[str, torch.Tensor]):
        self._terms = terms
        self._vals: dict[str, float] | None = None

    def _values(self) -> dict[str, float]:
        if self._vals is None:
            keys = list(self._terms)
            vals = torch.stack([v.detach() for v in self._terms.values()]).tolist() if keys else []
            self._vals = dict(zip(keys, vals))
        return self._vals

    def stacked(self) -> torch.Tensor:
        """(T,) the terms' values (detached, in key order) as one tensor on their device: what a replayed
        step (:class:`dtoc.util.replay.Replay`) returns, to be read back with :meth:`from_stacked`."""
        if not self._terms:
            return torch.zeros(0, dtype=torch.float64)
        return torch.stack([v.detach() for v in self._terms.values()])

    @classmethod
    def from_stacked(cls, keys: list[str], values: torch.Tensor) -> TermValues:
        """The terms ``keys`` from :meth:`stacked`'s tensor (no transfer until a value is read)."""
        return cls({k: values[i] for i, k in enumerate(keys)})

    def __getitem__(self, key: str) -> float:
        return self._values()[key]

    def __iter__(self) -> Iterator[str]:
        return iter(self._terms)

    def __len__(self) -> int:
        return len(self._terms)

    def __repr__(self) -> str:
        return repr(self._values())
