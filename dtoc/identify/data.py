"""The measurement as the identification sees it: channels, masks, noise levels.

A measurement (docs/contracts.md §1) holds the demanded gradient ``g`` (M, 3, N) mT/m and one or more measured
channels: the realized gradient ``G`` (M, 3, N) mT/m, the k-space ``k`` (M, 3, N) rad/m and the
zeroth-order field ``b0`` (M, N) uT, all sampled at t_n = n*dt.  :class:`IdentData` keeps them as float64
numpy arrays together with the per-(waveform, axis) mask of measured axes, so that every residual,
fit and score in :mod:`dtoc.identify` treats unmeasured entries identically (weight zero).

k-space of a predicted gradient is formed exactly as the contract defines it,
k(t_n) = gamma * integral_0^{t_n} G dt, with G piecewise linear between samples (trapezoid rule, which is
exact for a piecewise-linear waveform).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from dtoc.errors import InputError
from dtoc.hardware.measurement import k_from_G

#: Channel names in the order used everywhere (report keys are f"{name}_rmse").
CHANNELS = ("G", "k", "b0")


def integrate_k(G_mT_per_m: np.ndarray, dt_s: float) -> np.ndarray:
    """k (rad/m) of a gradient sampled at t_n = n*dt: gamma * cumulative trapezoid from t = 0.

    Args:
        G_mT_per_m: (..., N) gradient samples, mT/m.
        dt_s: sample spacing, s.
    Returns:
        (..., N) k in rad/m, k[..., 0] = 0.
    """
    return k_from_G(np.asarray(G_mT_per_m, dtype=np.float64), dt_s)


@dataclass
class IdentData:
    """A validated measurement in the arrays the identification works on.

    Attributes:
        dt_s: sample spacing, s.
        g: (M, 3, N) demanded gradient, mT/m.
        G: (M, 3, N) measured gradient, mT/m, or None.
        k: (M, 3, N) measured k-space, rad/m, or None.
        b0: (M, N) measured B0 offset, uT, or None.
        axes_measured: (M, 3) bool, which axes of G/k are measured.
        sigma: given per-sample noise std per channel ({"G": float|None, "k": ..., "b0": ...}).
        labels: M waveform names.
    """

    dt_s: float
    g: np.ndarray
    G: np.ndarray | None = None
    k: np.ndarray | None = None
    b0: np.ndarray | None = None
    axes_measured: np.ndarray | None = None
    sigma: dict = field(default_factory=dict)
    labels: list = field(default_factory=list)

    def __post_init__(self):
        self.g = np.asarray(self.g, dtype=np.float64)
        if self.g.ndim != 3 or self.g.shape[1] != 3:
            raise InputError(f"measurement key 'g': expected shape (M, 3, N) in mT/m, got {self.g.shape}")
        M, _, N = self.g.shape
        for name in ("G", "k"):
            a = getattr(self, name)
            if a is not None:
                a = np.asarray(a, dtype=np.float64)
                if a.shape != self.g.shape:
                    raise InputError(f"measurement key '{name}': expected shape {self.g.shape} like 'g', got {a.shape}")
                setattr(self, name, a)
        if self.b0 is not None:
            self.b0 = np.asarray(self.b0, dtype=np.float64)
            if self.b0.shape != (M, N):
                raise InputError(f"measurement key 'b0': expected shape {(M, N)} in uT, got {self.b0.shape}")
        if self.G is None and self.k is None:
            raise InputError("measurement: neither 'G' (mT/m) nor 'k' (rad/m) is given; at least one is required")
        if not (np.isfinite(self.dt_s) and self.dt_s > 0):
            raise InputError(f"measurement key 'dt': must be a positive time in s, got {self.dt_s}")
        if self.axes_measured is None:
            self.axes_measured = np.ones((M, 3), dtype=bool)
        self.axes_measured = np.asarray(self.axes_measured, dtype=bool)
        if self.axes_measured.shape != (M, 3):
            raise InputError(
                f"measurement key 'axes_measured': expected shape {(M, 3)}, got {self.axes_measured.shape}"
            )
        for name in ("G", "k"):  # unmeasured entries may hold anything (NaN): zero them once
            a = getattr(self, name)
            if a is not None:
                setattr(self, name, np.where(self.axes_measured[:, :, None], a, 0.0))
        self.sigma = {c: (None if self.sigma.get(c) is None else float(self.sigma[c])) for c in CHANNELS}
        if not self.labels:
            self.labels = [f"w{m}" for m in range(M)]
        self.labels = [str(x) for x in self.labels]

    @property
    def M(self) -> int:
        return self.g.shape[0]

    @property
    def N(self) -> int:
        return self.g.shape[2]

    def channels(self) -> list[str]:
        """Measured channels, in :data:`CHANNELS` order."""
        return [c for c in CHANNELS if getattr(self, c) is not None]

    def mask(self, channel: str) -> np.ndarray:
        """Weight mask (1.0 measured, 0.0 ignored): (M, 3, N) for G/k, (M, N) for b0."""
        if channel == "b0":
            return np.ones((self.M, self.N))
        return np.broadcast_to(self.axes_measured[:, :, None], self.g.shape).astype(np.float64)

    def measured(self, channel: str) -> np.ndarray:
        """The measured channel (unmeasured entries are 0 and carry no weight)."""
        return getattr(self, channel)


def from_measurement(meas) -> IdentData:
    """Build :class:`IdentData` from a :class:`dtoc.hardware.measurement.Measurement` (or any object or
    mapping with the docs/contracts.md §1 names: dt, g, G, k, b0, sigma_G, sigma_k, sigma_b0, labels, axes_measured)."""

    def get(name):
        if isinstance(meas, dict):
            return meas.get(name)
        return getattr(meas, name, None)

    def opt(x):
        return None if x is None else np.asarray(x)

    dt = get("dt")
    if dt is None:
        dt = get("dt_s")
    sigma = {}
    for c in CHANNELS:
        s = get(f"sigma_{c}")
        if s is None and isinstance(get("sigma"), dict):
            s = get("sigma").get(c)
        sigma[c] = None if s is None else float(np.asarray(s))
    labels = get("labels")
    labels = [] if labels is None else [str(x) for x in np.asarray(labels).reshape(-1)]
    return IdentData(
        dt_s=float(np.asarray(dt)),
        g=np.asarray(get("g")),
        G=opt(get("G")),
        k=opt(get("k")),
        b0=opt(get("b0")),
        axes_measured=opt(get("axes_measured")),
        sigma=sigma,
        labels=labels,
    )
