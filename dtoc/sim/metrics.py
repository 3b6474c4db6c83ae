"""Image and k-space quality metrics, defined once (docs/metrics.md).

All image metrics take images reconstructed by :func:`dtoc.sim.recon.reconstruct` on the same grid;
they accept numpy arrays or torch tensors and return torch scalars (differentiable where it makes
sense: :func:`nrmse` is the optimizer's image loss) -- use ``float(...)`` for reports.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from dtoc.util.cplx import cabs


def _t(x) -> torch.Tensor:
    return x if isinstance(x, torch.Tensor) else torch.as_tensor(np.asarray(x))


def nrmse(image, ideal) -> torch.Tensor:
    """The paper's normalised RMS error ``||abs(I) - abs(I0)||_2 / ||abs(I0)||_2``.

    Magnitude images, no rescaling (both from the same reconstruction of the same phantom), the
    2-norm over all pixels (and leading batch dims).  0 when ``image`` equals ``ideal``; 1 for an
    empty image (an all-zero ``ideal`` is guarded by a 1e-30 floor on the
    denominator).  Returned as a fraction (multiply by 100 for %).

    Args:
        image: (..., ny, nx) realized image, complex or magnitude.
        ideal: (..., ny, nx) target image I0 from ideal hardware.
    """
    a = cabs(_t(image))
    b = cabs(_t(ideal)).to(a.dtype)
    return torch.linalg.vector_norm(a - b) / torch.linalg.vector_norm(b).clamp_min(1e-30)


def object_mask(ideal, threshold: float = 0.1) -> np.ndarray:
    """Object region (bool (ny, nx)): pixels of the ideal magnitude image above ``threshold`` x its
    maximum, closed (3x3, two iterations: gaps of up to ~4 pixels in the outline are bridged) and with
    the holes filled (every pixel enclosed by the object belongs to it).

    Closing and filling matter for T2*-weighted images: a long-TE EPI of the brain at 7 T has a bright
    rim (fat) and bright CSF, but white and grey matter below 10 % of the maximum and, at the longest
    echo train, gaps in the rim; without them that tissue lay outside the "object" and, where the
    N/2-shifted head covers it, inside the ghost region, so the ideal image itself scored
    2.36 / 1.60 / 1.04 % "ghost" at echo spacings 1.89 / 2.25 / 2.61 ms (0.23 / 0.31 / 0.61 % now).
    """
    from scipy import ndimage

    m = np.abs(_t(ideal).detach().cpu().numpy())
    thr = m > threshold * m.max()
    pad = 3  # closing must not erode at the image border (scipy treats outside as background)
    obj = ndimage.binary_closing(np.pad(thr, pad), structure=np.ones((3,) * m.ndim, dtype=bool), iterations=2)
    obj = obj[tuple(slice(pad, -pad) for _ in range(m.ndim))] | thr
    return ndimage.binary_fill_holes(obj)


def ghost_mask(obj: np.ndarray, phase_dim: int = -2) -> np.ndarray:
    """N/2 (Nyquist) ghost region: the object mask circularly shifted by N/2 along the phase axis, minus the object.

    Args:
        obj: (ny, nx) bool object mask.
        phase_dim: array dimension of the phase-encoding direction (-2 = rows = y, the shipped specs).
    """
    n = obj.shape[phase_dim]
    return np.roll(obj, n // 2, axis=phase_dim) & ~obj


def ghost_ratio(image, ideal, *, phase_dim: int = -2, threshold: float = 0.1) -> torch.Tensor:
    """EPI ghost-to-signal ratio: energy in the N/2 ghost region / energy in the object region.

    ``sum_{ghost} |I|^2 / sum_{object} |I|^2`` with object = ``abs(I0) > threshold * max abs(I0)`` and
    ghost = object shifted by N/2 along phase minus the object (:func:`ghost_mask`); both regions are
    defined from the *ideal* image so that the ratio of every realized image is measured on the same
    pixels.  Dimensionless (x 100 for %); the ideal image itself scores its Gibbs ringing only.
    """
    img = _t(image)
    obj = object_mask(ideal, threshold)
    gh = ghost_mask(obj, phase_dim)
    p = cabs(img) ** 2
    o = torch.as_tensor(obj, device=p.device)
    g = torch.as_tensor(gh, device=p.device)
    return (p * g).sum() / (p * o).sum()


#: below this largest flip angle, rad (5.7e-5 deg), a sequence excites nothing an image figure could measure
NO_EXCITATION_FLIP_RAD = 1e-6


def no_signal_reason(ideal, rf_flips_rad=None) -> str | None:
    """Why the image figures of ``ideal`` would mean nothing, or None: no RF pulse flips more than
    :data:`NO_EXCITATION_FLIP_RAD` (field-camera protocols carry RF of ~1e-100 deg: both images are empty and an
    NRMSE of 0 % would look perfect), or the ideal image is empty (no signal reaches the ADC samples)."""
    flips = [abs(float(f)) for f in (rf_flips_rad or [])]
    if rf_flips_rad is not None and (not flips or max(flips) < NO_EXCITATION_FLIP_RAD):
        top = f"{np.degrees(max(flips)):.3g} deg" if flips else "none"
        return f"no signal: the largest RF flip angle is {top}, nothing is excited (images empty, no image figures)"
    a = cabs(_t(ideal))
    n = float(torch.linalg.vector_norm(a))
    if not np.isfinite(n) or n <= 1e-30:
        return "no signal: the ideal image is empty (no image figures)"
    return None


def image_metrics(image, ideal, *, epi: bool, phase_dim: int = -2, rf_flips_rad=None) -> dict:
    """The image figures every report prints: ``nrmse``, and for an EPI ``ghost_ratio`` of the image and
    ``ghost_ratio_ideal`` of the ideal image itself (its Gibbs ringing and T2* blurring along the echo
    train: the floor no gradient correction can go below); None for the ghost keys otherwise.  Floats.
    Where the images carry no signal (:func:`no_signal_reason`, ``rf_flips_rad``: the sequence's flip angles),
    every figure is None and ``image_reason`` says why."""
    reason = no_signal_reason(ideal, rf_flips_rad)
    if reason is not None:
        return {"nrmse": None, "ghost_ratio": None, "ghost_ratio_ideal": None, "image_reason": reason}
    out: dict = {"nrmse": float(nrmse(image, ideal)), "ghost_ratio": None, "ghost_ratio_ideal": None}
    if epi:
        out["ghost_ratio"] = float(ghost_ratio(image, ideal, phase_dim=phase_dim))
        out["ghost_ratio_ideal"] = float(ghost_ratio(ideal, ideal, phase_dim=phase_dim))
    return out


def kspace_errors(k_rad_per_m, k0_rad_per_m, dk_rad_per_m=None, mask=None) -> dict:
    """k-space deviation of realized from nominal samples.

    Args:
        k_rad_per_m: (3, N) realized k at the ADC samples, rad/m.
        k0_rad_per_m: (3, N) nominal k, rad/m.
        dk_rad_per_m: (3,) grid steps 2 pi / FOV (inf or None: axis not reported in dk).
        mask: (N,) bool samples to include (default all).
    Returns:
        dict with ``kspace_rmse_rad_per_m`` = sqrt(mean_i |k_i - k0_i|^2) (Euclidean norm over the
        three axes, mean over samples), ``kspace_max_err_rad_per_m`` = max_i |k_i - k0_i|, and
        ``kspace_max_err_dk`` = max over samples and axes of |k - k0| / dk (None without dk), all floats.
    """
    k = np.asarray(_t(k_rad_per_m).detach().cpu().numpy(), dtype=np.float64)
    k0 = np.asarray(_t(k0_rad_per_m).detach().cpu().numpy(), dtype=np.float64)
    if mask is not None:
        m = np.asarray(mask, dtype=bool)
        k, k0 = k[:, m], k0[:, m]
    if k.shape[1] == 0:
        return {
            "kspace_rmse_rad_per_m": 0.0,
            "kspace_max_err_rad_per_m": 0.0,
            "kspace_max_err_dk": 0.0 if dk_rad_per_m is not None else None,
        }
    e = k - k0
    norm = np.sqrt((e**2).sum(0))
    out: dict[str, float | None] = {
        "kspace_rmse_rad_per_m": float(np.sqrt(np.mean(norm**2))),
        "kspace_max_err_rad_per_m": float(norm.max()),
    }
    if dk_rad_per_m is None:
        out["kspace_max_err_dk"] = None
    else:
        dk = np.asarray(dk_rad_per_m, dtype=np.float64).reshape(-1)
        fin = np.isfinite(dk) & (dk > 0)
        out["kspace_max_err_dk"] = float((np.abs(e[fin]) / dk[fin, None]).max()) if fin.any() else None
    return out


def kspace_within(k_rad_per_m, k0_rad_per_m, dk_rad_per_m, tol_dk: float = 0.5) -> np.ndarray:
    """(N,) bool: samples whose realized k is within ``tol_dk`` grid steps of nominal on every finite-dk axis.

    The paper discards ("skips") samples that miss their target; this is the mask to pass as ``keep_mask``.
    """
    k = np.asarray(_t(k_rad_per_m).detach().cpu().numpy(), dtype=np.float64)
    k0 = np.asarray(_t(k0_rad_per_m).detach().cpu().numpy(), dtype=np.float64)
    dk = np.asarray(dk_rad_per_m, dtype=np.float64).reshape(-1)
    fin = np.isfinite(dk) & (dk > 0)
    return np.all(np.abs(k[fin] - k0[fin]) <= tol_dk * dk[fin, None], axis=0)


#: Internal figure name -> (report key, scale).  Internal image figures are fractions; reports give %.
REPORT_KEYS: dict[str, tuple[str, float]] = {
    "nrmse": ("nrmse_percent", 100.0),
    "ghost_ratio": ("ghost_ratio_percent", 100.0),
    "ghost_ratio_ideal": ("ghost_ratio_ideal_percent", 100.0),
    "ghost_ratio_excess": ("ghost_ratio_excess_percent", 100.0),
    "kspace_rmse_rad_per_m": ("kspace_rms_error_rad_per_m", 1.0),
    "kspace_max_err_rad_per_m": ("kspace_max_error_rad_per_m", 1.0),
    "kspace_max_err_dk": ("kspace_max_error_dk", 1.0),
    "kspace_max_dk": ("kspace_max_error_dk", 1.0),
    "kspace_rmse_kept_rad_per_m": ("kspace_rms_error_kept_rad_per_m", 1.0),
    "kspace_max_kept_dk": ("kspace_max_error_kept_dk", 1.0),
    "samples_discarded": ("n_samples_discarded", 1.0),
}


def report_figures(figures: dict[str, Any]) -> dict[str, Any]:
    """Internal figures -> report keys with units (:data:`REPORT_KEYS`); private ('_') keys dropped, others kept."""
    out: dict[str, Any] = {}
    for k, v in figures.items():
        if k.startswith("_"):
            continue
        key, scale = REPORT_KEYS.get(k, (k, 1.0))
        out[key] = v * scale if isinstance(v, (int, float)) and not isinstance(v, bool) and scale != 1.0 else v
    return out
