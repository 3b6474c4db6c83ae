"""Simulation stage: the forward model, phantoms, the PDG Bloch simulator, reconstruction and image metrics.

Modules (import them directly; this package imports nothing heavy on its own):

* :mod:`dtoc.sim.twin` -- :class:`~dtoc.sim.twin.Twin`, the one forward model: demanded gradient -> hardware
  chain -> realized gradient and B0 -> k-space (:class:`~dtoc.sim.twin.Realization`).
* :mod:`dtoc.sim.imager` -- :class:`~dtoc.sim.imager.Imager`: PDG images of realized waveforms and their targets.
* :mod:`dtoc.sim.phantom` -- :class:`~dtoc.sim.phantom.Phantom`, the built-in brain phantom, ``.npz`` I/O, rotation.
* :mod:`dtoc.sim.pdg` -- the phase-distribution-graph simulator (``build_graph``, ``simulate``, ``steady_state_mz``).
* :mod:`dtoc.sim.recon` -- plain inverse-FFT reconstruction assuming nominal k (``reconstruct``, ``cartesian_grid``).
* :mod:`dtoc.sim.metrics` -- NRMSE, EPI ghost ratio, k-space errors (defined in docs/metrics.md).
* :mod:`dtoc.sim.comparison` -- ideal versus realized acquisition (the library side of ``dtoc simulate``).
* :mod:`dtoc.sim.predict` -- realized versus demanded waveforms and k-space (the library side of ``dtoc predict``).
"""
