"""Simulation stage: phantoms, the PDG Bloch simulator, reconstruction and image metrics.

Modules (import them directly; this package imports nothing heavy on its own):

* :mod:`dtoc.sim.phantom` -- :class:`~dtoc.sim.phantom.Phantom`, the built-in brain phantom, ``.npz`` I/O, rotation.
* :mod:`dtoc.sim.pdg` -- the phase-distribution-graph simulator (``build_graph``, ``simulate``, ``steady_state_mz``).
* :mod:`dtoc.sim.recon` -- plain inverse-FFT reconstruction assuming nominal k (``reconstruct``, ``cartesian_grid``).
* :mod:`dtoc.sim.metrics` -- NRMSE, EPI ghost ratio, k-space errors (defined in docs/metrics.md).
* :mod:`dtoc.sim.comparison` -- ideal versus realized acquisition (the library side of ``dtoc simulate``).
"""
