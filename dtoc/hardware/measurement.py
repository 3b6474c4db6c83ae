"""Measurement files (contract docs/contracts.md §1): what was sent (``g``) and what was measured (``G``/``k``/``b0``).

Keys: ``dt`` scalar s; ``g`` (M, 3, N) mT/m demanded, sample n at ``t = n*dt``; ``G`` (M, 3, N) mT/m and/or
``k`` (M, 3, N) rad/m (``k(t_n) = gamma * integral_0^t_n G dt``); optional ``b0`` (M, N) uT; optional scalar
noise stds ``sigma_G``, ``sigma_k``, ``sigma_b0``; optional ``labels`` (M,) str; optional ``axes_measured``
(M, 3) bool (default all True; unmeasured entries are ignored, whatever they hold — they may be NaN).
Anything else in the file is ignored.  Every problem is a one-line :class:`InputError` naming the key.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dtoc.constants import GAMMA_RAD_PER_S_PER_MT
from dtoc.errors import InputError
from dtoc.hardware.npzio import save_npz


@dataclass
class Measurement:
    """Validated contents of a measurement file (all float64 numpy arrays; units as the contract).

    Attributes:
        dt_s: sample spacing, s.
        g: (M, 3, N) demanded gradient, mT/m.
        G: (M, 3, N) measured gradient, mT/m, or None.  Unmeasured entries are set to NaN.
        k: (M, 3, N) measured k-space, rad/m, or None.  Unmeasured entries are set to NaN.
        b0: (M, N) measured B0 offset, uT, or None.
        sigma_G, sigma_k, sigma_b0: per-sample noise std (mT/m, rad/m, uT) or None.
        labels: M names.
        axes_measured: (M, 3) bool.
        source: the file path.
    """

    dt_s: float
    g: np.ndarray
    G: np.ndarray | None = None
    k: np.ndarray | None = None
    b0: np.ndarray | None = None
    sigma_G: float | None = None
    sigma_k: float | None = None
    sigma_b0: float | None = None
    labels: list[str] = field(default_factory=list)
    axes_measured: np.ndarray | None = None
    source: str | None = None

    @property
    def n_waveforms(self) -> int:
        return self.g.shape[0]

    @property
    def n_samples(self) -> int:
        return self.g.shape[2]

    @property
    def t_s(self) -> np.ndarray:
        """(N,) sample times, s."""
        return np.arange(self.n_samples) * self.dt_s

    def realized_G(self) -> np.ndarray:
        """(M, 3, N) measured gradient, mT/m: ``G`` if given, else derived from ``k`` (:func:`G_from_k`)."""
        if self.G is not None:
            return self.G
        return G_from_k(self.k, self.dt_s)

    def realized_k(self) -> np.ndarray:
        """(M, 3, N) measured k-space, rad/m: ``k`` if given, else integrated from ``G`` (:func:`k_from_G`)."""
        if self.k is not None:
            return self.k
        return k_from_G(self.G, self.dt_s)

    def subset(self, idx) -> Measurement:
        """The waveforms ``idx`` (indices or bool mask) as a new Measurement (for held-out splits)."""
        idx = np.arange(self.n_waveforms)[idx]
        pick = lambda a: None if a is None else a[idx]  # noqa: E731
        return Measurement(
            self.dt_s,
            self.g[idx],
            pick(self.G),
            pick(self.k),
            pick(self.b0),
            self.sigma_G,
            self.sigma_k,
            self.sigma_b0,
            [self.labels[i] for i in idx],
            self.axes_measured[idx],
            self.source,
        )


def k_from_G(G: np.ndarray, dt_s: float) -> np.ndarray:
    """k (rad/m) of PWL gradients G (..., N) mT/m sampled at n*dt: exact trapezoidal running integral, k[0] = 0."""
    inc = 0.5 * dt_s * (G[..., 1:] + G[..., :-1]) * GAMMA_RAD_PER_S_PER_MT
    return np.concatenate([np.zeros(G.shape[:-1] + (1,)), np.cumsum(inc, axis=-1)], axis=-1)


def G_from_k(k: np.ndarray, dt_s: float) -> np.ndarray:
    """Gradient (mT/m) from sampled k (rad/m): central differences (one-sided at the ends).

    Second-order accurate for smooth waveforms; noise in k is amplified by ~1/(sqrt(2) gamma dt).
    """
    return np.gradient(k, dt_s, axis=-1) / GAMMA_RAD_PER_S_PER_MT


def _arr(z, key, path):
    try:
        return np.asarray(z[key])
    except ValueError:
        raise InputError(f"{path}: key {key!r} holds pickled objects; not accepted") from None


def _series(z, key, path, shape, unit, mask=None):
    a = _arr(z, key, path)
    want = "(" + ", ".join(str(s) for s in shape) + ")"
    if a.shape != tuple(shape):
        raise InputError(f"{path}: key {key!r} must have shape {want} in {unit}, got {a.shape}")
    if not np.issubdtype(a.dtype, np.number) or np.iscomplexobj(a):
        raise InputError(f"{path}: key {key!r} must be real numbers in {unit}")
    a = a.astype(np.float64)
    if mask is None:
        bad = ~np.isfinite(a)
    else:
        bad = ~np.isfinite(a) & mask[..., None]
    if bad.any():
        raise InputError(f"{path}: key {key!r} contains NaN or inf")
    if mask is not None:
        a = np.where(mask[..., None], a, np.nan)
    return a


def _sigma(z, key, path, unit):
    a = _arr(z, key, path)
    if a.size != 1 or not np.issubdtype(a.dtype, np.number):
        raise InputError(f"{path}: key {key!r} must be a scalar noise std in {unit}, got shape {a.shape}")
    v = float(a.reshape(()))
    if not np.isfinite(v) or v <= 0:
        raise InputError(
            f"{path}: key {key!r} must be a finite noise std > 0 in {unit}, got {v} "
            "(omit the key to have the noise estimated from the data)"
        )
    return v


def measurement_from_arrays(z, path: str = "measurement") -> Measurement:
    """Validate a mapping of contract keys (an opened npz or a dict) into a :class:`Measurement`."""
    keys = set(z.keys()) if hasattr(z, "keys") else set(z.files)
    if "dt" not in keys:
        raise InputError(f"{path}: key 'dt' missing (scalar sample spacing in s)")
    dt = _arr(z, "dt", path)
    if dt.size != 1 or not np.issubdtype(dt.dtype, np.number):
        what = f"dtype {dt.dtype}" if dt.size == 1 else f"shape {dt.shape}"
        raise InputError(f"{path}: key 'dt' must be a scalar number in s, got {what}")
    dt_s = float(dt.reshape(()))
    if not np.isfinite(dt_s) or dt_s <= 0:
        raise InputError(f"{path}: key 'dt' must be > 0 (s), got {dt_s}")
    if "g" not in keys:
        raise InputError(f"{path}: key 'g' missing (demanded gradient (M, 3, N) in mT/m)")
    g0 = _arr(z, "g", path)
    if g0.ndim != 3 or g0.shape[1] != 3 or g0.shape[0] < 1 or g0.shape[2] < 2:
        raise InputError(f"{path}: key 'g' must have shape (M, 3, N) in mT/m with M >= 1, N >= 2, got {g0.shape}")
    M, _, N = g0.shape
    g = _series(z, "g", path, (M, 3, N), "mT/m")
    axes = np.ones((M, 3), dtype=bool)
    if "axes_measured" in keys:
        a = _arr(z, "axes_measured", path)
        if a.shape != (M, 3) or not (a.dtype == bool or np.issubdtype(a.dtype, np.integer)):
            raise InputError(f"{path}: key 'axes_measured' must be bool with shape ({M}, 3), got {a.dtype} {a.shape}")
        if np.issubdtype(a.dtype, np.integer) and not np.all((a == 0) | (a == 1)):
            raise InputError(f"{path}: key 'axes_measured' must hold only true/false")
        axes = a.astype(bool)
    if "G" not in keys and "k" not in keys:
        raise InputError(f"{path}: needs key 'G' (M, 3, N) mT/m or key 'k' (M, 3, N) rad/m (measured)")
    G = _series(z, "G", path, (M, 3, N), "mT/m", axes) if "G" in keys else None
    k = _series(z, "k", path, (M, 3, N), "rad/m", axes) if "k" in keys else None
    b0 = _series(z, "b0", path, (M, N), "uT") if "b0" in keys else None
    sig = {
        key: (_sigma(z, key, path, unit) if key in keys else None)
        for key, unit in (("sigma_G", "mT/m"), ("sigma_k", "rad/m"), ("sigma_b0", "uT"))
    }
    labels = [f"w{i}" for i in range(M)]
    if "labels" in keys:
        lab = _arr(z, "labels", path)
        if lab.shape != (M,) or lab.dtype.kind not in "US":
            raise InputError(f"{path}: key 'labels' must be ({M},) strings, got {lab.dtype} {lab.shape}")
        labels = [str(x) for x in lab]
    return Measurement(dt_s, g, G, k, b0, sig["sigma_G"], sig["sigma_k"], sig["sigma_b0"], labels, axes, str(path))


#: Plausible sample spacing of a measurement, s.
DT_RANGE_S = (1e-8, 1e-3)
#: Plausible largest |g| of a measurement's demanded gradients, mT/m (outside: T/m or uT/m given).
G_RANGE_MT_PER_M = (0.1, 1000.0)
#: Accepted median ratio rms(measured) / rms(predicted from g) over measured, driven axes.
RATIO_RANGE = (0.4, 2.5)


def check_plausible(m: Measurement) -> None:
    """Reject unit mistakes with one line naming the key: ``dt`` outside :data:`DT_RANGE_S`, demanded
    ``g`` peaking outside :data:`G_RANGE_MT_PER_M`, and measured ``G`` (or ``k``) whose size differs from
    the demanded one (``g``, or ``gamma * integral g``) by more than :data:`RATIO_RANGE` (median over the
    measured axes of the waveforms that drive them): e.g. G in T/m, k in 1/m or cycles/m."""
    path = m.source or "measurement"
    if not DT_RANGE_S[0] <= m.dt_s <= DT_RANGE_S[1]:
        raise InputError(
            f"{path}: key 'dt' = {m.dt_s:g} s is implausible for gradient measurements (expected "
            f"{DT_RANGE_S[0]:g} to {DT_RANGE_S[1]:g} s; given in us or ms?)"
        )
    gpk = float(np.max(np.abs(m.g)))
    if not G_RANGE_MT_PER_M[0] <= gpk <= G_RANGE_MT_PER_M[1]:
        raise InputError(
            f"{path}: key 'g' peaks at {gpk:.4g} mT/m: implausible (expected {G_RANGE_MT_PER_M[0]:g} to "
            f"{G_RANGE_MT_PER_M[1]:g} mT/m; given in T/m or uT/m?)"
        )
    rms_g = np.sqrt(np.mean(m.g**2, axis=-1))  # (M, 3)
    driven = m.axes_measured & (rms_g > 0.05 * rms_g.max())
    if not driven.any():
        return
    checks = []
    if m.G is not None:
        checks.append(("G", "mT/m", m.G, m.g))
    if m.k is not None:
        checks.append(("k", "rad/m", m.k, k_from_G(m.g, m.dt_s)))
    for key, unit, meas, ref in checks:
        r_meas = np.sqrt(np.mean(np.where(m.axes_measured[..., None], meas, 0.0) ** 2, axis=-1))
        r_ref = np.sqrt(np.mean(ref**2, axis=-1))
        ok = driven & (r_ref > 0)
        if not ok.any():
            continue
        ratio = float(np.median(r_meas[ok] / r_ref[ok]))
        if not RATIO_RANGE[0] <= ratio <= RATIO_RANGE[1]:
            want = "demanded 'g'" if key == "G" else "gamma x integral of the demanded 'g'"
            raise InputError(
                f"{path}: key {key!r} is {ratio:.3g} times the {want} (median rms ratio over measured "
                f"axes): units off? ({key!r} must be in {unit})"
            )


def load_measurement(path: str | os.PathLike) -> Measurement:
    """Read and validate a measurement ``.npz`` (one-line InputError naming the key on any problem)."""
    p = Path(path)
    if p.is_dir():
        raise InputError(f"{p}: is a directory, expected a measurement .npz file")
    if not p.is_file():
        raise InputError(f"{p}: measurement file not found")
    try:
        z = np.load(p, allow_pickle=False)
    except Exception as e:  # noqa: BLE001
        raise InputError(f"{p}: not a readable .npz measurement file ({type(e).__name__})") from None
    if not isinstance(z, np.lib.npyio.NpzFile):
        raise InputError(f"{p}: not an .npz archive (a single array?); expected the keys dt, g, G and/or k")
    with z:
        m = measurement_from_arrays(z, str(p))
    check_plausible(m)
    return m


def save_measurement(m: Measurement, path: str | os.PathLike, force: bool = False) -> Path:
    """Write a measurement file (deterministic, atomic); NaN (unmeasured) entries are written as 0."""
    out: dict[str, np.ndarray] = {"dt": np.float64(m.dt_s), "g": m.g}
    for key in ("G", "k"):
        a = getattr(m, key)
        if a is not None:
            out[key] = np.nan_to_num(a, nan=0.0)
    if m.b0 is not None:
        out["b0"] = m.b0
    for key in ("sigma_G", "sigma_k", "sigma_b0"):
        if getattr(m, key) is not None:
            out[key] = np.float64(getattr(m, key))
    if m.labels:
        out["labels"] = np.array(m.labels, dtype=str)
    if m.axes_measured is not None:
        out["axes_measured"] = np.asarray(m.axes_measured, dtype=bool)
    return save_npz(path, out, force=force)
