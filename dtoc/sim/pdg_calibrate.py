"""Calibrated emission pruning (``PDGConfig.calibrate_emission``): the measured signal of every emitter.

The pre-pass (:func:`dtoc.sim.pdg_graph.build_graph`) bounds what each state can emit; with calibration
on, :func:`dtoc.sim.pdg.build_graph` hands it :func:`emission_peaks`, one cheap forward pass of the main
pass on the phantom, and the graph is pruned a second time with the measured values (docs/simulator.md).
"""

from __future__ import annotations

import dataclasses

import torch

from dtoc.sim.pdg_main import main_loop, prepare


def emission_peaks(ir, phantom, graph, cfg) -> dict:
    """Peak |signal| (max over the interval's ADC samples and the coils; units of the simulated signal,
    PD x voxels) of every emitting state, for the intervals evaluated by the batched 'gemm' path:
    {interval n: (J_n,) array in ``graph.intervals[n].emit`` order}.  One forward pass, float32, no
    autograd, the IR's demanded gradient, equilibrium Mz (= PD).  States evaluated exactly (strong
    diffusion) are reported as +inf.  Passed by :func:`dtoc.sim.pdg.build_graph` to the pre-pass for
    ``PDGConfig.calibrate_emission``."""
    cfg = dataclasses.replace(cfg, calibrate_emission=False)
    probe: dict = {}
    with torch.no_grad():
        main_loop(prepare(ir, phantom, graph, cfg, None, None, None, torch.float32, "cpu"), True, False, probe=probe)
    return probe
