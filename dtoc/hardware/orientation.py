"""Slice orientation: the rotation from a ``.seq`` file's logical gradient axes to the scanner's physical axes.

A GIRF and eddy currents live on the *physical* gradient axes; a ``.seq`` file's x/y/z are played on the axes
its prescription rotates them onto.  ``R`` (3x3, row-major, logical -> physical: ``g_phys = R @ g_log``) is
given by name or by 9 numbers (docs/conventions.md, "Orientation"):

- ``tra``: identity (logical x, y, z = physical x, y, z; slice normal along z).
- ``cor``: logical x -> physical x, y -> z, z -> -y (slice normal along physical y; a proper rotation).
- ``sag``: logical x -> physical y, y -> z, z -> x (slice normal along physical x).

:class:`RotatedChain` plays a hardware model at an orientation: it rotates the demanded gradient to physical
axes, applies the model there and rotates the realized gradient back, so k-space stays in the file's frame.
Per-axis limits hold on the physical axes: the optimizer holds them there with
:meth:`dtoc.optimize.limits.Limits.rotated` (boxes around the base, checked on R @ g).
:func:`logical_limit_scale` is the conservative uniform bound (the factor that keeps every physical axis within
its limit whatever the logical waveform, ``max_i sum_j |R_ij|``); dtoc no longer limits with it (it refused
bases that play within the physical limits), it stays as the reference the tests compare against.
"""

from __future__ import annotations

import math

import numpy as np

from dtoc.errors import InputError

NAMED = {
    "tra": np.eye(3),
    "cor": np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]),
    "sag": np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]),
}

#: other names of the three (docs/conventions.md): one rotation, one batch key
ALIASES = {
    "transversal": "tra",
    "transverse": "tra",
    "coronal": "cor",
    "sagittal": "sag",
}


def parse_orientation(text: str | None) -> np.ndarray | None:
    """``tra|sag|cor`` or 9 comma/space separated numbers (row-major, logical -> physical) -> (3, 3) R.

    Raises:
        InputError: unknown name, not 9 finite numbers, or not a rotation (orthonormal to 1e-6, det +1).
    """
    if text is None:
        return None
    t = text.strip().lower()
    t = ALIASES.get(t, t)
    if t in NAMED:
        return NAMED[t].copy()
    try:
        vals = [float(x) for x in t.replace(",", " ").split()]
    except ValueError:
        raise InputError(f"--orientation {text!r}: expected tra, sag, cor or 9 numbers") from None
    if len(vals) != 9 or not all(math.isfinite(v) for v in vals):
        raise InputError(f"--orientation {text!r}: expected tra, sag, cor or 9 finite numbers (row-major)")
    R = np.array(vals).reshape(3, 3)
    err = float(np.max(np.abs(R @ R.T - np.eye(3))))
    if err > 1e-6 or np.linalg.det(R) < 0:
        raise InputError(
            f"--orientation: not a rotation matrix (|R R^T - I| = {err:.2g}, det {np.linalg.det(R):.3g}); "
            "give an orthonormal matrix with det +1, row-major, logical -> physical"
        )
    return R


def file_orientation(definitions: dict) -> np.ndarray | None:
    """The orientation a dtoc output records (``DtocOrientation`` 9 numbers), or None."""
    v = (definitions or {}).get("DtocOrientation")
    if v is None:
        return None
    vals = v.split() if isinstance(v, str) else list(np.ravel(v))
    try:
        R = np.array([float(x) for x in vals]).reshape(3, 3)
    except ValueError:
        return None
    return R


def orientation_name(R: np.ndarray | None) -> str:
    """'tra' / 'cor' / 'sag' when R is one of them, else the 9 numbers."""
    if R is None:
        return "tra"
    for k, v in NAMED.items():
        if np.allclose(R, v, atol=1e-9):
            return k
    return " ".join(f"{x:.9g}" for x in np.asarray(R).ravel())


def logical_limit_scale(R: np.ndarray | None) -> float:
    """Factor f <= 1 such that per-logical-axis limits ``f * limit`` keep every physical axis within ``limit``:
    ``|sum_j R_ij g_j| <= sum_j |R_ij| max_j |g_j|``, so f = 1 / max_i sum_j |R_ij| (1 for tra/cor/sag)."""
    if R is None:
        return 1.0
    return float(1.0 / np.max(np.sum(np.abs(R), axis=1)))


class RotatedChain:
    """A hardware chain (:class:`dtoc.sim.twin.HardwareChain`) played at orientation ``R``.

    ``chain(g_log, dt) = (R^T H(R g_log), b0)``: the model acts on the physical axes, k-space is computed in
    the file's logical frame.  The B0 term (spatially uniform) is not rotated.
    """

    def __init__(self, hardware, R: np.ndarray) -> None:
        self.hardware = hardware
        self.R = np.asarray(R, dtype=np.float64)
        self._R_on: dict = {}  # R as a tensor per (dtype, device), made once: a call moves no host data

    def __call__(self, g, dt_s: float):
        import torch  # kept off the import path of the light commands (docs/cli.md, start-up)

        key = (g.dtype, str(g.device))
        if key not in self._R_on:
            self._R_on[key] = torch.as_tensor(self.R, dtype=g.dtype, device=g.device)
        R = self._R_on[key]
        g_phys = torch.einsum("ij,...jm->...im", R, g)
        G_phys, b0 = self.hardware(g_phys, dt_s)
        return torch.einsum("ji,...jm->...im", R, G_phys), b0

    def to(self, device) -> RotatedChain:
        if hasattr(self.hardware, "to"):
            self.hardware = self.hardware.to(device)
        return self

    def frozen(self) -> RotatedChain:
        if hasattr(self.hardware, "frozen"):
            self.hardware = self.hardware.frozen()
        return self

    @property
    def is_identity(self) -> bool:
        return bool(getattr(self.hardware, "is_identity", False))
