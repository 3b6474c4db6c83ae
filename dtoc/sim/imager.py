"""Images of realized waveforms: PDG Bloch simulation of one or more phantoms, then plain iFFT reconstruction.

The targets ``I0`` are simulated with the base (ideal) gradient; the phase-distribution graph depends on
the base sequence only and is built once (its pruning bounds use the tissue range of the first phantom;
rotated copies hold the same tissues).  Units: mT/m, uT; images (ny, nx) as :mod:`dtoc.sim.recon` defines
((nz, ny, nx) for a 3D-encoded sequence on a 3D phantom).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch

from dtoc.sim import recon
from dtoc.sim.pdg import PDGConfig, build_graph, simulate, steady_state_mz
from dtoc.sim.phantom import check_phantom_matches

if TYPE_CHECKING:
    from dtoc.seq.ir import SequenceIR
    from dtoc.sim.phantom import Phantom


class Imager:
    """Simulated images of one or more phantoms through the PDG simulator and iFFT recon.

    Args:
        ir: base sequence.
        phantoms: list of :class:`~dtoc.sim.phantom.Phantom` (e.g. rotated copies for augmentation).
        n_dummies: dummy repetitions for the steady-state initial magnetisation (0: none).
        dtype, device: simulation precision and device.
        config: :class:`~dtoc.sim.pdg.PDGConfig` of the main simulation (default ``PDGConfig()``).
        mz0: precomputed steady-state Mz per phantom (skips the dummy simulation).
        steady_state_options: keyword arguments of :func:`~dtoc.sim.pdg.steady_state_mz` for the dummy train
            (None: its defaults, float64 on the CPU, as ``dtoc optimize`` runs it; ``dtoc simulate`` passes its
            own ``config``, ``dtype`` and ``device``).
        graph: the :func:`~dtoc.sim.pdg.build_graph` of ``ir`` with ``config`` and ``phantoms[0]``, if built already.
    """

    def __init__(
        self,
        ir: SequenceIR,
        phantoms: list[Phantom],
        n_dummies: int = 0,
        dtype: torch.dtype = torch.float64,
        device: str | torch.device = "cpu",
        config: PDGConfig | None = None,
        mz0: list | None = None,
        steady_state_options: dict | None = None,
        graph=None,
    ):
        self.ir = ir
        self.phantoms = phantoms
        self.dtype = dtype
        self.device = device
        self.config = config or PDGConfig()
        self.n_dummies = n_dummies
        for ph in phantoms:
            check_phantom_matches(ir, ph)
        # ``graph``: one built already for this base, config and first phantom (e.g. for a cost estimate)
        self.graph = graph if graph is not None else build_graph(ir, self.config, phantoms[0] if phantoms else None)
        self.mz0: list = []
        #: ideal (base-waveform) signal (n_coils, N_adc) and image (ny, nx) of every phantom
        self.target_signals: list[torch.Tensor] = []
        self.targets: list[torch.Tensor] = []
        for i, ph in enumerate(phantoms):
            if mz0 is not None:
                mz = mz0[i]
            elif n_dummies > 0:
                mz = steady_state_mz(ir, ph, n_dummies, **(steady_state_options or {}))
            else:
                mz = None
            self.mz0.append(mz)
            with torch.no_grad():
                sig = self.signal(None, None, len(self.mz0) - 1)
                self.target_signals.append(sig)
                self.targets.append(self.image(sig).detach())

    def with_config(self, config: PDGConfig, dtype: torch.dtype) -> Imager:
        """The same phantoms and steady state through a different simulator preset / precision
        (e.g. ``PDGConfig.fast()`` and float32 inside the optimizer loop); targets re-simulated with it,
        so image and target share the preset's pruning."""
        return Imager(
            self.ir, self.phantoms, self.n_dummies, dtype=dtype, device=self.device, config=config, mz0=self.mz0
        )

    def signal(self, G_fine: torch.Tensor | None, b0_uT: torch.Tensor | None, idx: int) -> torch.Tensor:
        """(n_coils, N_adc) complex signal of phantom ``idx`` for a realized waveform (None = base)."""
        return simulate(
            self.ir,
            self.phantoms[idx],
            grad_mT_per_m=G_fine,
            b0_uT=b0_uT,
            graph=self.graph,
            config=self.config,
            initial_mz=self._mz0_host(idx),
            dtype=self.dtype,
            device=self.device,
        )

    def _mz0_host(self, idx: int):
        """The steady-state Mz of phantom ``idx`` as a host array, copied from the device once (each
        simulate call then reads it without a device synchronisation); None: equilibrium."""
        mz = self.mz0[idx]
        if not isinstance(mz, torch.Tensor):
            return mz
        cache = self.__dict__.setdefault("_mz0_np", {})
        if idx not in cache or cache[idx][0] is not mz:
            cache[idx] = (mz, mz.detach().cpu().numpy())
        return cache[idx][1]

    def image(self, signal: torch.Tensor, keep_mask=None, grid: recon.CartesianGrid | None = None) -> torch.Tensor:
        """Image by plain iFFT onto the target grid (keep_mask: (N_adc,) bool, False = discarded;
        ``grid``: a precomputed :func:`dtoc.sim.recon.cartesian_grid`, which then carries the mask)."""
        return recon.reconstruct(signal, self.ir, keep_mask=keep_mask, grid=grid)
