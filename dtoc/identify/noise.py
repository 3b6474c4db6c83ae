"""Noise floor of a measured channel, estimated from the data itself.

Two estimators, both for white per-sample noise (the meaning of ``sigma_*`` in docs/contracts.md §1):

* **Repeated waveforms** (preferred when available): waveforms whose demanded ``g`` is identical must
  have identical realized responses, so the scatter of the measurements about their group mean is noise
  alone: sigma^2 = sum (y - mean)^2 / ((n_rep - 1) * n_samples).  Unbiased whatever the hardware does
  (as long as it is repeatable).
* **High-order differences of the residual** (always applicable): the residual of a model's prediction
  is noise plus a signal that is band-limited by the gradient chain (its power sits well below Nyquist),
  while white noise is flat up to Nyquist.  The p-th forward difference multiplies a component at
  frequency f by (2 sin(pi f dt))^p: white noise keeps variance C(2p, p) sigma^2, a 5 kHz residual at
  dt = 10 us is attenuated by 0.03 (p = 3).  What leaks through is concentrated at the few waveform corners,
  so the scale is taken robustly: sigma = 1.4826 * MAD(diff_p r) / sqrt(C(2p, p)).  The minimum over
  p = 2, 3, 4 is used (each is unbiased for pure noise; a smooth residual only ever raises an estimate).
  A model error is largest right after the corners of the demanded waveform (where its slope changes:
  the transient of a missing low-pass, delay or eddy term), and a robust scale is still biased by a
  contaminated fraction eps (+13 % for eps = 10 %).  So samples within ``CORNER_GUARD`` samples of a corner
  of ``g`` (|second difference| > 1e-9 of its peak) are left out when enough others remain (>= 20 % and
  >= 1000 samples): on ramps, plateaus and gaps a linear model error is smooth and the differences remove it.

The accuracy of both is asserted in tests/test_identify_noise.py (within a few percent on pure noise,
within 10 % with a GIRF-sized residual under the noise).
"""

from __future__ import annotations

from dataclasses import dataclass
from math import comb

import numpy as np

#: MAD -> standard deviation for a Gaussian.
_MAD_TO_STD = 1.482602218505602


@dataclass(frozen=True)
class NoiseEstimate:
    """A per-sample noise standard deviation and how it was obtained."""

    sigma: float
    method: str  # "given" | "repeated" | "difference"
    n_samples: int


#: Samples after/before a corner of the demanded waveform left out of the difference estimator.
CORNER_GUARD = 12


def _rows(x: np.ndarray, mask: np.ndarray, quiet: np.ndarray | None = None) -> list:
    """Fully measured time series of ``x`` (..., N): one (row, quiet-row) pair per measured row."""
    x2 = np.asarray(x, dtype=np.float64).reshape(-1, x.shape[-1])
    m2 = np.asarray(mask).reshape(-1, x.shape[-1]) > 0
    q2 = np.ones_like(m2) if quiet is None else np.broadcast_to(quiet, x.shape).reshape(-1, x.shape[-1])
    return [(x2[i], q2[i]) for i in range(x2.shape[0]) if m2[i].all()]


def quiet_samples(g: np.ndarray, guard: int = CORNER_GUARD) -> np.ndarray:
    """(M, 3, N) bool: samples farther than ``guard`` samples from any corner of ``g`` on that axis."""
    g = np.asarray(g, dtype=np.float64)
    d2 = np.abs(np.diff(g, n=2, axis=-1))
    scale = max(float(np.max(np.abs(g))), 1e-300)
    corner = np.zeros(g.shape, dtype=bool)
    corner[..., 1:-1] = d2 > 1e-9 * scale
    corner[..., 0] = corner[..., -1] = True
    # Dilate by `guard` samples either side (cumulative-sum window).
    c = np.cumsum(np.concatenate([np.zeros(g.shape[:-1] + (1,)), corner], axis=-1), axis=-1)
    N = g.shape[-1]
    lo = np.clip(np.arange(N) - guard, 0, N)
    hi = np.clip(np.arange(N) + guard + 1, 0, N)
    near = (c[..., hi] - c[..., lo]) > 0
    return ~near


def difference_sigma(
    residual: np.ndarray, mask: np.ndarray, orders=(2, 3, 4), quiet: np.ndarray | None = None
) -> NoiseEstimate | None:
    """Robust high-order-difference estimate of white noise in ``residual`` (..., N).

    Args:
        residual: measured minus predicted, any leading shape, time last.
        mask: same shape, > 0 where measured (rows are used only when fully measured).
        orders: difference orders tried; the smallest estimate wins.
        quiet: optional bool array broadcastable to ``residual``: samples to use (e.g. away from corners);
            ignored when it leaves fewer than 1000 samples or 20 % of them.
    Returns:
        The estimate, or None when fewer than 64 samples are usable.
    """
    rows = _rows(residual, mask, quiet)
    n = sum(r.size for r, _ in rows)
    if n < 64:
        return None
    nq = sum(int(q.sum()) for _, q in rows)
    use_quiet = quiet is not None and nq >= max(1000, 0.2 * n)
    best = None
    for p in orders:
        parts = []
        for r, q in rows:
            if r.size <= p + 1:
                continue
            d = np.diff(r, n=p)
            parts.append(d[q[: d.size]] if use_quiet else d)
        d = np.concatenate(parts) if parts else np.zeros(0)
        if d.size < 32:
            continue
        mad = np.median(np.abs(d - np.median(d)))
        s = _MAD_TO_STD * mad / np.sqrt(comb(2 * p, p))
        best = s if best is None else min(best, s)
    if best is None:
        return None
    return NoiseEstimate(
        float(best), "difference" + (" (away from corners)" if use_quiet else ""), int(nq if use_quiet else n)
    )


def repeated_sigma(g: np.ndarray, y: np.ndarray, mask: np.ndarray, min_samples: int = 1000) -> NoiseEstimate | None:
    """Noise from repeated demanded waveforms.

    Args:
        g: (M, 3, N) demanded gradients.
        y: (M, ..., N) a measured channel (G, k: (M, 3, N); b0: (M, N)).
        mask: like ``y``, > 0 where measured.
        min_samples: fewer pooled degrees of freedom than this -> None.
    Returns:
        The pooled estimate, or None when no waveform is repeated (with the same measured entries).
    """
    M = g.shape[0]
    groups: dict[bytes, list[int]] = {}
    for m in range(M):
        key = np.ascontiguousarray(g[m]).tobytes() + (np.asarray(mask[m]) > 0).tobytes()
        groups.setdefault(key, []).append(m)
    ss, dof = 0.0, 0
    for idx in groups.values():
        if len(idx) < 2:
            continue
        w = np.asarray(mask[idx[0]]) > 0
        ys = np.stack([np.asarray(y[i])[w] for i in idx])
        ss += float(((ys - ys.mean(axis=0)) ** 2).sum())
        dof += (len(idx) - 1) * ys.shape[1]
    if dof < min_samples:
        return None
    return NoiseEstimate(float(np.sqrt(ss / dof)), "repeated", int(dof))


def estimate_sigma(
    given: float | None, g: np.ndarray, y: np.ndarray, residual: np.ndarray, mask: np.ndarray
) -> NoiseEstimate:
    """The noise floor of one channel: the given value, else repeated waveforms, else differences.

    Args:
        given: ``sigma_*`` from the file, or None.
        g: (M, 3, N) demanded gradient.
        y: the measured channel; residual: measured minus declared-model prediction; mask: as y.
    Returns:
        A :class:`NoiseEstimate` (sigma > 0; a floor of 1e-12 x the channel's scale guards a noiseless file).
    """
    scale = float(np.max(np.abs(y[np.asarray(mask) > 0]))) if np.any(np.asarray(mask) > 0) else 1.0
    floor = max(scale, 1e-30) * 1e-12
    if given is not None and given > 0:
        return NoiseEstimate(float(given), "given", int(np.sum(np.asarray(mask) > 0)))
    est = repeated_sigma(g, y, mask)
    if est is None:
        quiet = quiet_samples(g)
        if np.ndim(y) == 2:  # b0 (M, N): quiet where every axis is quiet
            quiet = quiet.all(axis=1)
        est = difference_sigma(residual, mask, quiet=quiet)
    if est is None:
        est = NoiseEstimate(floor, "none", 0)
    if est.sigma < floor:
        est = NoiseEstimate(floor, est.method, est.n_samples)
    if given is not None:  # 0 (or negative) given: a noiseless claim cannot whiten a residual; say so
        est = NoiseEstimate(est.sigma, est.method + f" (the file's sigma = {given:g} is not usable)", est.n_samples)
    return est
