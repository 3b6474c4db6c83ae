"""Synthetic measurements for tests, examples and benchmarks.

:func:`probe_waveforms` makes demanded gradients like those used to characterise gradient systems: on each
axis independently, a random train of trapezoids and triangles (random signed amplitude, slew between 30 %
and 100 % of the limit, random plateau and gap lengths), starting and ending at zero.  Axes differ, so
cross terms are identifiable.  :func:`simulate_measurement` plays them through a "true scanner"
(a :class:`dtoc.hardware.model.HardwareModel`) and adds white Gaussian noise; :func:`save_measurement`
writes the docs/contracts.md §1 ``.npz``.  Everything is seeded: same arguments, same arrays.
"""

from __future__ import annotations

import io

import numpy as np
import torch

from dtoc.hardware.model import HardwareModel
from dtoc.identify.data import IdentData, integrate_k
from dtoc.util.atomic import atomic_write_bytes


def probe_waveforms(
    M: int,
    N: int,
    dt_s: float = 10e-6,
    gmax_mT_per_m: float = 30.0,
    smax_T_per_m_per_s: float = 150.0,
    seed: int = 0,
    axes=(0, 1, 2),
) -> np.ndarray:
    """(M, 3, N) demanded test gradients in mT/m (see module docstring); unused axes are zero."""
    rng = np.random.default_rng(seed)
    g = np.zeros((M, 3, N))
    smax = smax_T_per_m_per_s * 1e3  # mT/m/s
    for m in range(M):
        for a in axes:
            n = int(rng.integers(5, 40))
            while n < N - 10:
                amp = rng.uniform(0.2, 1.0) * gmax_mT_per_m * rng.choice([-1.0, 1.0])
                slew = rng.uniform(0.3, 1.0) * smax
                nr = max(1, int(np.ceil(abs(amp) / slew / dt_s)))
                npl = int(rng.integers(0, 120)) if rng.random() < 0.7 else 0
                if n + 2 * nr + npl >= N - 2:
                    break
                ramp = np.arange(1, nr + 1) / nr
                g[m, a, n + 1 : n + nr + 1] = amp * ramp
                g[m, a, n + nr + 1 : n + nr + npl + 1] = amp
                g[m, a, n + nr + npl + 1 : n + 2 * nr + npl + 1] = amp * (1.0 - ramp)
                n = n + 2 * nr + npl + 1 + int(rng.integers(5, 200))
    return g


def simulate_measurement(
    true_model: HardwareModel,
    g: np.ndarray,
    dt_s: float,
    *,
    sigma_G: float | None = 0.01,
    sigma_k: float | None = None,
    sigma_b0: float | None = None,
    seed: int = 1,
    give_sigma: bool = False,
) -> IdentData:
    """Play ``g`` through ``true_model`` and add white noise.

    Args:
        true_model: the "true scanner".
        g: (M, 3, N) demanded gradients, mT/m.
        sigma_G / sigma_k / sigma_b0: noise std of the channels to deliver (None: channel absent).
        give_sigma: store the noise levels in the measurement (else they must be estimated).
    Returns:
        :class:`IdentData` with the requested channels.
    """
    rng = np.random.default_rng(seed)
    with torch.no_grad():
        G, b0 = true_model(torch.as_tensor(g, dtype=torch.float64), dt_s)
    G = G.numpy()
    b0 = b0.numpy()
    out = {}
    if sigma_G is not None:
        out["G"] = G + sigma_G * rng.standard_normal(G.shape)
    if sigma_k is not None:
        out["k"] = integrate_k(G, dt_s) + sigma_k * rng.standard_normal(G.shape)
    if sigma_b0 is not None:
        out["b0"] = b0 + sigma_b0 * rng.standard_normal(b0.shape)
    sig = {"G": sigma_G, "k": sigma_k, "b0": sigma_b0} if give_sigma else {}
    return IdentData(dt_s=dt_s, g=g, sigma=sig, **out)


def measurement_npz_bytes(d: IdentData) -> bytes:
    """The docs/contracts.md §1 ``.npz`` bytes of a measurement (deterministic)."""
    arrays = {"dt": np.float64(d.dt_s), "g": d.g}
    for c in ("G", "k", "b0"):
        if getattr(d, c) is not None:
            arrays[c] = getattr(d, c)
        if d.sigma.get(c) is not None:
            arrays[f"sigma_{c}"] = np.float64(d.sigma[c])
    arrays["labels"] = np.asarray(d.labels)
    arrays["axes_measured"] = d.axes_measured
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


def save_measurement(d: IdentData, path, force: bool = False):
    """Write the measurement ``.npz`` atomically."""
    return atomic_write_bytes(path, measurement_npz_bytes(d), force=force)


def lowpass_girf(
    dt_s: float = 10e-6,
    bandwidth_hz: float = 12e3,
    cross: float = 0.01,
    cross_tau_s: float = 50e-6,
    b0_uT_per_mT_per_m: float | None = None,
    n_taps: int = 64,
):
    """A self-made, smooth GIRF for tests and examples (time domain, causal, 10 us taps by default).

    Self terms: a normalised gamma-shaped impulse response (second-order low-pass, -3 dB near
    ``bandwidth_hz``) with DC gain 1, slightly different per axis; cross terms: ``cross`` x an exponential
    of ``cross_tau_s`` (DC gain ``cross``); optional B0 row: ``b0_uT_per_mT_per_m`` x the same exponential.

    Returns:
        :class:`dtoc.hardware.girf_io.GirfData` (dt, t0 = 0, h (3, 3, L), h0 (3, L) or None).
    """
    from dtoc.hardware.girf_io import GirfData

    t = (np.arange(n_taps) + 0.5) * dt_s
    h = np.zeros((3, 3, n_taps))
    for a in range(3):
        # second-order low-pass: t exp(-t/T), |H| = 1/(1 + (2 pi f T)^2): -3 dB at f = sqrt(sqrt(2)-1)/(2 pi T).
        T = np.sqrt(np.sqrt(2) - 1) / (2 * np.pi * bandwidth_hz * (1.0 + 0.05 * a))
        k = t * np.exp(-t / T)
        h[a, a] = k / k.sum()
    e = np.exp(-t / cross_tau_s)
    e /= e.sum()
    for o in range(3):
        for i in range(3):
            if o != i:
                h[o, i] = cross * (1.0 + 0.3 * (o - i)) * e
    h0 = None
    if b0_uT_per_mT_per_m is not None:
        h0 = np.stack([b0_uT_per_mT_per_m * (1.0 + 0.2 * i) * e for i in range(3)])
    return GirfData(dt_s=dt_s, t0_s=0.0, h=h, h0=h0, source="dtoc.identify.synth.lowpass_girf")
