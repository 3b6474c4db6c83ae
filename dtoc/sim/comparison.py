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
from dtoc.sim.phantom import Phantom
from dtoc.sim.recon import cartesian_grid, reconstruct
from dtoc.util.figures import png_bytes


@dataclass
class ComparisonResult:
    """Images (magnitude, (ny, nx)), k-space ((3, N_adc), rad/m) and metrics of ideal vs realized."""

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
    model=None,
    *,
    keep_mask=None,
    n_dummies: int = 0,
    config=None,
    dtype=torch.float64,
    device: str = "cpu",
    step: Callable[[str], None] | None = None,
) -> ComparisonResult:
    """Simulate and reconstruct ``ir`` on ``phantom`` with ideal hardware and with ``model``.

    Args:
        ir: base sequence (:class:`dtoc.seq.ir.SequenceIR`), Cartesian nominal k-space.
        phantom: tissue maps.
        model: :class:`dtoc.hardware.HardwareModel` (None or identity: realized = ideal).
        keep_mask: (N_adc,) bool samples used by the reconstruction (default all).
        n_dummies: dummy repetitions before the sequence (steady-state initial Mz; 0 = equilibrium).
        config: :class:`dtoc.sim.pdg.PDGConfig`.
        dtype, device: simulation precision and device.
        step: optional progress callback, called with a short description before each stage.
    """
    from dtoc.sim.pdg import build_graph, simulate, steady_state_mz

    note = step or (lambda _s: None)
    grid = cartesian_grid(ir, keep_mask)
    ny, nx = grid.shape
    note("graph")
    graph = build_graph(ir, config, phantom)
    mz0 = None
    if n_dummies and n_dummies > 0:
        note(f"{n_dummies} dummy cycles")
        mz0 = steady_state_mz(ir, phantom, int(n_dummies), config=config, dtype=dtype, device=device)
    note("ideal simulation")
    with torch.no_grad():
        s0 = simulate(ir, phantom, graph=graph, config=config, initial_mz=mz0, dtype=dtype, device=device)
    img0 = reconstruct(s0, ir, grid=grid).abs()
    k0 = ir.nominal_kspace_rad_per_m()
    identity = model is None or getattr(model, "is_identity", False)
    if identity:
        s, k = s0, k0.copy()
        img = img0
    else:
        note("hardware model")
        with torch.no_grad():
            g = torch.as_tensor(ir.grad_mT_per_m, dtype=dtype, device=device)
            G, b0 = model(g, ir.dt_fine_s)
            note("realized simulation")
            s = simulate(ir, phantom, G, b0, graph=graph, config=config, initial_mz=mz0, dtype=dtype, device=device)
        img = reconstruct(s, ir, grid=grid).abs()
        k = ir.kspace_rad_per_m(G.detach().to("cpu", torch.float64)).numpy()
    note("metrics")
    dk = np.array([2 * np.pi / grid.fov_m[0], 2 * np.pi / grid.fov_m[1], np.inf])
    used = grid.flat_index >= 0
    m: dict[str, Any] = {"nrmse": float(metrics.nrmse(img, img0))}
    m.update(metrics.kspace_errors(k, k0, dk, mask=used))
    if ir.kind == "epi":
        phase_dim = -1 if ir.phase_axis == 0 else -2
        m["ghost_ratio"] = float(metrics.ghost_ratio(img, img0, phase_dim=phase_dim))
        m["ghost_ratio_ideal"] = float(metrics.ghost_ratio(img0, img0, phase_dim=phase_dim))
    else:
        m["ghost_ratio"] = None
        m["ghost_ratio_ideal"] = None
    m["kept_samples"] = int(used.sum())
    m["n_adc_samples"] = int(used.size)
    m["matrix"] = [nx, ny]
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
    vmax = float(max(i0.max(), i1.max(), 1e-30))
    diff = i1 - i0
    dmax = float(max(np.abs(diff).max(), 1e-12 * vmax))
    fig, ax = plt.subplots(1, 4, figsize=(16, 4.3))
    ax[0].imshow(i0, origin="lower", cmap="gray", vmin=0, vmax=vmax)
    ax[0].set_title("ideal I0")
    ax[1].imshow(i1, origin="lower", cmap="gray", vmin=0, vmax=vmax)
    nr = res.metrics["nrmse"]
    ax[1].set_title(f"realized I (NRMSE {100 * nr:.3g} %)")
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
