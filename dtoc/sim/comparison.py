"""Ideal versus realized acquisition of one sequence on one phantom: the library side of ``dtoc simulate``.

Pipeline (the paper's forward model, evaluation only):
demanded gradient g (IR fine grid) -> hardware model -> realized G and B0 term -> PDG simulation ->
plain iFFT reconstruction assuming the *nominal* k-space -> images, metrics (docs/metrics.md).
The ideal image I0 uses G = g and no B0 term.  With an identity hardware model the realized
acquisition *is* the ideal one (same tensor), so its NRMSE is exactly 0.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from dtoc.errors import InputError
from dtoc.sim import metrics
from dtoc.sim.imager import Imager
from dtoc.sim.phantom import Phantom, check_phantom_matches
from dtoc.sim.recon import cartesian_grid, cartesian_grid_3d
from dtoc.sim.twin import HardwareChain, Twin
from dtoc.util.figures import png_bytes


@dataclass
class ComparisonResult:
    """Images (magnitude, (ny, nx) or (nz, ny, nx)), k-space ((3, N_adc), rad/m) and metrics of ideal vs realized."""

    ideal_image: np.ndarray
    realized_image: np.ndarray
    k0_rad_per_m: np.ndarray
    k_rad_per_m: np.ndarray
    dk_rad_per_m: np.ndarray
    metrics: dict[str, Any]
    identity_hardware: bool
    extra: dict[str, Any] = field(default_factory=dict)


_DTYPES = {"float32": torch.float32, "float64": torch.float64}


def torch_dtype(name: str) -> torch.dtype:
    """'float32' | 'float64' -> torch dtype (InputError otherwise)."""
    if name not in _DTYPES:
        raise InputError(f"--dtype {name!r}: expected float32 or float64")
    return _DTYPES[name]


def check_device(device: str) -> str:
    """Validate a torch device string (InputError if unavailable)."""
    try:
        d = torch.device(device)
    except (RuntimeError, TypeError):
        raise InputError(f"--device {device!r}: expected cpu or cuda[:N]") from None
    if d.type == "cuda" and not torch.cuda.is_available():
        raise InputError(f"--device {device}: CUDA is not available on this machine")
    if d.type not in ("cpu", "cuda"):
        raise InputError(f"--device {device!r}: expected cpu or cuda[:N]")
    return str(d)


def compare_ideal_realized(
    ir,
    phantom: Phantom,
    model: HardwareChain | None = None,
    *,
    keep_mask=None,
    n_dummies: int = 0,
    config=None,
    dtype=torch.float64,
    device: str = "cpu",
    step: Callable[[str], None] | None = None,
    reference=None,
) -> ComparisonResult:
    """Simulate and reconstruct ``ir`` on ``phantom`` with ideal hardware and with ``model``.

    Args:
        ir: base sequence (:class:`dtoc.seq.ir.SequenceIR`), Cartesian nominal k-space.
        phantom: tissue maps.
        model: the :class:`~dtoc.sim.twin.HardwareChain` (None or identity: realized = ideal).
        keep_mask: (N_adc,) bool samples used by the reconstruction (default all).
        n_dummies: dummy repetitions before the sequence (steady-state initial Mz; 0 = equilibrium).
        config: :class:`dtoc.sim.pdg.PDGConfig`.
        dtype, device: simulation precision and device.
        step: optional progress callback, called with a short description before each stage.
        reference: the base ``ir`` was compiled from (:class:`~dtoc.seq.ir.SequenceIR` of the same structure,
            :func:`dtoc.sim.reference.check_same_structure`): the ideal image, nominal k, grid and dk are the
            base's, the realized acquisition is ``ir`` played through ``model`` (``--reference BASE``).
    """
    from dtoc.sim.pdg import PDGConfig

    note = step or (lambda _s: None)
    played, ir = ir, (ir if reference is None else reference)  # below, ``ir`` is what the acquisition intends
    ndft = ir.meta.get("recon") == "ndft"  # non-Cartesian: non-uniform DFT on the nominal trajectory
    three_d = check_phantom_matches(ir, phantom)
    grid = None if ndft else (cartesian_grid_3d(ir, keep_mask) if three_d else cartesian_grid(ir, keep_mask))
    matrix = list(ir.require_geometry("simulate").image_shape[::-1] if grid is None else grid.shape[::-1])
    note("graph" if not n_dummies or n_dummies <= 0 else f"graph, {n_dummies} dummy cycles, ideal simulation")
    imager = Imager(
        ir,
        [phantom],
        max(int(n_dummies or 0), 0),
        dtype=dtype,
        device=device,
        config=config or PDGConfig(),
        steady_state_options={"config": config, "dtype": dtype, "device": device},
    )
    img0 = imager.image(imager.target_signals[0], keep_mask=keep_mask if ndft else None, grid=grid).abs()
    twin = Twin(played, model, dtype=dtype, device=device)
    k0 = ir.nominal_kspace_rad_per_m()
    identity = twin.is_ideal
    if identity and reference is None:
        k = k0.copy()
        img = img0
    else:
        note("hardware model, realized simulation")
        with torch.no_grad():
            r = twin.forward(moments=False)
            s = imager.signal(r.realized_grad_mT_per_m, r.b0_uT, 0)
        img = imager.image(s, keep_mask=keep_mask if ndft else None, grid=grid).abs()
        # k figures in float64 whatever the simulation precision
        k = played.kspace_rad_per_m(r.realized_grad_mT_per_m.detach().to("cpu", torch.float64)).numpy()
    note("metrics")
    fov = ir.require_geometry("simulate").fov_xy_m if grid is None else grid.fov_m
    dk = np.array([2 * np.pi / f for f in fov] + ([] if three_d else [np.inf]))
    if grid is not None and not three_d:  # an axis with one grid point is not encoded: no figure in its dk
        for a, n in enumerate(grid.shape[::-1]):
            if n == 1:
                dk[a] = np.inf
    used = (
        (np.ones(ir.n_adc_samples, dtype=bool) if keep_mask is None else np.asarray(keep_mask, dtype=bool))
        if grid is None
        else grid.flat_index >= 0
    )
    m: dict[str, Any] = metrics.image_metrics(
        img, img0, epi=ir.kind == "epi" and not three_d, phase_dim=ir.phase_image_dim,
        rf_flips_rad=[r.flip_angle_rad for r in ir.rf],
    )  # fmt: skip
    m.update(metrics.kspace_errors(k, k0, dk, mask=used))
    m["kept_samples"] = int(used.sum())
    m["n_adc_samples"] = int(used.size)
    m["matrix"] = matrix
    return ComparisonResult(
        ideal_image=img0.detach().cpu().numpy().astype(np.float64),
        realized_image=img.detach().cpu().numpy().astype(np.float64),
        k0_rad_per_m=np.asarray(k0, dtype=np.float64),
        k_rad_per_m=np.asarray(k, dtype=np.float64),
        dk_rad_per_m=dk,
        metrics=m,
        identity_hardware=identity,
    )


def plot_comparison(res: ComparisonResult, title: str = "") -> bytes:
    """PNG bytes: ideal image, realized image, difference (realized - ideal, magnitude), k-space (in dk units)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    i0, i1 = res.ideal_image, res.realized_image
    if i0.ndim == 3:  # a 3D image: its central z slice
        title = (title + ", " if title else "") + f"central slice z = {i0.shape[0] // 2} of {i0.shape[0]}"
        i0, i1 = i0[i0.shape[0] // 2], i1[i1.shape[0] // 2]
    vmax = float(max(i0.max(), i1.max(), 1e-30))
    diff = i1 - i0
    dmax = float(max(np.abs(diff).max(), 1e-12 * vmax))
    fig, ax = plt.subplots(1, 4, figsize=(16, 4.3))
    ax[0].imshow(i0, origin="lower", cmap="gray", vmin=0, vmax=vmax)
    ax[0].set_title("ideal I0")
    ax[1].imshow(i1, origin="lower", cmap="gray", vmin=0, vmax=vmax)
    nr = res.metrics["nrmse"]
    ax[1].set_title("realized I (no signal)" if nr is None else f"realized I (NRMSE {100 * nr:.3g} %)")
    im = ax[2].imshow(diff, origin="lower", cmap="RdBu_r", vmin=-dmax, vmax=dmax)
    ax[2].set_title("|I| - |I0|")
    fig.colorbar(im, ax=ax[2], fraction=0.046)
    for a in ax[:3]:
        a.set_xlabel("x (pixel)")
        a.set_ylabel("y (pixel)")
    dk = res.dk_rad_per_m
    ax[3].plot(res.k0_rad_per_m[0] / dk[0], res.k0_rad_per_m[1] / dk[1], ".", ms=2, color="0.6", label="nominal k0")
    if not res.identity_hardware:
        ax[3].plot(res.k_rad_per_m[0] / dk[0], res.k_rad_per_m[1] / dk[1], ".", ms=2, color="C3", label="realized k")
    ax[3].set_xlabel("kx / dk")
    ax[3].set_ylabel("ky / dk")
    ax[3].set_aspect("equal")
    ax[3].legend(loc="upper right", fontsize=8)
    em = res.metrics.get("kspace_max_err_dk")
    ax[3].set_title("k-space" + (f" (max error {em:.3g} dk)" if em is not None else ""))
    if title:
        fig.suptitle(title)
    return png_bytes(fig, dpi=90)
