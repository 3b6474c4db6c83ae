"""The digital twin's forward model, written once: demanded gradient -> hardware -> realized gradient, B0 -> k-space.

``g (3, M) mT/m on the IR's fine grid -> HardwareChain -> G (3, M) mT/m, b0 (M,) uT -> k at every ADC
sample (3, N_adc) rad/m and the k-space moment before every RF pulse after the first (3, N_rf - 1) rad/m``.

Every stage that plays a sequence through the hardware (``dtoc simulate``, ``predict``, ``optimize``,
``identify``'s image hint) calls :meth:`Twin.forward` and gets one :class:`Realization`; the Bloch
simulation and reconstruction of those waveforms is :class:`dtoc.sim.imager.Imager`.  Conventions
(units, time origin, refocusing) are those of docs/conventions.md.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol, runtime_checkable

import numpy as np
import torch

if TYPE_CHECKING:
    from dtoc.seq.ir import SequenceIR


@runtime_checkable
class HardwareChain(Protocol):
    """The gradient chain of a scanner: demanded -> realized gradient and B0 term.

    ``chain(g, dt_s)`` takes the demanded gradient ``g`` (B, 3, M) mT/m (or (3, M)) sampled every
    ``dt_s`` seconds and returns ``(G, b0)``: the realized gradient of the same shape, mT/m, and the
    spatially uniform field offset (B, M) uT, or None when the chain has no B0 term.  It is a torch
    function of ``g`` (differentiable where the optimizer needs it).  :class:`dtoc.hardware.HardwareModel`
    is the implementation dtoc ships.
    """

    def __call__(self, g: torch.Tensor, dt_s: float) -> tuple[torch.Tensor, torch.Tensor | None]: ...


@dataclass(frozen=True)
class Realization:
    """One demanded waveform played through the twin (all torch tensors on the twin's device and dtype).

    Attributes:
        demanded_grad_mT_per_m: (3, M) demanded gradient g on the IR's fine grid, mT/m.
        realized_grad_mT_per_m: (3, M) realized gradient G, mT/m (``g`` itself for ideal hardware).
        b0_uT: (M,) spatially uniform field offset, uT (None when the chain has no B0 term).
        kspace_rad_per_m: (3, N_adc) realized k at every ADC sample, rad/m.
        moments_rad_per_m: (3, N_rf - 1) realized k-space moment just before every RF pulse after the first,
            rad/m (None with fewer than two pulses).
    """

    demanded_grad_mT_per_m: torch.Tensor
    realized_grad_mT_per_m: torch.Tensor
    b0_uT: torch.Tensor | None
    kspace_rad_per_m: torch.Tensor
    moments_rad_per_m: torch.Tensor | None


class Twin:
    """A sequence played through a hardware chain: the forward model every command shares.

    Args:
        ir: the sequence (:class:`dtoc.seq.ir.SequenceIR`); its demanded gradient is the default input.
        hardware: the :class:`HardwareChain` (None = ideal hardware: G = g, no B0 term).
        dtype, device: torch precision and device of every tensor the twin returns.
    """

    def __init__(
        self,
        ir: SequenceIR,
        hardware: HardwareChain | None,
        dtype: torch.dtype = torch.float64,
        device: str | torch.device = "cpu",
    ):
        self.ir = ir
        self.hardware = hardware
        self.dtype = dtype
        self.device = torch.device(device)
        self._t_moments_s = np.array([r.t_center_s - 1e-9 for r in ir.rf[1:]], dtype=np.float64)
        self._k_plans: dict = {}  # (what, samples) -> KspacePlan: the index tensors made once (:meth:`_plan`)

    @property
    def is_ideal(self) -> bool:
        """True when the chain is ideal hardware (None, or a model that declares itself identity)."""
        return self.hardware is None or bool(getattr(self.hardware, "is_identity", False))

    def demanded(self, grad_mT_per_m=None) -> torch.Tensor:
        """(3, M) demanded gradient as a tensor of the twin (default: the IR's own)."""
        g = self.ir.grad_mT_per_m if grad_mT_per_m is None else grad_mT_per_m
        if isinstance(g, torch.Tensor):
            return g
        return torch.as_tensor(np.asarray(g), dtype=self.dtype, device=self.device)

    def realize(self, g_fine: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Realized gradient (3, M) mT/m and B0 (M,) uT (None when the chain has no B0 term)."""
        if self.hardware is None:
            return g_fine, None
        out = self.hardware(g_fine[None], self.ir.dt_fine_s)
        if isinstance(out, tuple):
            G, b0 = out[0], (out[1] if len(out) > 1 else None)
        else:
            G, b0 = out, None
        return G[0], (None if b0 is None else b0[0])

    def _plan(self, what: str, n: int):
        """The :class:`~dtoc.seq.kspace.KspacePlan` of the ADC samples ('adc') or the moments ('moments') on
        waveforms of ``n`` fine samples, made on first use: a repeated forward moves nothing from the host (the
        same numbers as :meth:`SequenceIR.kspace_rad_per_m`)."""
        key = (what, n)
        if key not in self._k_plans:
            from dtoc.seq.kspace import KspacePlan

            t = self.ir.adc_times_s if what == "adc" else self._t_moments_s
            rf = self.ir.rf
            self._k_plans[key] = KspacePlan(n, self.ir.dt_fine_s, t, [r.t_center_s for r in rf], [r.use for r in rf])
        return self._k_plans[key]

    def kspace(self, G_fine: torch.Tensor) -> torch.Tensor:
        """(3, N_adc) k-space (rad/m) of a fine-grid waveform at the ADC samples."""
        return self._plan("adc", G_fine.shape[-1])(G_fine)

    def moments(self, G_fine: torch.Tensor) -> torch.Tensor | None:
        """(3, N_rf - 1) k-space moment (rad/m) just before each RF pulse after the first (None if < 2 pulses)."""
        if self._t_moments_s.size == 0:
            return None
        return self._plan("moments", G_fine.shape[-1])(G_fine)

    def forward(self, grad_mT_per_m=None, *, moments: bool = True) -> Realization:
        """Play a demanded waveform (3, M) mT/m (default: the IR's) through the chain; see :class:`Realization`.

        Differentiable with respect to a tensor ``grad_mT_per_m``.  ``moments=False`` skips the RF moments.
        """
        g = self.demanded(grad_mT_per_m)
        G, b0 = self.realize(g)
        k = self.kspace(G)
        return Realization(g, G, b0, k, self.moments(G) if moments else None)
