"""Import published GIRF files (MATLAB v5 or v7.3/HDF5) into the contract format (:class:`GirfData`).

Recognised layouts (the three in ``../shared/data/girf`` and files laid out like them):

1. **Per-term time-domain kernels** (KCL 7 T 2023 / 2024): variables ``h<i><o>`` (``hxy`` = response on
   **y** to input on **x**, as the publishing group's code uses them) with a time axis ``t`` (s).  Complex
   storage with negligible imaginary parts is reduced to the real part (the largest dropped imaginary
   part is recorded in ``notes``).  ``dt = (t[-1] - t[0]) / (L - 1)`` (10.0067 us for the 2023 file),
   ``t0 = t[0]`` (centred, non-causal kernels; the bulk delay was removed by the publishers and is *not*
   re-added).  Axes without data (the 2023 file has no z) get an **ideal** response: a unit tap at
   t = 0 on the missing self term, zero cross terms to and from it; this is stated in ``notes``.
2. **Frequency-domain 3x3 struct** (KCL 2024 ``GMTF``): ``GMTF1<i><o>`` first-order terms and
   ``GMTF0<i>`` zeroth-order (B0) terms on ``freq`` (Hz).  Imported as a frequency-domain GIRF (converted
   to taps on use).  Its phase equals that of the time-domain 2024 file times exp(+2 pi i f 10 us): the
   struct's ``info`` says a -10 us ADC/gradient shift was added.  That shift belongs to the publishers'
   ADC timing convention, not to the gradient chain, so the importer **undoes the shift the ``info``
   declares** (delays the response by 10 us; the result matches ``7T_GIRF.mat`` of the same scanner);
   ``as_published=True`` keeps the file's phase.  ``info`` and ``GRDdelays_us`` (not applied) go to ``notes``.
   The B0 term's unit is undocumented: it is imported as given and flagged in ``notes``.
3. **Siemens/GIRFReco per-axis HDF5** (Prisma 3 T 2020, ``GIRF_{X,Y,Z}.mat``): ``GIRF_FT`` self term and
   ``b0ec_FT`` B0 term on a frequency axis ``freq`` in **kHz**.  The stored ``freq`` vector is a linspace
   that misses f = 0 by half a bin; the data are the standard ``fftshift`` DFT bins ``(k - N/2) df`` with
   ``df = 2 * max|freq| / N`` (verified: the bin N/2 is real and the rest Hermitian about it).  Sample 0
   (the -Nyquist bin) is an underflow and is set to zero; the N-point grid is kept, so the taps are
   exactly ``1 / (N df)`` = 5 us apart.  Beyond the band of the file's own ``GIRF_Temporal`` (|f| <= 63.4 kHz
   for the Prisma files) ``GIRF_FT`` is measurement noise (|H| up to ~3e3 near 100 kHz) and would
   dominate the taps; the response is set to zero there, exactly as the publishers' time-domain kernel.  Cross terms
   are zero (not measured).  The system delays (~4-8 us) are **kept** (not removed).  The B0 term unit is
   undocumented (GIRFReco.jl treats its prediction as a k0 phase in rad): imported only when
   ``include_b0=True`` and flagged in ``notes``.

``shift_s`` (default 0) adds a pure delay to every term (positive = later).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from dtoc.constants import AXES
from dtoc.errors import InputError
from dtoc.hardware.girf_io import GirfData


def _loadmat(path: Path) -> dict:
    import scipy.io

    try:
        return scipy.io.loadmat(str(path), squeeze_me=True, struct_as_record=False)
    except NotImplementedError:  # v7.3
        return {}
    except Exception as e:  # noqa: BLE001
        raise InputError(f"{path}: not a readable MATLAB file ({type(e).__name__})") from None


def _h5_complex(ds) -> np.ndarray:
    a = np.asarray(ds)
    if a.dtype.names and {"real", "imag"} <= set(a.dtype.names):
        return (a["real"] + 1j * a["imag"]).ravel()
    return a.ravel().astype(np.complex128)


def _import_time_terms(m: dict, path: Path, allow_partial: bool = False) -> GirfData:
    t = np.asarray(m["t"], dtype=np.float64).ravel()
    L = t.size
    if L < 2 or np.any(np.diff(t) <= 0):
        raise InputError(f"{path}: variable 't' must be an increasing time axis (s)")
    dt = (t[-1] - t[0]) / (L - 1)
    if np.max(np.abs(np.diff(t) - dt)) > 1e-6 * dt:
        raise InputError(f"{path}: variable 't' must be uniformly spaced")
    h = np.zeros((3, 3, L))
    have = np.zeros((3, 3), dtype=bool)
    max_imag = 0.0
    for i, ai in enumerate(AXES):
        for o, ao in enumerate(AXES):
            name = f"h{ai}{ao}"
            if name in m:
                v = np.asarray(m[name]).ravel()
                if v.size != L:
                    raise InputError(f"{path}: variable {name!r} must have {L} samples like 't', got {v.size}")
                if not np.all(np.isfinite(v)):
                    raise InputError(f"{path}: variable {name!r} contains NaN or inf")
                if np.iscomplexobj(v):
                    max_imag = max(max_imag, float(np.abs(v.imag).max()))
                h[o, i] = v.real
                have[o, i] = True
    notes = [
        f"per-term time-domain kernels h<in><out> from {path.name}: h[o, i] = h{{i}}{{o}} (hxy = response on y to input on x)",
        f"dt = {dt:.9g} s from t, t0 = t[0] = {t[0]:.9g} s (centred kernel); bulk delay as published (removed), not re-added",
    ]
    if max_imag:
        notes.append(f"complex kernels reduced to real part (largest |imag| {max_imag:.3g})")
    missing = [AXES[a] for a in range(3) if not have[a, a]]
    _partial(path, missing, allow_partial)
    i0 = int(np.argmin(np.abs(t)))
    if abs(t[i0]) > 1e-3 * dt and missing:
        raise InputError(f"{path}: no tap at t = 0 to place the ideal response of missing axis {missing}")
    for a in range(3):
        if not have[a, a]:
            h[a, a, i0] = 1.0
    if missing:
        notes.append(
            f"axis {','.join(missing)} not in the file: ideal response (unit tap at t=0), no cross terms to/from it"
        )
    return GirfData(dt_s=float(dt), t0_s=float(t[0]), h=h, source=path.name, notes=notes)


def gmtf_convention_shift_s(info: str | None) -> float:
    """The ADC/gradient shift a GMTF struct's ``info`` declares ("Added -10us shift to ADC wrt GRD"), s."""
    import re

    if not info:
        return 0.0
    m = re.search(r"added\s*([+-]?\d+(?:\.\d+)?)\s*us\s*shift", str(info), flags=re.IGNORECASE)
    return float(m.group(1)) * 1e-6 if m else 0.0


def _import_gmtf(s, path: Path, include_b0: bool, as_published: bool = False) -> GirfData:
    f = np.asarray(s.freq, dtype=np.float64).ravel()
    F = f.size
    H = np.zeros((3, 3, F), dtype=np.complex128)
    for i, ai in enumerate(AXES):
        for o, ao in enumerate(AXES):
            name = f"GMTF1{ai}{ao}"
            if not hasattr(s, name):
                raise InputError(f"{path}: struct GMTF lacks field {name!r}")
            H[o, i] = np.asarray(getattr(s, name)).ravel()
    H0 = None
    notes = [f"GMTF struct from {path.name}: frequency domain, H[o, i] = GMTF1{{i}}{{o}}, f from 'freq' (Hz)"]
    info = str(s.info) if hasattr(s, "info") else None
    if info:
        notes.append(f"info: {info}")
    undo = -gmtf_convention_shift_s(info)
    if undo and not as_published:
        notes.append(
            f"the declared ADC/gradient convention shift is undone: delayed by {undo * 1e6:g} us, so that "
            "the response is on the gradient's own clock (matches the group's time-domain 7T_GIRF.mat)"
        )
    elif undo:
        notes.append("phase kept as published (includes the declared ADC/gradient convention shift)")
    if hasattr(s, "GRDdelays_us"):
        notes.append(f"GRDdelays_us = {np.asarray(s.GRDdelays_us).ravel().tolist()} (recorded, not applied)")
    if include_b0:
        H0 = np.stack([np.asarray(getattr(s, f"GMTF0{a}")).ravel() for a in AXES]).astype(np.complex128)
        notes.append("H0 from GMTF0x/y/z: unit undocumented, imported as given (assumed uT per mT/m)")
    if not np.all(np.isfinite(H)) or (H0 is not None and not np.all(np.isfinite(H0))):
        raise InputError(f"{path}: GMTF contains NaN or inf")
    if undo and not as_published:
        ph = np.exp(-2j * np.pi * f * undo)
        H = H * ph
        H0 = None if H0 is None else H0 * ph
    return GirfData(f_hz=f, H=H, H0=H0, source=path.name, notes=notes)


def _import_prisma_axis(path: Path):
    """(f (N,) Hz, H (N,), H0 (N,) or None, band_hz or None) of one GIRFReco-style HDF5 file."""
    import h5py

    try:
        z = h5py.File(path, "r")
    except Exception as e:  # noqa: BLE001
        raise InputError(f"{path}: not a readable MATLAB v7.3 (HDF5) file ({type(e).__name__})") from None
    with z:
        for key in ("GIRF_FT", "freq"):
            if key not in z:
                raise InputError(f"{path}: HDF5 GIRF file lacks variable {key!r}")
        H = _h5_complex(z["GIRF_FT"])
        fk = np.asarray(z["freq"], dtype=np.float64).ravel()
        b0 = _h5_complex(z["b0ec_FT"]) if "b0ec_FT" in z else None
        ht = _h5_complex(z["GIRF_Temporal"]) if "GIRF_Temporal" in z else None
    N = H.size
    if fk.size != N or N % 2 or N < 8:
        raise InputError(f"{path}: 'GIRF_FT' and 'freq' must have the same even length")
    if not np.all(np.isfinite(fk)) or np.max(np.abs(fk)) <= 0:
        raise InputError(f"{path}: 'freq' must be a finite frequency axis in kHz")
    fmax_hz = np.max(np.abs(fk)) * 1e3  # kHz -> Hz
    df = 2 * fmax_hz / N
    c = N // 2
    Hs = H[1:]  # without the underflow sample 0 (the -Nyquist bin)
    if not np.all(np.isfinite(Hs)):
        raise InputError(f"{path}: 'GIRF_FT' contains NaN or inf")
    herm = np.max(np.abs(Hs - np.conj(Hs[::-1]))) / max(np.max(np.abs(Hs[c - 50 : c + 50])), 1e-30)
    if herm > 1e-6 or abs(H[c].imag) > 1e-9 * abs(H[c]):
        raise InputError(f"{path}: 'GIRF_FT' is not Hermitian about bin N/2; unknown layout")
    # keep the full N-point DFT grid (dt = 1 / (N df) exactly), with the underflow -Nyquist bin set to 0
    f = (np.arange(N) - c) * df
    H = H.copy()
    H[0] = 0.0
    b0 = None if b0 is None else np.where(np.arange(N) == 0, 0.0, np.nan_to_num(b0, nan=0.0, posinf=0.0, neginf=0.0))
    band = None
    if ht is not None and ht.size == N and np.all(np.isfinite(ht)):
        # the publishers' own time-domain kernel is GIRF_FT restricted to a band; beyond it GIRF_FT is
        # measurement noise (|H| up to ~3e3 near 100 kHz): use the same band (symmetric about f = 0)
        spec = np.abs(np.fft.fftshift(np.fft.fft(np.fft.ifftshift(ht))))
        sup = np.flatnonzero(spec > 1e-9 * spec.max())
        if sup.size and sup[0] < c < sup[-1]:
            nb = int(min(c - sup[0], sup[-1] - c))
            if nb < c - 1:
                band = nb * df
                out = np.abs(np.arange(N) - c) > nb
                H[out] = 0.0
                if b0 is not None:
                    b0[out] = 0.0
    return f, H, b0, band


def import_girf(
    files: list[str | os.PathLike],
    include_b0: bool = False,
    shift_s: float = 0.0,
    as_published: bool = False,
    allow_partial: bool = False,
) -> GirfData:
    """Read one published GIRF (one file, or the per-axis X/Y/Z files) into :class:`GirfData`.

    Args:
        files: MATLAB files of one GIRF (layouts in the module docstring).
        include_b0: import the zeroth-order (B0) term when present (off by default: in the published
            files its unit is undocumented, so it is only imported on request and flagged).
        shift_s: extra pure delay added to every term, s (positive = later).
        as_published: keep a GMTF's declared ADC/gradient convention shift in its phase (default: undo it).
        allow_partial: accept a GIRF that lacks an axis, giving that axis an ideal response (default:
            refuse it with one line: a scanner's missing axis is not ideal, it is unmeasured).
    Raises:
        InputError: unreadable or malformed files; a partial GIRF without ``allow_partial``.
    """
    paths = [Path(f) for f in files]
    if not paths:
        raise InputError("no GIRF file given")
    for p in paths:
        if p.is_dir():
            raise InputError(f"{p}: is a directory, expected a MATLAB .mat GIRF file")
        if not p.is_file():
            raise InputError(f"{p}: file not found")
        if p.suffix.lower() == ".npz":
            raise InputError(
                f"{p}: already a .npz: dtoc GIRF files need no import (use it with --girf; 'dtoc girf show' checks it)"
            )
        if p.stat().st_size == 0:
            raise InputError(f"{p}: empty file")
    if len(paths) == 1:
        m = _loadmat(paths[0])
        if "GMTF" in m:
            gd = _import_gmtf(m["GMTF"], paths[0], include_b0, as_published)
        elif m and "t" in m and any(k.startswith("h") and len(k) == 3 for k in m):
            gd = _import_time_terms(m, paths[0], allow_partial)
        elif not m:
            gd = _import_prisma([paths[0]], include_b0, allow_partial)
        else:
            raise InputError(
                f"{paths[0]}: unknown GIRF layout (expected h<in><out> + t, a GMTF struct, or GIRF_FT + freq)"
            )
    else:
        gd = _import_prisma(paths, include_b0, allow_partial)
    if shift_s:
        gd = _shift(gd, shift_s)
    return gd


def _prisma_axis_of(p: Path) -> int:
    stem = p.stem.upper()
    for a, name in enumerate("XYZ"):
        if stem.endswith("_" + name) or stem == name:
            return a
    raise InputError(f"{p}: cannot tell the axis from the name (expected ..._X/_Y/_Z.mat)")


def _partial(where, missing: list[str], allow_partial: bool) -> None:
    """Refuse a GIRF without some axes unless the user asked for ideal ones (--partial)."""
    if missing and not allow_partial:
        ax = ",".join(missing)
        raise InputError(
            f"{where}: axis {ax} is not in the GIRF (a partial measurement); pass --partial to import it with an "
            f"ideal {ax} (unit response, no cross terms), which the scanner's {ax} axis is not"
        )


def _import_prisma(paths: list[Path], include_b0: bool, allow_partial: bool = False) -> GirfData:
    got: dict[int, tuple] = {}
    for p in paths:
        if _loadmat(p):  # a MATLAB v5 file among per-axis HDF5 files
            raise InputError(
                f"{p}: several files are only accepted as per-axis HDF5 GIRF_X/Y/Z.mat files; import it alone"
            )
        data = _import_prisma_axis(p)  # checks the layout before the name
        a = _prisma_axis_of(p)
        if a in got:
            raise InputError(f"{p}: axis {AXES[a]} given twice")
        got[a] = data
    f = None
    for fa, _, _, _ in got.values():
        if f is None:
            f = fa
        elif fa.shape != f.shape or np.max(np.abs(fa - f)) > 1e-6 * np.max(np.abs(f)):
            raise InputError("per-axis GIRF files have different frequency axes")
    F = f.size
    H = np.zeros((3, 3, F), dtype=np.complex128)
    H0 = np.zeros((3, F), dtype=np.complex128) if include_b0 else None
    for a in range(3):
        if a in got:
            H[a, a] = got[a][1]
            if include_b0 and got[a][2] is not None:
                H0[a] = got[a][2]
        else:
            H[a, a] = 1.0  # ideal: unit response, zero delay
    notes = [
        f"per-axis HDF5 files {', '.join(p.name for p in paths)}: self terms only (cross terms zero, not measured)",
        f"frequency axis rebuilt as fftshift DFT bins, df = {f[1] - f[0]:.6g} Hz (tap spacing "
        f"{1 / (f.size * (f[1] - f[0])):.6g} s); underflow sample 0 (-Nyquist bin) set to 0",
        "system delays kept (not removed)",
    ]
    bands = sorted({g[3] for g in got.values() if g[3] is not None})
    if bands:
        notes.append(
            f"band-limited to |f| <= {bands[0]:.6g} Hz, the band of the files' own GIRF_Temporal "
            "(beyond it GIRF_FT is measurement noise)"
        )
        if len(bands) > 1:
            for a in got:
                got[a][1][np.abs(f) > bands[0]] = 0.0
                if got[a][2] is not None:
                    got[a][2][np.abs(f) > bands[0]] = 0.0
    missing = [AXES[a] for a in range(3) if a not in got]
    _partial(", ".join(p.name for p in paths), missing, allow_partial)
    if missing:
        notes.append(f"axis {','.join(missing)} not given: ideal unit response")
    if include_b0:
        notes.append(
            "H0 from b0ec_FT: unit undocumented (GIRFReco.jl treats it as a k0 phase in rad), imported as given"
        )
    if not np.all(np.isfinite(H)):
        raise InputError("per-axis GIRF files contain NaN or inf")
    return GirfData(f_hz=f, H=H, H0=H0, source=", ".join(p.name for p in paths), notes=notes)


def _shift(gd: GirfData, shift_s: float) -> GirfData:
    if gd.is_time_domain:
        return GirfData(
            dt_s=gd.dt_s,
            t0_s=gd.t0_s + shift_s,
            h=gd.h,
            h0=gd.h0,
            source=gd.source,
            notes=gd.notes + [f"added delay {shift_s:.6g} s"],
        )
    ph = np.exp(-2j * np.pi * gd.f_hz * shift_s)
    return GirfData(
        f_hz=gd.f_hz,
        H=gd.H * ph,
        H0=None if gd.H0 is None else gd.H0 * ph,
        source=gd.source,
        notes=gd.notes + [f"added delay {shift_s:.6g} s"],
    )
