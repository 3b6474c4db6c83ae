"""GIRF files (contract docs/contracts.md §2): load, validate, save, convert frequency <-> time domain.

Time domain: ``dt`` (s), ``h`` (3, 3, L) real, ``h[o, i, l]`` = per-sample response on output axis o to a
unit-area impulse on input axis i at time ``t0 + l*dt`` after it (``h[o, o].sum()`` = DC gain);
``t0`` (s, default 0); optional ``h0`` (3, L), the B0 response in uT per (mT/m) per sample.
Frequency domain: ``f`` (F,) Hz, ``H`` (3, 3, F) complex, optional ``H0`` (3, F) complex, with the
convention ``H(f) = sum_l h[l] exp(-2 pi i f (t0 + l dt))`` (a positive delay has a negative phase slope).
Optional text keys ``source`` and ``notes`` describe provenance.

A frequency-domain GIRF must be on a uniform grid that contains f = 0: either two-sided
(``-F0 df ... (F-F0-1) df``) or one-sided (``0 ... (F-1) df``, real kernel implied).  It is converted to
taps by inverse DFT on ``N`` points (two-sided: N = F; one-sided: N = 2(F-1)), ``dt = 1 / (N df)``,
centred: ``t0 = -floor(N/2) dt`` (the kernel is periodic in time with period ``N dt``; choose a grid
fine enough that the response has decayed within half of it).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dtoc.errors import InputError
from dtoc.hardware.npzio import save_npz


@dataclass
class GirfData:
    """A GIRF in time domain (``h`` set) or frequency domain (``H`` set); see module docstring.

    Attributes:
        dt_s, t0_s: tap spacing and time of tap 0, s (time domain).
        h: (3, 3, L) float64, per-sample response, h[o, i] output o, input i.
        h0: (3, L) float64 or None, B0 response, uT per (mT/m) per sample.
        f_hz: (F,) frequencies, Hz (frequency domain); H: (3, 3, F) complex; H0: (3, F) complex or None.
        source: file(s) it came from; notes: conventions applied on import.
    """

    dt_s: float | None = None
    t0_s: float = 0.0
    h: np.ndarray | None = None
    h0: np.ndarray | None = None
    f_hz: np.ndarray | None = None
    H: np.ndarray | None = None
    H0: np.ndarray | None = None
    source: str | None = None
    notes: list[str] = field(default_factory=list)

    @property
    def is_time_domain(self) -> bool:
        return self.h is not None

    def to_time_domain(self) -> GirfData:
        """This GIRF with taps ``h`` (converted from ``H`` by inverse DFT when needed)."""
        if self.is_time_domain:
            return self
        dt, t0, h = freq_to_taps(self.f_hz, self.H)
        h0 = None
        if self.H0 is not None:
            _, _, h0 = freq_to_taps(self.f_hz, self.H0)
        return GirfData(
            dt_s=dt,
            t0_s=t0,
            h=h,
            h0=h0,
            source=self.source,
            notes=self.notes + [f"converted from frequency domain: N={h.shape[-1]}, dt={dt:.6g} s, centred"],
        )

    def response(self, f_hz: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """``H(f)`` (3, 3, F) and ``H0(f)`` (3, F) or None at arbitrary frequencies (DTFT of the taps)."""
        td = self.to_time_domain()
        f = np.asarray(f_hz, dtype=np.float64)
        t = td.t0_s + np.arange(td.h.shape[-1]) * td.dt_s
        H = np.empty((3, 3, f.size), dtype=np.complex128)
        H0 = None if td.h0 is None else np.empty((3, f.size), dtype=np.complex128)
        for a in range(0, f.size, 512):  # chunks keep the (F, L) phase matrix small
            E = np.exp(-2j * np.pi * np.outer(f[a : a + 512], t))  # (Fc, L)
            H[..., a : a + 512] = td.h @ E.T
            if H0 is not None:
                H0[:, a : a + 512] = td.h0 @ E.T
        return H, H0

    @property
    def nyquist_hz(self) -> float:
        td = self.to_time_domain()
        return 0.5 / td.dt_s

    def arrays(self) -> dict[str, np.ndarray]:
        """The contract keys of this GIRF (what :func:`save_girf` writes)."""
        out: dict[str, np.ndarray] = {}
        if self.is_time_domain:
            out.update(dt=np.float64(self.dt_s), t0=np.float64(self.t0_s), h=np.asarray(self.h, np.float64))
            if self.h0 is not None:
                out["h0"] = np.asarray(self.h0, np.float64)
        else:
            out.update(f=np.asarray(self.f_hz, np.float64), H=np.asarray(self.H, np.complex128))
            if self.H0 is not None:
                out["H0"] = np.asarray(self.H0, np.complex128)
        if self.source:
            out["source"] = np.str_(self.source)
        if self.notes:
            out["notes"] = np.str_("\n".join(self.notes))
        return out


def freq_to_taps(f_hz: np.ndarray, H: np.ndarray) -> tuple[float, float, np.ndarray]:
    """Uniform two- or one-sided frequency response (..., F) -> (dt, t0, centred real taps (..., N))."""
    f = np.asarray(f_hz, dtype=np.float64)
    F = f.size
    df = (f[-1] - f[0]) / (F - 1)
    k = f / df
    if F < 3 or df <= 0 or np.max(np.abs(k - np.round(k))) > 1e-6:
        raise InputError("GIRF key 'f' must be a uniform frequency grid containing 0 (two- or one-sided)")
    k = np.round(k).astype(np.int64)
    if k[0] == 0:  # one-sided
        N = 2 * (F - 1)
        taps = np.fft.irfft(H, n=N, axis=-1)
    elif k[0] < 0 < k[-1]:
        N = F
        spec = np.zeros(H.shape[:-1] + (N,), dtype=np.complex128)
        spec[..., k % N] = H
        taps = np.fft.ifft(spec, axis=-1).real
    else:
        raise InputError("GIRF key 'f' must start at 0 (one-sided) or be negative-to-positive (two-sided)")
    dt = 1.0 / (N * df)
    taps = np.fft.fftshift(taps, axes=-1)
    t0 = -(N // 2) * dt
    return dt, t0, taps


def _key(z, name: str, path) -> np.ndarray:
    try:
        return np.asarray(z[name])
    except ValueError:
        raise InputError(f"{path}: key {name!r} holds pickled objects; not accepted") from None


def _finite(a: np.ndarray, name: str, path, shape: str) -> None:
    if not np.issubdtype(a.dtype, np.number):
        raise InputError(f"{path}: key {name!r} must be numeric with shape {shape}")
    if not np.all(np.isfinite(a)):
        raise InputError(f"{path}: key {name!r} contains NaN or inf")


def _scalar(z, name: str, path, positive: bool = False) -> float:
    a = _key(z, name, path)
    if a.ndim != 0 and a.size != 1:
        raise InputError(f"{path}: key {name!r} must be a scalar (s), got shape {a.shape}")
    _finite(a, name, path, "()")
    v = float(a.reshape(()))
    if positive and v <= 0:
        raise InputError(f"{path}: key {name!r} must be > 0 (s), got {v}")
    return v


#: Plausible range of a GIRF's tap spacing, s (anything else is a unit mistake: ms or us given as s).
DT_RANGE_S = (1e-8, 1e-3)
#: Longest accepted kernel, s (a GIRF decays within milliseconds; longer is a unit or layout mistake).
MAX_SPAN_S = 2.0
#: Accepted DC gain of a self term (x->x ...): a real gradient chain is within a few % of 1.
SELF_DC_RANGE = (0.5, 2.0)
#: Largest accepted |DC gain| of a cross term and of a B0 term (uT per mT/m).
CROSS_DC_MAX = 0.5
B0_DC_MAX = 100.0


def check_plausible(gd: GirfData, path: str = "GIRF") -> None:
    """Reject a GIRF whose magnitudes are physically implausible (unit mistakes), one line naming the key.

    Checks: ``dt`` within :data:`DT_RANGE_S`, kernel span at most :data:`MAX_SPAN_S`, self-term DC gain
    ``sum(h[a, a])`` within :data:`SELF_DC_RANGE` (a kernel stored as a density in 1/s has a DC gain of
    ~1/dt; one scaled by 1e3 has 1000), cross-term |DC gain| <= :data:`CROSS_DC_MAX`, B0-term |DC gain|
    <= :data:`B0_DC_MAX` uT per mT/m.
    """
    from dtoc.constants import AXES

    td = gd.to_time_domain()
    key_dt = "dt" if gd.is_time_domain else "f"
    if not DT_RANGE_S[0] <= td.dt_s <= DT_RANGE_S[1]:
        what = f"'dt' = {td.dt_s:g} s" if gd.is_time_domain else f"'f' spacing gives a tap spacing of {td.dt_s:g} s"
        raise InputError(
            f"{path}: key {what} is implausible for a GIRF (expected {DT_RANGE_S[0]:g} to "
            f"{DT_RANGE_S[1]:g} s; given in ms or us instead of s, or f in kHz instead of Hz?)"
        )
    span = td.h.shape[-1] * td.dt_s
    if abs(td.t0_s) > MAX_SPAN_S:
        raise InputError(
            f"{path}: key 't0' = {td.t0_s:g} s is implausible (more than {MAX_SPAN_S:g} s; given in us or ms?)"
        )
    if span > MAX_SPAN_S:
        raise InputError(
            f"{path}: key {key_dt!r}: kernel spans {span:g} s (more than {MAX_SPAN_S:g} s): implausible for a GIRF"
        )
    hk = "h" if gd.is_time_domain else "H"
    dc = td.h.sum(axis=-1)
    for a in range(3):
        v = float(dc[a, a])
        if not SELF_DC_RANGE[0] <= v <= SELF_DC_RANGE[1]:
            hint = (
                " (taps stored as a density in 1/s? multiply by dt)"
                if abs(v * td.dt_s - 1) < 0.5
                else (" (units off by 1e3?)" if 200 < abs(v) < 5000 or 2e-4 < abs(v) < 5e-3 else "")
            )
            raise InputError(
                f"{path}: key {hk!r}: DC gain of self term {AXES[a]}->{AXES[a]} is {v:.4g}, expected about 1 "
                f"({SELF_DC_RANGE[0]:g} to {SELF_DC_RANGE[1]:g}){hint}"
            )
    for o in range(3):
        for i in range(3):
            if o != i and abs(dc[o, i]) > CROSS_DC_MAX:
                raise InputError(
                    f"{path}: key {hk!r}: DC gain of cross term {AXES[i]}->{AXES[o]} is {dc[o, i]:.4g}; "
                    f"|gain| above {CROSS_DC_MAX:g} is implausible (axes swapped or units off?)"
                )
    if td.h0 is not None:
        d0 = td.h0.sum(axis=-1)
        for i in range(3):
            if abs(d0[i]) > B0_DC_MAX:
                raise InputError(
                    f"{path}: key {'h0' if gd.is_time_domain else 'H0'!r}: DC gain of B0 term {AXES[i]}->b0 is "
                    f"{d0[i]:.4g} uT per mT/m; above {B0_DC_MAX:g} is implausible (units off?)"
                )


def validate_girf_arrays(z, path: str = "GIRF", plausible: bool = True) -> GirfData:
    """Validate a mapping of contract keys (an opened npz) and build :class:`GirfData`.

    ``plausible``: also reject physically implausible magnitudes (:func:`check_plausible`)."""
    gd = _validate_girf_arrays(z, path)
    if plausible:
        check_plausible(gd, path)
    return gd


def _validate_girf_arrays(z, path: str) -> GirfData:
    keys = set(z.keys()) if hasattr(z, "keys") else set(z.files)
    text = {}
    for k in ("source", "notes"):
        if k in keys:
            try:
                arr = np.asarray(z[k])
                # one string, or an array of strings (one per line; older files and other writers)
                text[k] = "\n".join(str(x) for x in arr.reshape(-1)) if arr.ndim else str(arr)
            except ValueError:
                text[k] = None
    notes = text.get("notes").split("\n") if text.get("notes") else []
    if "h" in keys:
        if "dt" not in keys:
            raise InputError(f"{path}: key 'dt' missing: a time-domain GIRF needs its tap spacing dt (s)")
        dt = _scalar(z, "dt", path, positive=True)
        t0 = _scalar(z, "t0", path) if "t0" in keys else 0.0
        h = _key(z, "h", path)
        if h.ndim != 3 or h.shape[:2] != (3, 3) or h.shape[2] < 1:
            raise InputError(f"{path}: key 'h' must have shape (3, 3, L), got {h.shape}")
        _finite(h, "h", path, "(3, 3, L)")
        if np.iscomplexobj(h):
            raise InputError(f"{path}: key 'h' must be real (time-domain taps)")
        h0 = None
        if "h0" in keys:
            h0 = _key(z, "h0", path)
            if h0.shape != (3, h.shape[2]):
                raise InputError(f"{path}: key 'h0' must have shape (3, {h.shape[2]}), got {h0.shape}")
            _finite(h0, "h0", path, "(3, L)")
            if np.iscomplexobj(h0):
                raise InputError(f"{path}: key 'h0' must be real (time-domain taps)")
            h0 = h0.astype(np.float64)
        return GirfData(
            dt_s=dt, t0_s=t0, h=h.astype(np.float64), h0=h0, source=text.get("source") or str(path), notes=notes
        )
    if "H" in keys:
        if "f" not in keys:
            raise InputError(f"{path}: key 'f' missing: a frequency-domain GIRF needs f (F,) in Hz")
        f = _key(z, "f", path)
        if f.ndim != 1 or f.size < 3:
            raise InputError(f"{path}: key 'f' must have shape (F,) with F >= 3, got {f.shape}")
        _finite(f, "f", path, "(F,)")
        if np.any(np.diff(f) <= 0):
            raise InputError(f"{path}: key 'f' must be strictly increasing (Hz)")
        H = _key(z, "H", path)
        if H.shape != (3, 3, f.size):
            raise InputError(f"{path}: key 'H' must have shape (3, 3, {f.size}), got {H.shape}")
        _finite(H, "H", path, "(3, 3, F)")
        H0 = None
        if "H0" in keys:
            H0 = _key(z, "H0", path)
            if H0.shape != (3, f.size):
                raise InputError(f"{path}: key 'H0' must have shape (3, {f.size}), got {H0.shape}")
            _finite(H0, "H0", path, "(3, F)")
            H0 = H0.astype(np.complex128)
        gd = GirfData(
            f_hz=f.astype(np.float64),
            H=H.astype(np.complex128),
            H0=H0,
            source=text.get("source") or str(path),
            notes=notes,
        )
        gd.to_time_domain()  # validates the grid now (one-line error naming 'f')
        return gd
    raise InputError(f"{path}: not a GIRF file: needs key 'h' (3, 3, L) with 'dt', or 'H' (3, 3, F) with 'f'")


def load_girf(path: str | os.PathLike) -> GirfData:
    """Read and validate a contract GIRF ``.npz`` (one-line InputError naming the key on failure)."""
    p = Path(path)
    if p.is_dir():
        raise InputError(f"{p}: is a directory, expected a GIRF .npz file")
    if not p.is_file():
        raise InputError(f"{p}: GIRF file not found")
    if p.suffix.lower() == ".mat":
        raise InputError(f"{p}: a MATLAB file; convert it first with 'dtoc girf import {p.name} -o h.npz'")
    try:
        with np.load(p, allow_pickle=False) as z:
            return validate_girf_arrays(z, str(p))
    except InputError:
        raise
    except Exception as e:  # noqa: BLE001 - not an npz at all
        raise InputError(f"{p}: not a readable .npz GIRF file ({type(e).__name__})") from None


def save_girf(girf: GirfData, path: str | os.PathLike, force: bool = False) -> Path:
    """Write the contract ``.npz`` atomically and deterministically."""
    return save_npz(path, girf.arrays(), force=force)
