"""Estimate a 3x3 GIRF (+ B0 row) from measured input/output pairs (measurement contract, docs/contracts.md §1).

Per frequency f and output o (x, y, z, and b0 when measured), the row ``H[o, :]`` (1 x 3) minimises

    sum_m |O_o(f, m) - sum_i H[o, i](f) I_i(f, m)|^2 + lambda |H[o, :]|^2

over the waveforms m whose output o was measured, i.e. ``H[o, :] = (sum_m O I^H) (sum_m I I^H + lambda 1)^-1``
(the multi-input form of the classic ``H = sum O I* / (sum |I|^2 + lambda)``; it equals that formula when
each waveform drives one axis).  ``I`` and ``O`` are DFTs of the demanded and measured series, zero-padded to
at least twice their length so that the circular convolution of the DFT equals the linear one for
responses shorter than the record.  ``lambda = reg * max_f mean_i S_ii(f)`` (``S_ii`` the input power
summed over waveforms): the fit falls back smoothly to zero where the inputs carry no energy.

Options: ``fmax_hz`` (frequency window: H is multiplied by a cosine taper from ``0.8 fmax`` to zero at
``fmax``; beyond it H = 0), ``time_window_s`` = (t_min, t_max) (taps outside are dropped; default: the
record length centred on 0, i.e. ``(-N dt / 2, N dt / 2)``).  The measured G is used when present, else G
derived from k by central differences (:func:`dtoc.hardware.measurement.G_from_k`).

The result is a time-domain :class:`GirfData` on the measurement's ``dt`` with ``t0 = -(number of
non-causal taps) * dt``.
"""

from __future__ import annotations

import numpy as np
import scipy.fft

from dtoc.errors import InputError
from dtoc.hardware.girf_io import GirfData
from dtoc.hardware.measurement import Measurement


def _describe_source(source: str | None) -> str:
    """File name and content hash of the measurement (independent of the working directory)."""
    from pathlib import Path

    if not source:
        return "measurement"
    p = Path(source)
    if p.is_file():
        from dtoc.util.atomic import sha256_file

        return f"{p.name} (sha256 {sha256_file(p)[:16]})"
    return p.name


def _taper(f: np.ndarray, fmax_hz: float | None) -> np.ndarray:
    if fmax_hz is None:
        return np.ones_like(f)
    af = np.abs(f)
    f0 = 0.8 * fmax_hz
    w = np.ones_like(f)
    mid = (af > f0) & (af < fmax_hz)
    w[mid] = 0.5 * (1 + np.cos(np.pi * (af[mid] - f0) / (fmax_hz - f0)))
    w[af >= fmax_hz] = 0.0
    return w


def _solve_rows(I: np.ndarray, O: np.ndarray, use: np.ndarray, lam: float) -> np.ndarray:
    """I (M, 3, F), O (M, F), use (M,) bool -> H row (3, F)."""
    Iu, Ou = I[use], O[use]
    S = np.einsum("mif,mjf->fij", Iu, Iu.conj())  # (F, 3, 3)  sum I I^H
    R = np.einsum("mf,mjf->fj", Ou, Iu.conj())  # (F, 3)     sum O I^H
    S = S + lam * np.eye(3)[None]
    # row = R S^-1  <=>  S^T row^T = R^T
    row = np.linalg.solve(np.transpose(S, (0, 2, 1)), R[..., None])[..., 0]
    return row.T


#: Fewest samples per waveform a GIRF fit accepts.
MIN_FIT_SAMPLES = 32


def fit_girf(
    meas: Measurement,
    reg: float = 1e-6,
    fmax_hz: float | None = None,
    time_window_s: tuple[float, float] | None = None,
    fit_b0: bool = True,
) -> GirfData:
    """Regularised least-squares GIRF from a :class:`Measurement` (see module docstring).

    Args:
        meas: validated measurement (M waveforms, 3 axes, N samples at ``dt``).
        reg: relative Tikhonov weight (dimensionless, > 0).
        fmax_hz: frequency window (None: up to Nyquist).
        time_window_s: (t_min, t_max) of the kept taps, s.
        fit_b0: also fit the B0 row when the file has ``b0``.
    Returns:
        Time-domain :class:`GirfData` (``h`` (3, 3, L), ``h0`` (3, L) or None) on ``meas.dt_s``.
    """
    if not (reg > 0 and np.isfinite(reg)):
        raise InputError(f"--reg must be > 0, got {reg}")
    M, _, N = meas.g.shape
    if N < MIN_FIT_SAMPLES:
        raise InputError(
            f"the measurement has {N} samples per waveform; a GIRF fit needs at least {MIN_FIT_SAMPLES} "
            "(its frequency resolution is 1 / (N dt))"
        )
    dt = meas.dt_s
    Gm = meas.realized_G()
    nfft = scipy.fft.next_fast_len(2 * N)
    f = np.fft.fftfreq(nfft, dt)
    I = np.fft.fft(meas.g, n=nfft, axis=-1)  # (M, 3, F)
    lam = reg * float(np.max(np.mean(np.sum(np.abs(I) ** 2, axis=0), axis=0)))
    w = _taper(f, fmax_hz)
    # where the weakest driven input axis carries less than 10x lambda, the fit is pulled towards 0 by the
    # regularisation (bias > ~10 %): report the band in which the fitted H is supported by the data
    S_axis = np.sum(np.abs(I) ** 2, axis=0)  # (3, F)
    driven = [a for a in range(3) if np.any(meas.g[:, a])]
    supported = np.min(S_axis[driven], axis=0) >= 10 * lam if driven else np.zeros(nfft, bool)
    pos = (f >= 0) & ~supported
    f_sup = float(np.min(f[pos])) if pos.any() else float(np.max(f))
    undriven = [("x", "y", "z")[a] for a in range(3) if a not in driven]
    H = np.zeros((3, 3, nfft), dtype=np.complex128)
    src = _describe_source(meas.source)
    notes = [
        f"fitted from {src}: {M} waveforms, dt {dt:.6g} s, reg {reg:g} (lambda {lam:.3g}), "
        f"fmax {'Nyquist' if fmax_hz is None else f'{fmax_hz:g} Hz'}",
        f"data support the fit up to {f_sup:.6g} Hz (input power of every driven axis >= 10 lambda); "
        "above it H is pulled towards 0 by the regularisation: use broadband inputs (triangles, chirps)",
    ]
    if undriven:
        notes.append(f"input axis {','.join(undriven)} never driven: its column of H is 0 (not identifiable)")
    for o in range(3):
        use = meas.axes_measured[:, o]
        if not use.any():
            raise InputError(f"{meas.source}: axis {'xyz'[o]} is never measured; cannot fit its GIRF row")
        O = np.fft.fft(np.nan_to_num(Gm[:, o]), n=nfft, axis=-1)
        H[o] = _solve_rows(I, O, use, lam) * w
    H0 = None
    if fit_b0 and meas.b0 is not None:
        O = np.fft.fft(meas.b0, n=nfft, axis=-1)
        H0 = _solve_rows(I, O, np.ones(M, dtype=bool), lam) * w
    taps = np.fft.fftshift(np.fft.ifft(H, axis=-1).real, axes=-1)
    taps0 = None if H0 is None else np.fft.fftshift(np.fft.ifft(H0, axis=-1).real, axes=-1)
    t = (np.arange(nfft) - nfft // 2) * dt
    tmin, tmax = time_window_s if time_window_s is not None else (-0.5 * N * dt, 0.5 * N * dt)
    if not tmin < tmax:
        raise InputError(f"time window must have t_min < t_max, got ({tmin}, {tmax})")
    keep = (t >= tmin - 1e-12) & (t <= tmax + 1e-12)
    if not keep.any():
        raise InputError(f"time window ({tmin}, {tmax}) s keeps no taps")
    k0 = int(np.flatnonzero(keep)[0])
    return GirfData(
        dt_s=dt,
        t0_s=float(t[k0]),
        h=taps[..., keep],
        h0=None if taps0 is None else taps0[..., keep],
        source=f"dtoc girf fit {src}",
        notes=notes,
    )
