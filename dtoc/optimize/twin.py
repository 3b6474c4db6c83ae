"""The digital twin over the optimizer's variables: raster-edge samples of the demanded gradient.

``edges (3, N+1) -> played demanded g (3, 2N+1) -> Twin.forward (hardware -> G, b0 -> k, moments)``.
:class:`EdgeTwin` adds to the shared forward model (:class:`dtoc.sim.twin.Twin`) the map from the
optimizer's edge variables to the played waveform and back to an exportable waveform; the images come
from :class:`dtoc.sim.imager.Imager`.  Units: mT/m, uT, rad/m, s.
"""

from __future__ import annotations

import numpy as np
import torch

from dtoc.optimize.limits import EdgeProjector, edges_to_played
from dtoc.seq.ir import SequenceIR, edges_to_fine
from dtoc.sim.twin import HardwareChain, Realization, Twin


class EdgeTwin(Twin):
    """Sequence + hardware chain + projector.

    Args:
        ir: the base :class:`~dtoc.seq.ir.SequenceIR` (its gradient is the target G0 = g0).
        hardware: the :class:`~dtoc.sim.twin.HardwareChain`; None = ideal.
        projector: :class:`~dtoc.optimize.limits.EdgeProjector` of this sequence and its limits.
    """

    def __init__(
        self,
        ir: SequenceIR,
        hardware: HardwareChain | None,
        projector: EdgeProjector,
        dtype: torch.dtype = torch.float64,
        device: str | torch.device = "cpu",
    ):
        super().__init__(ir, hardware, dtype=dtype, device=device)
        self.projector = projector
        self.base_fine = np.asarray(ir.grad_mT_per_m, dtype=np.float64)
        self.fine_mask = projector.fine_free_mask()
        self._base_fine_t = torch.as_tensor(self.base_fine, dtype=dtype, device=self.device)
        self._mask_t = torch.as_tensor(self.fine_mask, device=self.device)
        self.free_t = torch.as_tensor(projector.free, device=self.device)

    def base_edges(self) -> torch.Tensor:
        return torch.as_tensor(self.projector.base, dtype=self.dtype, device=self.device)

    def played(self, edges: torch.Tensor) -> torch.Tensor:
        """(3, 2N+1) played demanded waveform from edge samples (differentiable)."""
        fine = edges_to_fine(edges)
        return torch.where(self._mask_t, fine, self._base_fine_t)

    def forward_edges(self, edges: torch.Tensor, *, moments: bool = True) -> Realization:
        """:meth:`Twin.forward` of the waveform played from edge samples (differentiable)."""
        return self.forward(self.played(edges), moments=moments)

    def export_fine(self, edges) -> np.ndarray:
        """Played fine waveform of (already projected) edges, numpy float64."""
        e = edges.detach().cpu().numpy() if isinstance(edges, torch.Tensor) else np.asarray(edges)
        return edges_to_played(np.asarray(e, dtype=np.float64), self.base_fine, self.fine_mask)
