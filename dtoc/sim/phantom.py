"""Phantoms: voxel maps of the tissue parameters the simulator needs.

The :class:`Phantom` container is the simulator's input contract; generators (the built-in brain
phantom :func:`brain_phantom`, :func:`uniform_phantom`), the ``.npz`` loader/writer
(:func:`load_phantom`, :func:`save_phantom`) and the deterministic rotation :func:`rotate` live beside it.

Geometry: a 2D phantom of shape (ny, nx) covers ``fov_m = (fov_x, fov_y)`` centred on the isocentre;
voxel (iy, ix) sits at x = (ix - nx/2) * fov_x / nx, y = (iy - ny/2) * fov_y / ny (m), the positions
a plain inverse FFT of a centred k-space grid assigns to its pixels (see :mod:`dtoc.sim.recon`).  A 3D
phantom (for 3D-encoded sequences) has maps of shape (nz, ny, nx) over ``fov_m = (fov_x, fov_y, fov_z)``,
voxel (iz, iy, ix) at z = (iz - nz/2) * fov_z / nz as well (:func:`brain_phantom_3d`).

Partial volume: a voxel holding several tissues gets PD = sum_c f_c PD_c and PD-weighted mean *rates*
(1/T1, 1/T2, 1/T2', D) -- the single-compartment approximation of the mixed signal.  The same rule is
used when the built-in phantom is area-averaged from its high-resolution label map and when a phantom
is rotated, so a phantom finer than the image never aliases and rotation does not create fake tissue.
Tissue values and their sources: docs/metrics.md ("Built-in brain phantom").
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from dtoc.constants import DEFAULT_B0_T
from dtoc.errors import InputError


@dataclass
class Phantom:
    """Tissue maps, each (ny, nx) float64 unless noted ((nz, ny, nx) for a 3D phantom).

    Attributes:
        pd: proton density (relative, >= 0).
        t1_s, t2_s, t2dash_s: relaxation times, s (> 0; use np.inf for "none").
        d_m2_per_s: isotropic diffusion coefficient, m^2/s (>= 0).
        b0_hz: off-resonance, Hz.
        b1: relative transmit field (1 = nominal flip angle).
        fov_m: (fov_x, fov_y), m ((fov_x, fov_y, fov_z) for a 3D phantom).
        coil_sens: optional (n_coils, ny, nx) ((n_coils, nz, ny, nx) in 3D) complex receive sensitivities (None = one uniform coil).
        voxel_shape: 'box' or 'sinc' or 'none': the intra-voxel signal model the simulator applies
            (a box voxel attenuates a state of dephasing k by sinc(k dx / 2pi) per axis).
    """

    pd: np.ndarray
    t1_s: np.ndarray
    t2_s: np.ndarray
    t2dash_s: np.ndarray
    d_m2_per_s: np.ndarray
    b0_hz: np.ndarray
    b1: np.ndarray
    fov_m: tuple[float, ...]
    coil_sens: np.ndarray | None = None
    voxel_shape: str = "box"

    @property
    def shape(self) -> tuple[int, ...]:
        return tuple(self.pd.shape)

    @property
    def is_3d(self) -> bool:
        """True for a (nz, ny, nx) phantom."""
        return self.pd.ndim == 3

    def axis_positions_m(self) -> tuple[np.ndarray, ...]:
        """Voxel-centre coordinates per axis, m: (x (nx,), y (ny,)) and z (nz,) for a 3D phantom."""
        n = self.shape[::-1]  # (nx, ny[, nz])
        return tuple((np.arange(n[a]) - n[a] / 2) * self.fov_m[a] / n[a] for a in range(len(n)))

    def positions_m(self) -> tuple[np.ndarray, np.ndarray]:
        """(x, y) voxel-centre coordinates, each of the maps' shape, m."""
        xyz = self.axis_positions_m()
        grids = np.meshgrid(*xyz[::-1], indexing="ij")  # ([z,] y, x)
        return grids[-1], grids[-2]

    @property
    def voxel_size_m(self) -> tuple[float, float]:
        """(dx, dy) voxel edge lengths, m."""
        ny, nx = self.shape[-2:]
        return (self.fov_m[0] / nx, self.fov_m[1] / ny)

    @property
    def voxel_size_z_m(self) -> float | None:
        """dz of a 3D phantom, m (None in 2D)."""
        return self.fov_m[2] / self.shape[0] if self.is_3d else None


MAP_KEYS = ("pd", "t1_s", "t2_s", "t2dash_s", "d_m2_per_s", "b0_hz", "b1")
#: keys a user ``.npz`` must hold; the others default to: t2dash_s inf, d_m2_per_s 0, b0_hz 0, b1 1.
REQUIRED_KEYS = ("pd", "t1_s", "t2_s", "fov_m")


# ------------------------------------------------------------------------------------------------
# Tissue table (values and sources documented in docs/metrics.md)
# ------------------------------------------------------------------------------------------------
#: Tissue classes of the built-in phantom, label order (0 = background).
TISSUES = ("background", "fat", "skull", "csf", "gm", "wm", "lesion")

#: Per field strength: tissue -> (PD, T1 s, T2 s, T2' s, D m^2/s).
TISSUE_PARAMS: dict[float, dict[str, tuple[float, float, float, float, float]]] = {
    3.0: {
        "fat": (0.90, 0.37, 0.133, 0.10, 1.0e-11),
        "skull": (0.05, 0.30, 0.010, 0.02, 0.0),
        "csf": (1.00, 4.20, 1.99, 0.50, 3.0e-9),
        "gm": (0.80, 1.33, 0.110, 0.165, 0.80e-9),
        "wm": (0.69, 0.832, 0.080, 0.157, 0.70e-9),
        "lesion": (0.85, 1.20, 0.140, 0.20, 1.10e-9),
    },
    7.0: {
        "fat": (0.90, 0.58, 0.070, 0.05, 1.0e-11),
        "skull": (0.05, 0.40, 0.006, 0.01, 0.0),
        "csf": (1.00, 4.43, 1.00, 0.25, 3.0e-9),
        "gm": (0.80, 2.13, 0.055, 0.083, 0.80e-9),
        "wm": (0.69, 1.22, 0.046, 0.065, 0.70e-9),
        "lesion": (0.85, 1.90, 0.070, 0.10, 1.10e-9),
    },
}


def tissue_params(field_T: float) -> dict[str, tuple[float, float, float, float, float]]:
    """Tissue table at ``field_T`` (3 or 7 T; other fields: log-linear interpolation of T1, T2, T2')."""
    f = float(field_T)
    if f <= 0 or not math.isfinite(f):
        raise InputError(f"field strength {field_T!r} T: expected a positive number (3 or 7)")
    if f in TISSUE_PARAMS:
        return TISSUE_PARAMS[f]
    lo, hi = TISSUE_PARAMS[3.0], TISSUE_PARAMS[7.0]
    w = min(max((f - 3.0) / 4.0, -0.5), 1.5)  # modest extrapolation only
    out: dict[str, tuple[float, float, float, float, float]] = {}
    for name in lo:
        a, b = lo[name], hi[name]
        t1, t2, t2d = (float(math.exp((1 - w) * math.log(a[i]) + w * math.log(b[i]))) for i in (1, 2, 3))
        out[name] = (a[0], t1, t2, t2d, a[4])
    return out


# ------------------------------------------------------------------------------------------------
# Built-in brain phantom
# ------------------------------------------------------------------------------------------------
def _star(u, v, cx, cy, a, b, rot_rad=0.0, harmonics=()):
    """Normalised radius of (u, v) w.r.t. a star-shaped ellipse; inside where the value < 1.

    harmonics: iterable of (order, amplitude, phase) modulating the boundary radius 1 + sum A cos(n th + p).
    """
    c, s = math.cos(rot_rad), math.sin(rot_rad)
    du, dv = u - cx, v - cy
    x = (c * du + s * dv) / a
    y = (-s * du + c * dv) / b
    rho = np.hypot(x, y)
    if harmonics:
        th = np.arctan2(y, x)
        mod = np.ones_like(rho)
        for n, amp, ph in harmonics:
            mod = mod + amp * np.cos(n * th + ph)
        rho = rho / mod
    return rho


def label_map(u: np.ndarray, v: np.ndarray, seed: int, lesion: bool) -> np.ndarray:
    """Tissue labels (indices into TISSUES) at normalised coordinates u, v in [-1, 1] (FOV edge = +-1)."""
    rng = np.random.default_rng(seed)
    # cortex folding: a few random high-order harmonics (deterministic for a given seed)
    gyri = [
        (int(n), float(rng.uniform(0.025, 0.045)), float(rng.uniform(0, 2 * np.pi)))
        for n in rng.choice(np.arange(9, 19), 4, replace=False)
    ]
    surface = [(int(n), float(rng.uniform(0.006, 0.012)), float(rng.uniform(0, 2 * np.pi))) for n in (3, 5)]
    lab = np.zeros(u.shape, dtype=np.int8)
    lab[_star(u, v, 0, 0, 0.74, 0.90) < 1] = TISSUES.index("fat")
    lab[_star(u, v, 0, 0, 0.69, 0.85) < 1] = TISSUES.index("skull")
    lab[_star(u, v, 0, 0.0, 0.655, 0.815) < 1] = TISSUES.index("csf")
    lab[_star(u, v, 0, 0.0, 0.63, 0.79, harmonics=surface) < 1] = TISSUES.index("gm")
    lab[_star(u, v, 0, 0.0, 0.53, 0.68, harmonics=surface + gyri) < 1] = TISSUES.index("wm")
    # interhemispheric fissure (CSF sliver), anterior and posterior
    fiss = (np.abs(u) < 0.012) & (np.abs(v) > 0.45) & (_star(u, v, 0, 0, 0.655, 0.815) < 1)
    lab[fiss] = TISSUES.index("csf")
    # deep grey matter (thalami / basal ganglia)
    for cx in (-0.17, 0.17):
        lab[_star(u, v, cx, -0.05, 0.09, 0.16) < 1] = TISSUES.index("gm")
    # lateral ventricles (butterfly) and third ventricle
    for cx, rot in ((-0.075, -0.35), (0.075, 0.35)):
        lab[_star(u, v, cx, 0.12, 0.05, 0.24, rot_rad=rot) < 1] = TISSUES.index("csf")
    lab[_star(u, v, 0.0, -0.06, 0.018, 0.10) < 1] = TISSUES.index("csf")
    if lesion:
        lab[_star(u, v, 0.30, 0.28, 0.055, 0.04, rot_rad=0.5) < 1] = TISSUES.index("lesion")
    return lab


def _smooth_b0_hz(u, v, field_T: float, seed: int) -> np.ndarray:
    """Smooth off-resonance map, Hz: low-order shim residual plus a frontal (sinus-like) hot spot."""
    rng = np.random.default_rng(seed + 1)
    scale = field_T / 3.0
    c = rng.normal(0, 1, 5)
    poly = 8.0 * (c[0] * u + c[1] * v) + 6.0 * (c[2] * u * u + c[3] * v * v + c[4] * u * v)
    sinus = 60.0 * np.exp(-(((u) / 0.22) ** 2 + ((v - 0.62) / 0.14) ** 2))
    return scale * (poly + sinus)


def _smooth_b1(u, v, field_T: float) -> np.ndarray:
    """Relative transmit field: central brightening, stronger at 7 T (about +-8 % at 3 T, +-30 % at 7 T)."""
    amp = 0.08 if field_T < 5 else 0.30
    r2 = (u / 0.75) ** 2 + (v / 0.9) ** 2
    return 1.0 + amp * (1.0 - 2.0 * r2) * np.exp(-0.5 * r2)


def _as_shape(n) -> tuple[int, int]:
    if isinstance(n, (int, np.integer)):
        ny = nx = int(n)
    else:
        try:
            ny, nx = (int(x) for x in n)
        except Exception:  # noqa: BLE001
            raise InputError(f"phantom matrix {n!r}: expected an int or (ny, nx)") from None
    if ny < 1 or nx < 1 or ny > 4096 or nx > 4096:
        raise InputError(f"phantom matrix {(ny, nx)}: expected 1..4096 voxels per axis")
    return ny, nx


def _as_fov(fov_m, ndim: int = 2) -> tuple[float, ...]:
    """(fov_x, fov_y) of a 2D phantom (a scalar: square), or (fov_x, fov_y, fov_z) of a 3D one, m."""
    f = np.atleast_1d(np.asarray(fov_m, dtype=np.float64)).ravel()
    if f.size == 1:
        f = np.full(ndim, f[0])
    if f.size < ndim or not np.all(np.isfinite(f[:ndim])) or np.any(f[:ndim] <= 0):
        want = "(fov_x, fov_y)" if ndim == 2 else "(fov_x, fov_y, fov_z)"
        raise InputError(f"fov_m {fov_m!r}: expected a positive number or {want} in m")
    return tuple(float(x) for x in f[:ndim])


def _mix(fractions: dict[str, np.ndarray], params: dict[str, tuple]) -> dict[str, np.ndarray]:
    """Partial-volume mixing: PD-weighted mean rates (see module docstring)."""
    shape = next(iter(fractions.values())).shape
    pd = np.zeros(shape)
    r1 = np.zeros(shape)
    r2 = np.zeros(shape)
    r2d = np.zeros(shape)
    dd = np.zeros(shape)
    for name, f in fractions.items():
        p, t1, t2, t2d, d = params[name]
        w = f * p
        pd += w
        r1 += w / t1
        r2 += w / t2
        r2d += w / t2d
        dd += w * d
    return _maps_from_weighted(pd, r1, r2, r2d, dd)


def _maps_from_weighted(pd, r1w, r2w, r2dw, dw):
    """Maps from PD and PD-weighted rates; background (pd == 0) gets T = inf, D = 0."""
    ok = pd > 1e-12
    safe = np.where(ok, pd, 1.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = np.where(ok & (r1w > 0), safe / np.where(r1w > 0, r1w, 1.0), np.inf)
        t2 = np.where(ok & (r2w > 0), safe / np.where(r2w > 0, r2w, 1.0), np.inf)
        t2d = np.where(ok & (r2dw > 0), safe / np.where(r2dw > 0, r2dw, 1.0), np.inf)
    d = np.where(ok, dw / safe, 0.0)
    return {"pd": np.where(ok, pd, 0.0), "t1_s": t1, "t2_s": t2, "t2dash_s": t2d, "d_m2_per_s": np.maximum(d, 0.0)}


def brain_phantom(
    n,
    field_T: float = DEFAULT_B0_T,
    fov_m=0.25,
    b0: bool = False,
    b1: bool = False,
    seed: int = 0,
    *,
    lesion: bool = True,
    scalp: bool = True,
    oversample: int | None = None,
) -> Phantom:
    """Built-in 2D (axial) numerical brain phantom, deterministic, any matrix size.

    The head (fat, skull, CSF rim, cortex with seeded gyri, white matter, deep grey matter,
    ventricles, optional lesion) is defined by smooth analytic shapes in coordinates normalised to the
    FOV, so it fills the same fraction (about 85 % of the y extent) of any FOV.  Labels are evaluated on
    an ``oversample`` x ``oversample`` sub-grid in every voxel (default: enough for >= 512 samples per
    axis, at least 4) and area-averaged, i.e. each voxel holds the exact box average of the tissue
    fractions; parameters mix by the partial-volume rule of the module docstring.

    Args:
        n: matrix, int (square) or (ny, nx).
        field_T: 3 or 7 (tissue table; other values interpolate).
        fov_m: FOV, m, scalar or (fov_x, fov_y).
        b0: add a smooth off-resonance map (Hz, scaled with field); else zeros.
        b1: add a smooth relative B1 map; else ones.
        seed: selects the cortical folding pattern and the B0 map coefficients.
        lesion: include a small white-matter lesion.
        scalp: include the extracranial fat and the skull.  ``False`` leaves a brain-only head (CSF,
            grey and white matter, as the BrainWeb "3T" phantom of MRzero that the paper used): its
            outer edge is the dim CSF rim instead of the bright one-voxel fat ring, so it carries much
            less energy at the k-space edge (docs/results.md, Figure 5).
        oversample: sub-samples per voxel and axis.
    Returns:
        :class:`Phantom` with voxel_shape 'box'.
    """
    ny, nx = _as_shape(n)
    fov = _as_fov(fov_m)
    params = tissue_params(field_T)
    os_ = int(oversample) if oversample else max(4, int(math.ceil(512 / max(ny, nx))))
    counts = _label_counts(ny, nx, os_, seed, lesion, scalp)
    fractions = {name: c / os_**2 for name, c in counts.items() if c.any()}
    maps = _mix(fractions, params)
    b0_map, b1_map = _field_maps(ny, nx, field_T, seed, b0, b1)
    return Phantom(
        pd=maps["pd"],
        t1_s=maps["t1_s"],
        t2_s=maps["t2_s"],
        t2dash_s=maps["t2dash_s"],
        d_m2_per_s=maps["d_m2_per_s"],
        b0_hz=b0_map,
        b1=b1_map,
        fov_m=fov,
        voxel_shape="box",
    )


def _field_maps(ny: int, nx: int, field_T: float, seed: int, b0: bool, b1: bool) -> tuple[np.ndarray, np.ndarray]:
    """(ny, nx) B0 (Hz) and relative B1 maps at the voxel centres: the smooth maps when asked, else 0 and 1."""
    yc = (np.arange(ny) - ny / 2) * 2.0 / ny
    xc = (np.arange(nx) - nx / 2) * 2.0 / nx
    vc, uc = np.meshgrid(yc, xc, indexing="ij")
    b0_map = _smooth_b0_hz(uc, vc, float(field_T), seed) if b0 else np.zeros((ny, nx))
    b1_map = _smooth_b1(uc, vc, float(field_T)) if b1 else np.ones((ny, nx))
    return b0_map, b1_map


def _label_counts(ny: int, nx: int, os_: int, seed: int, lesion: bool, scalp: bool, scale: float = 1.0) -> dict:
    """Per tissue, the number of the ``os_`` x ``os_`` sub-samples of every voxel (ny, nx) that hold it, for the
    head's cross-section shrunk by ``scale`` (1: the axial section of :func:`brain_phantom`)."""
    # sub-sample centres in normalised units (FOV edge at +-1); voxel (iy, ix) covers [(i - n/2 - 1/2), (i - n/2 + 1/2)] * 2/n
    sub = (np.arange(os_) + 0.5) / os_ - 0.5
    ux = ((np.arange(nx)[:, None] - nx / 2 + sub[None, :]) * 2.0 / nx).ravel()
    uy = ((np.arange(ny)[:, None] - ny / 2 + sub[None, :]) * 2.0 / ny).ravel()
    vv, uu = np.meshgrid(uy, ux, indexing="ij")
    lab = label_map(uu / scale, vv / scale, seed, lesion) if scale != 1.0 else label_map(uu, vv, seed, lesion)
    if not scalp:
        lab[(lab == TISSUES.index("fat")) | (lab == TISSUES.index("skull"))] = TISSUES.index("background")
    return {
        name: (lab == ti).reshape(ny, os_, nx, os_).sum(axis=(1, 3))
        for ti, name in enumerate(TISSUES)
        if name != "background"
    }


#: Semi-axis of the 3D head along z, in units of half the z FOV (as the axial section's 0.90 along y).
HEAD_Z_SEMI_AXIS = 0.90


def brain_phantom_3d(
    n_xyz,
    fov_m,
    field_T: float = DEFAULT_B0_T,
    seed: int = 0,
    *,
    b0: bool = False,
    b1: bool = False,
    lesion: bool = True,
    scalp: bool = True,
) -> Phantom:
    """Built-in 3D brain phantom (nz, ny, nx) over ``fov_m = (fov_x, fov_y, fov_z)``, deterministic.

    An ellipsoidal head: the slice at normalised height w (FOV edge at +-1) is the axial section of
    :func:`brain_phantom` shrunk by sqrt(1 - (w / 0.90)^2), so the head fills the z FOV in the same
    fraction as the y FOV (a slab FOV holds the whole head, squeezed: a test object for the image
    term of 3D-encoded sequences, not anatomy).  Voxels are box averages of the tissue labels over
    a sub-grid (>= 256 samples per in-plane axis, 4 per z voxel).  ``b0`` / ``b1``: the smooth maps of
    :func:`brain_phantom` in every slice (else B0 = 0, B1 = 1).

    Args:
        n_xyz: (nx, ny, nz) matrix.
        fov_m: (fov_x, fov_y, fov_z), m.
    """
    try:
        nx, ny, nz = (int(v) for v in n_xyz)
    except Exception:  # noqa: BLE001
        raise InputError(f"3D phantom matrix {n_xyz!r}: expected (nx, ny, nz)") from None
    _as_shape((ny, nx))
    if not 1 <= nz <= 1024:
        raise InputError(f"3D phantom matrix {n_xyz!r}: expected 1..1024 voxels along z")
    fov = _as_fov(fov_m, 3)
    params = tissue_params(field_T)
    os_ = max(4, int(math.ceil(256 / max(ny, nx))))
    os_z = 4
    fr = {name: np.zeros((nz, ny, nx)) for name in TISSUES if name != "background"}
    for iz in range(nz):
        for sz in (np.arange(os_z) + 0.5) / os_z - 0.5:
            w = (iz - nz / 2 + sz) * 2.0 / nz
            if abs(w) >= HEAD_Z_SEMI_AXIS:
                continue
            scale = math.sqrt(1.0 - (w / HEAD_Z_SEMI_AXIS) ** 2)
            for name, c in _label_counts(ny, nx, os_, seed, lesion, scalp, scale).items():
                fr[name][iz] += c / (os_**2 * os_z)
    maps = _mix({k: v for k, v in fr.items() if v.any()}, params)
    b0_map, b1_map = _field_maps(ny, nx, field_T, seed, b0, b1)
    return Phantom(
        pd=maps["pd"],
        t1_s=maps["t1_s"],
        t2_s=maps["t2_s"],
        t2dash_s=maps["t2dash_s"],
        d_m2_per_s=maps["d_m2_per_s"],
        b0_hz=np.repeat(b0_map[None], nz, 0),
        b1=np.repeat(b1_map[None], nz, 0),
        fov_m=fov,
        voxel_shape="box",
    )


def uniform_phantom(
    n,
    fov_m=0.25,
    *,
    pd: float = 1.0,
    t1_s: float = 1.0,
    t2_s: float = 0.1,
    t2dash_s: float = np.inf,
    d_m2_per_s: float = 0.0,
    b0_hz: float = 0.0,
    b1: float = 1.0,
    voxel_shape: str = "box",
) -> Phantom:
    """Phantom of identical voxels (physics tests: one voxel = ``n=1``)."""
    ny, nx = _as_shape(n)
    full = lambda val: np.full((ny, nx), float(val))  # noqa: E731
    p = Phantom(
        full(pd),
        full(t1_s),
        full(t2_s),
        full(t2dash_s),
        full(d_m2_per_s),
        full(b0_hz),
        full(b1),
        _as_fov(fov_m),
        None,
        voxel_shape,
    )
    validate_phantom(p)
    return p


# ------------------------------------------------------------------------------------------------
# Rotation (augmentation)
# ------------------------------------------------------------------------------------------------
def _rotate_map(a: np.ndarray, deg: float, fill: float) -> np.ndarray:
    """Bilinear rotation of a (ny, nx) map (each slice of a (nz, ny, nx) one) by ``deg`` (counter-clockwise in x-y) about the isocentre pixel (ny/2, nx/2)."""
    from scipy.ndimage import map_coordinates

    if a.ndim == 3:  # a 3D phantom: every z slice about the z axis
        return np.stack([_rotate_map(sl, deg, fill) for sl in a])
    ny, nx = a.shape
    th = math.radians(deg)
    c, s = math.cos(th), math.sin(th)
    # snap to exact values for multiples of 90 deg so rotate(p, 90) is exact
    c, s = (round(c) if abs(c - round(c)) < 1e-12 else c), (round(s) if abs(s - round(s)) < 1e-12 else s)
    iy, ix = np.meshgrid(np.arange(ny, dtype=np.float64), np.arange(nx, dtype=np.float64), indexing="ij")
    y = iy - ny / 2
    x = ix - nx / 2
    # source of output point r is R(-th) r
    xs = c * x + s * y
    ys = -s * x + c * y
    return map_coordinates(a, [ys + ny / 2, xs + nx / 2], order=1, mode="constant", cval=fill)


def rotate(phantom: Phantom, deg: float) -> Phantom:
    """The phantom rotated by ``deg`` degrees (counter-clockwise from +x towards +y) about the isocentre.

    Deterministic bilinear resampling of PD and of the PD-weighted rates (1/T1, 1/T2, 1/T2', D), so
    partial voxels mix as in :func:`brain_phantom`; B0 and B1 maps are rotated with the object (they
    are properties of the head); coil sensitivities stay fixed (hardware).  Voxels rotated in from
    outside the FOV are empty.  Pixel-square FOVs only (fov_x/nx == fov_y/ny), so that rotation is
    isotropic in metres.
    """
    validate_phantom(phantom)
    dx, dy = phantom.voxel_size_m
    if abs(dx - dy) > 1e-9 * max(dx, dy):
        raise InputError(f"rotate: voxels must be square, got {dx:g} x {dy:g} m")
    if deg % 360 == 0:
        return replace(phantom, **{k: getattr(phantom, k).copy() for k in MAP_KEYS})
    pd = phantom.pd
    with np.errstate(divide="ignore"):
        rates = [pd / phantom.t1_s, pd / phantom.t2_s, pd / phantom.t2dash_s, pd * phantom.d_m2_per_s]
    rates = [np.where(pd > 0, r, 0.0) for r in rates]
    pd_r = np.maximum(_rotate_map(pd, deg, 0.0), 0.0)
    r_r = [np.maximum(_rotate_map(r, deg, 0.0), 0.0) for r in rates]
    maps = _maps_from_weighted(pd_r, *r_r)
    b0 = _rotate_map(phantom.b0_hz, deg, 0.0)
    b1 = _rotate_map(phantom.b1, deg, 1.0)
    return Phantom(
        pd=maps["pd"],
        t1_s=maps["t1_s"],
        t2_s=maps["t2_s"],
        t2dash_s=maps["t2dash_s"],
        d_m2_per_s=maps["d_m2_per_s"],
        b0_hz=b0,
        b1=b1,
        fov_m=phantom.fov_m,
        coil_sens=None if phantom.coil_sens is None else phantom.coil_sens.copy(),
        voxel_shape=phantom.voxel_shape,
    )


# ------------------------------------------------------------------------------------------------
# Validation and files
# ------------------------------------------------------------------------------------------------
def validate_phantom(p: Phantom, source: str = "phantom") -> Phantom:
    """Check shapes and value ranges; raise a one-line :class:`InputError` naming the map."""
    if not isinstance(p.pd, np.ndarray) or p.pd.ndim not in (2, 3) or p.pd.size == 0:
        raise InputError(
            f"{source}: 'pd' must be a non-empty (ny, nx) or (nz, ny, nx) array, got shape {np.shape(p.pd)}"
        )
    shape = p.pd.shape
    for k in MAP_KEYS:
        a = getattr(p, k)
        if np.shape(a) != shape:
            raise InputError(f"{source}: '{k}' has shape {np.shape(a)}, expected {shape} like 'pd'")
        if not np.issubdtype(np.asarray(a).dtype, np.number) or np.iscomplexobj(a):
            raise InputError(f"{source}: '{k}' must be real numbers")
    if not np.all(np.isfinite(p.pd)) or np.any(p.pd < 0):
        raise InputError(f"{source}: 'pd' must be finite and >= 0")
    for k in ("t1_s", "t2_s", "t2dash_s"):
        a = getattr(p, k)
        if np.any(np.isnan(a)) or np.any(a <= 0):
            raise InputError(f"{source}: '{k}' must be > 0 s (inf allowed), min is {np.nanmin(a):g}")
    if not np.all(np.isfinite(p.d_m2_per_s)) or np.any(p.d_m2_per_s < 0):
        raise InputError(f"{source}: 'd_m2_per_s' must be finite and >= 0 m^2/s")
    if np.any(p.d_m2_per_s > 1e-7):
        raise InputError(f"{source}: 'd_m2_per_s' max {p.d_m2_per_s.max():g} m^2/s is implausible (free water is 3e-9)")
    if not np.all(np.isfinite(p.b0_hz)):
        raise InputError(f"{source}: 'b0_hz' must be finite (Hz)")
    if not np.all(np.isfinite(p.b1)) or np.any(p.b1 < 0):
        raise InputError(f"{source}: 'b1' must be finite and >= 0 (relative)")
    _as_fov(p.fov_m, p.pd.ndim)
    if p.coil_sens is not None and (np.ndim(p.coil_sens) != len(shape) + 1 or np.shape(p.coil_sens)[1:] != shape):
        raise InputError(
            f"{source}: 'coil_sens' has shape {np.shape(p.coil_sens)}, expected (n_coils, {', '.join(map(str, shape))})"
        )
    if p.voxel_shape not in ("box", "sinc", "none"):
        raise InputError(f"{source}: voxel_shape {p.voxel_shape!r}: expected 'box', 'sinc' or 'none'")
    return p


def load_phantom(path: str | os.PathLike) -> Phantom:
    """Read a user phantom from ``.npz`` (keys in docs/metrics.md) and validate it.

    Required keys: pd, t1_s, t2_s (each (ny, nx)) and fov_m (m, scalar or (2,)); optional: t2dash_s
    (s, default inf), d_m2_per_s (default 0), b0_hz (default 0), b1 (default 1), coil_sens
    (n_coils, ny, nx) complex, voxel_shape (str, default 'box').  Other keys are ignored.
    """
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: phantom file not found")
    if p.suffix.lower() != ".npz":
        raise InputError(f"{p}: unsupported phantom format (expected .npz with keys {', '.join(REQUIRED_KEYS)})")
    check_phantom_size(p)
    try:
        with np.load(p, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except Exception as e:  # noqa: BLE001
        raise InputError(f"{p}: not a readable .npz file ({type(e).__name__})") from None
    missing = [k for k in REQUIRED_KEYS if k not in data]
    if missing:
        raise InputError(f"{p}: missing key(s) {', '.join(missing)} (required: pd, t1_s, t2_s as (ny, nx), fov_m in m)")
    pd = np.asarray(data["pd"])
    if pd.ndim not in (2, 3):
        raise InputError(f"{p}: 'pd' has shape {pd.shape}, expected (ny, nx) or (nz, ny, nx)")
    shape = pd.shape
    defaults = {"t2dash_s": np.inf, "d_m2_per_s": 0.0, "b0_hz": 0.0, "b1": 1.0}

    def get(k):
        if k in data:
            a = np.asarray(data[k])
            if a.shape != shape:
                raise InputError(f"{p}: '{k}' has shape {a.shape}, expected {shape} like 'pd'")
            if not np.issubdtype(a.dtype, np.number) or np.iscomplexobj(a):
                raise InputError(f"{p}: '{k}' must be real numbers")
            return a.astype(np.float64)
        return np.full(shape, defaults[k])

    coil = None
    if "coil_sens" in data:
        coil = np.asarray(data["coil_sens"]).astype(np.complex128)
    vs = str(data["voxel_shape"]) if "voxel_shape" in data else "box"
    try:
        fov = _as_fov(data["fov_m"], pd.ndim)
    except InputError:
        want = "(fov_x, fov_y)" if pd.ndim == 2 else "(fov_x, fov_y, fov_z)"
        raise InputError(
            f"{p}: 'fov_m' {np.asarray(data['fov_m']).tolist()!r}: expected a positive number or {want} in m"
        ) from None
    ph = Phantom(
        pd=get("pd"),
        t1_s=get("t1_s"),
        t2_s=get("t2_s"),
        t2dash_s=get("t2dash_s"),
        d_m2_per_s=get("d_m2_per_s"),
        b0_hz=get("b0_hz"),
        b1=get("b1"),
        fov_m=fov,
        coil_sens=coil,
        voxel_shape=vs,
    )
    return validate_phantom(ph, str(p))


def save_phantom(phantom: Phantom, path: str | os.PathLike, force: bool = False) -> Path:
    """Write a phantom as ``.npz`` (the keys :func:`load_phantom` reads), atomically and deterministically."""
    import io
    import zipfile

    from dtoc.util.atomic import atomic_write_bytes

    validate_phantom(phantom)
    arrays = {k: np.ascontiguousarray(getattr(phantom, k), dtype=np.float64) for k in MAP_KEYS}
    arrays["fov_m"] = np.asarray(phantom.fov_m, dtype=np.float64)
    arrays["voxel_shape"] = np.asarray(phantom.voxel_shape)
    if phantom.coil_sens is not None:
        arrays["coil_sens"] = np.asarray(phantom.coil_sens, dtype=np.complex128)
    buf = io.BytesIO()
    # fixed timestamps in the zip entries -> byte-identical files for identical phantoms
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for k, a in arrays.items():
            info = zipfile.ZipInfo(f"{k}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            b = io.BytesIO()
            np.save(b, a, allow_pickle=False)
            zf.writestr(info, b.getvalue())
    return atomic_write_bytes(path, buf.getvalue(), force=force)


#: Names of the built-in phantom specs (``name`` or ``name:N``) accepted by :func:`resolve_phantom`.
BUILTIN_PHANTOMS = ("brain", "brain-noscalp", "brain3d")


def is_builtin_spec(spec) -> bool:
    """True when ``spec`` names a built-in phantom (``brain``, ``brain-noscalp:32``, ...)."""
    return str(spec).split(":", 1)[0] in BUILTIN_PHANTOMS


def resolve_phantom(
    spec, *, matrix=None, fov_m=None, field_T: float = 3.0, b0: bool = False, b1: bool = False, seed: int = 0
) -> Phantom:
    """A phantom from a CLI-style spec: None / 'brain' (built-in head at ``matrix``), 'brain:N' (N x N),
    'brain-noscalp' / 'brain-noscalp:N' (the same without extracranial fat and skull, see
    :func:`brain_phantom`), or a .npz path."""
    name, _, size = ("brain" if spec is None else str(spec)).partition(":")
    if name == "brain3d":
        raise InputError("phantom brain3d: a 3D phantom is made on a 3D-encoded sequence's grid (phantom_for)")
    if name in BUILTIN_PHANTOMS:
        if size:
            try:
                n = int(size)
            except ValueError:
                raise InputError(f"phantom {spec!r}: expected {name}:N with an integer N") from None
            matrix = (n, n)
        if matrix is None:
            raise InputError(f"phantom: matrix unknown; give --phantom {name}:N or a .npz file")
        if fov_m is None:
            raise InputError("phantom: field of view unknown; give a .npz phantom with fov_m")
        return brain_phantom(matrix, field_T=field_T, fov_m=fov_m, b0=b0, b1=b1, seed=seed, scalp=name == "brain")
    return load_phantom(spec)


#: at most this many voxels in a phantom (1024 x 1024, or e.g. 128 x 128 x 64): docs/cli.md, "Accepted ranges"
MAX_PHANTOM_VOXELS = 1024 * 1024


def check_phantom_size(spec) -> None:
    """Refuse, before anything is built or inflated, a phantom spec whose size is outside the accepted range:
    ``brain:N`` / ``brain3d:N`` with N outside [4, 1024], or a ``.npz`` whose 'pd' declares more than
    :data:`MAX_PHANTOM_VOXELS` voxels (read from the archive's header, not inflated)."""
    from dtoc.util.validate import check_npz_archive, check_range

    if spec is None or isinstance(spec, Phantom):
        return
    s = str(spec)
    name, _, size = s.partition(":")
    if name in BUILTIN_PHANTOMS:
        if size:
            try:
                n = int(size)
            except ValueError:
                raise InputError(f"--phantom {spec!r}: expected {name}:N with an integer N") from None
            check_range("phantom_n", n, f"--phantom {name}:N, N")
        return
    if s.lower().endswith(".npz") and Path(s).is_file():
        shapes = check_npz_archive(s, "--phantom")
        pd = shapes.get("pd")
        if pd is not None and math.prod(pd) > MAX_PHANTOM_VOXELS:
            raise InputError(
                f"{s}: phantom 'pd' {tuple(pd)} has {math.prod(pd)} voxels, more than the {MAX_PHANTOM_VOXELS} accepted "
                "(1024 x 1024; docs/cli.md): refused before loading"
            )


def phantom_for(
    ir, spec=None, *, size: int | None = None, field_T: float = DEFAULT_B0_T, b0: bool = False, b1: bool = False
) -> Phantom:
    """The phantom of a spec (:func:`resolve_phantom`) on the image grid of sequence ``ir``.

    Built-in phantoms are made at the sequence's in-plane matrix (``size`` overrides it: N x N) and FOV
    (:attr:`dtoc.seq.ir.SequenceIR.geometry`); ``brain3d`` (``brain3d:N``) on a 3D-encoded sequence's grid
    (``ir.meta['grid3d']``); a ``.npz`` phantom is read as it is.
    """
    check_phantom_size(spec)
    if size is not None:
        from dtoc.util.validate import check_range

        check_range("phantom_n", size, "phantom size")
    geo = ir.geometry
    name, _, n3 = str(spec).partition(":")
    if name == "brain3d":
        return _brain3d_for(ir, n3 or (str(size) if size else ""), field_T, b0, b1)
    if is_builtin_spec("brain" if spec is None else spec) and geo is None:
        raise InputError(
            "no image grid for this sequence (its ADC samples are on none dtoc can reconstruct: the notes say why): "
            "cannot build the phantom"
        )
    matrix = fov = None
    if geo is not None:
        nx, ny = geo.matrix_xy
        matrix = (size or ny, size or nx)
        fov = geo.fov_xy_m
    return resolve_phantom(spec, matrix=matrix, fov_m=fov, field_T=field_T, b0=b0, b1=b1)


def _brain3d_for(ir, size: str, field_T: float, b0: bool = False, b1: bool = False) -> Phantom:
    """:func:`brain_phantom_3d` on the 3D grid of a 3D-encoded sequence (``brain3d:N``: N x N in plane)."""
    g = (getattr(ir, "meta", None) or {}).get("grid3d")
    if g is None:
        raise InputError("phantom brain3d: the sequence has no 3D Cartesian grid (2D files take brain or a 2D .npz)")
    nx, ny, nz = (int(v) for v in g["matrix_xyz"])
    if size:
        try:
            nx = ny = int(size)
        except ValueError:
            raise InputError(f"phantom brain3d:{size}: expected brain3d:N with an integer N") from None
    return brain_phantom_3d((nx, ny, nz), tuple(g["fov_m"]), field_T=field_T, b0=b0, b1=b1)


def is_3d_spec(spec) -> bool:
    """True when a phantom (object or spec) is 3D: ``brain3d[:N]``, a (nz, ny, nx) ``.npz`` or :class:`Phantom`."""
    if isinstance(spec, Phantom):
        return spec.is_3d
    if spec is None:
        return False
    s = str(spec)
    if s.split(":", 1)[0] == "brain3d":
        return True
    if s.lower().endswith(".npz") and Path(s).is_file():
        try:
            with np.load(s, allow_pickle=False) as z:
                return "pd" in z.files and z["pd"].ndim == 3
        except Exception:  # noqa: BLE001  (load_phantom reports an unreadable file)
            return False
    return False


def check_phantom_matches(ir, phantom) -> bool:
    """A 3D-encoded sequence (``ir.meta['grid3d']``) images a 3D phantom, a 2D one a 2D phantom: one line otherwise.
    ``phantom``: a :class:`Phantom` or a spec (:func:`is_3d_spec`; None = the default 'brain').  Returns whether
    both are 3D (the phantom's :func:`is_3d_spec`, read once)."""
    three_d = (getattr(ir, "meta", None) or {}).get("grid3d") is not None
    ph_3d = is_3d_spec(phantom)
    if three_d and not ph_3d:
        raise InputError(
            "the sequence is 3D-encoded: its image needs a 3D phantom (--phantom brain3d, or a .npz with (nz, ny, nx) maps)"
        )
    if ph_3d and not three_d:
        what = f"a 3D phantom {phantom.shape}" if isinstance(phantom, Phantom) else f"the 3D phantom {phantom}"
        raise InputError(f"{what} needs a 3D-encoded sequence (k on a 3D Cartesian grid)")
    return ph_3d
