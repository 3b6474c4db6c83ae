"""The differentiable digital twin as the optimizer sees it.

``edges (3, N+1) -> played demanded g (3, 2N+1) -> hardware model -> realized G (3, 2N+1), b0 (2N+1)
-> k-space at the ADC samples (3, N_adc) -> PDG Bloch simulation -> iFFT image``.

:class:`Twin` holds the sequence-only part (hardware, k-space); :class:`Imager` the object-dependent
part (phantoms, their target images, the simulator).  Units: mT/m, uT, rad/m, s.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from dtoc.optimize.limits import EdgeProjector, edges_to_played


class Twin:
    """Sequence + hardware model + projector.

    Args:
        ir: the base :class:`~dtoc.seq.ir.SequenceIR` (its gradient is the target G0 = g0).
        hardware: callable ``(g (B, 3, T), dt_s) -> (G (B, 3, T), b0_uT (B, T) or None)``; None = ideal.
        projector: :class:`~dtoc.optimize.limits.EdgeProjector` of this sequence and its limits.
    """

    def __init__(self, ir, hardware: Callable | None, projector: EdgeProjector, dtype=torch.float64, device="cpu"):
        self.ir = ir
        self.hardware = hardware
        self.projector = projector
        self.dtype = dtype
        self.device = torch.device(device)
        self.base_fine = np.asarray(ir.grad_mT_per_m, dtype=np.float64)
        self.fine_mask = projector.fine_free_mask()
        self._base_fine_t = torch.as_tensor(self.base_fine, dtype=dtype, device=self.device)
        self._mask_t = torch.as_tensor(self.fine_mask, device=self.device)
        self.free_t = torch.as_tensor(projector.free, device=self.device)

    def base_edges(self) -> torch.Tensor:
        return torch.as_tensor(self.projector.base, dtype=self.dtype, device=self.device)

    def played(self, edges: torch.Tensor) -> torch.Tensor:
        """(3, 2N+1) played demanded waveform from edge samples (differentiable)."""
        from dtoc.seq.ir import edges_to_fine

        fine = edges_to_fine(edges)
        return torch.where(self._mask_t, fine, self._base_fine_t)

    def realize(self, g_fine: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Realized gradient (3, M) and B0 (M,) uT (None when the model has no B0 term)."""
        if self.hardware is None:
            return g_fine, None
        out = self.hardware(g_fine[None], self.ir.dt_fine_s)
        if isinstance(out, tuple):
            G, b0 = out[0], (out[1] if len(out) > 1 else None)
        else:
            G, b0 = out, None
        return G[0], (None if b0 is None else b0[0])

    def kspace(self, G_fine: torch.Tensor) -> torch.Tensor:
        """(3, N_adc) k-space (rad/m) of a fine-grid waveform at the ADC samples."""
        return self.ir.kspace_rad_per_m(G_fine)

    def moments(self, G_fine: torch.Tensor) -> torch.Tensor | None:
        """(3, N_rf - 1) k-space moment (rad/m) just before each RF pulse after the first (None if < 2 pulses)."""
        t = getattr(self, "_t_mom", None)
        if t is None:
            t = np.array([r.t_center_s - 1e-9 for r in self.ir.rf[1:]], dtype=np.float64)
            self._t_mom = t
        if t.size == 0:
            return None
        return self.ir.kspace_rad_per_m(G_fine, times_s=t)

    def export_fine(self, edges) -> np.ndarray:
        """Played fine waveform of (already projected) edges, numpy float64."""
        e = edges.detach().cpu().numpy() if isinstance(edges, torch.Tensor) else np.asarray(edges)
        return edges_to_played(np.asarray(e, dtype=np.float64), self.base_fine, self.fine_mask)


class Imager:
    """Simulated images of one or more phantoms through the PDG simulator and iFFT recon.

    The targets ``I0`` are simulated with the base (ideal) gradient; the phase-distribution graph
    depends on the base sequence only and is built once per phantom.

    Args:
        ir: base sequence.
        phantoms: list of :class:`~dtoc.sim.phantom.Phantom` (rotated copies for augmentation).
        n_dummies: dummy repetitions for the steady-state initial magnetisation (0: none).
    """

    def __init__(
        self,
        ir,
        phantoms: list,
        n_dummies: int = 0,
        dtype=torch.float64,
        device="cpu",
        config=None,
        mz0: list | None = None,
    ):
        from dtoc.sim import pdg, recon

        self.ir = ir
        self._pdg = pdg
        self._recon = recon
        self.phantoms = phantoms
        self.dtype = dtype
        self.device = device
        self.config = config or pdg.PDGConfig()
        self.n_dummies = n_dummies
        # the graph's pruning bounds use the tissue range of the (first) phantom; rotated copies
        # hold the same tissues
        self.graph = pdg.build_graph(ir, self.config, phantoms[0] if phantoms else None)
        self.mz0 = []
        self.targets = []
        for i, ph in enumerate(phantoms):
            if mz0 is not None:
                mz = mz0[i]
            else:
                mz = pdg.steady_state_mz(ir, ph, n_dummies) if n_dummies > 0 else None
            self.mz0.append(mz)
            with torch.no_grad():
                sig = self.signal(None, None, len(self.mz0) - 1)
                self.targets.append(self.image(sig).detach())

    def with_config(self, config, dtype) -> Imager:
        """The same phantoms and steady state through a different simulator preset / precision
        (e.g. ``PDGConfig.fast()`` and float32 inside the optimizer loop); targets re-simulated with it,
        so image and target share the preset's pruning."""
        return Imager(
            self.ir, self.phantoms, self.n_dummies, dtype=dtype, device=self.device, config=config, mz0=self.mz0
        )

    def signal(self, G_fine, b0_uT, idx: int) -> torch.Tensor:
        """(n_coils, N_adc) complex signal of phantom ``idx`` for a realized waveform (None = base)."""
        return self._pdg.simulate(
            self.ir,
            self.phantoms[idx],
            grad_mT_per_m=G_fine,
            b0_uT=b0_uT,
            graph=self.graph,
            config=self.config,
            initial_mz=self.mz0[idx],
            dtype=self.dtype,
            device=self.device,
        )

    def image(self, signal, keep_mask=None) -> torch.Tensor:
        """Image by plain iFFT onto the target grid (keep_mask: (N_adc,) bool, False = discarded)."""
        return self._recon.reconstruct(signal, self.ir, keep_mask=keep_mask)
