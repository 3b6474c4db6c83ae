"""Configuration of the PDG simulator (thresholds, limits, chunk sizes); see docs/simulator.md."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class PDGConfig:
    """Thresholds and limits of the phase distribution graph.

    All signal thresholds are in units of the equilibrium magnetisation of one voxel of PD 1, i.e.
    relative to the largest signal one voxel can give.  They are *bounds*: the pre-pass bounds every
    state's amplitude by the sum of the magnitudes of its contributions (no phase cancellation) and
    its later signal by the longest T1, T2, T2' of the phantom, so the true error is smaller.

    Attributes:
        min_magnitude: states (and RF splitting edges) whose amplitude bound is below this are
            dropped while the graph grows (forward pass).  Default 1e-6.
        min_latent_signal: after the forward pass, a state is kept only if (amplitude bound) x
            (bound on what it can still contribute to any later ADC sample, through any chain of
            RF splits) >= this.  Default 1e-5.
        min_emitted_signal: a transverse state is evaluated at an ADC only if its amplitude bound x
            voxel-shape envelope x relaxation bound >= this.  Default 1e-5.  With the defaults the
            image NRMSE of the paper's GRE against :meth:`strict` is 0.2 % (:meth:`fast`: 1.4 %;
            single-shot EPI: exact); docs/simulator.md.
        max_states: at most this many states per RF interval (the largest bounds are kept).
        merge_k_rad_per_m: states whose nominal k differs by less than this (per axis, rounded to
            this quantum) and ...
        merge_tau_s: ... whose dephasing time differs by less than this are merged into one.
        chunk_elems: largest number of (state x sample x voxel) complex elements formed at once in
            the signal evaluation (memory bound: ~ 16 bytes x 4 x chunk_elems in float64 with
            autograd).  Default 2**22.
        signal_method: 'auto' (per interval: 'separable' for >= 256 ADC samples of <= 8 emitting
            states, else 'gemm'), 'gemm' (one shared sample x voxel kernel, states as a matrix
            product), 'direct' (exact exponentials per state, sample and voxel; the reference) or
            'separable' (per-axis phase factors and a windowed Taylor expansion of the in-window
            relaxation/off-resonance, evaluated as matrix products on the Cartesian voxel grid).
            All agree to <= 1e-8 relative (tests/test_sim_physics.py).
        taylor_tol: target relative truncation error of the 'separable' method's Taylor expansion.
        window_samples: ADC samples per window of the 'separable' method.
        line_aware: 'separable' on readouts along lines of constant phase-encoding moment (EPI,
            Cartesian; up to the realized gradient's in-line drift, expanded in a Jacobi-Anger
            series): windows follow the lines and the phase-encoded axis is contracted once per line
            (:func:`dtoc.sim.pdg_signal._apply_kernel_lines`, ~n_pe / terms fewer operations).  True,
            default; False = per-sample windows (the reference for tests and benchmarks).
        voxel_size_z_m: slab thickness for the box voxel attenuation along z (None: no z
            attenuation, the 2D phantom is a sheet).
        object_spectrum: estimate a dephased state's signal with the phantom's PD spectrum at its
            k (True, default; much stronger pruning of spoiled states) instead of the per-voxel
            bound only (False: strict bound, many more states).
        checkpoint_bytes: when autograd would keep more than this (estimate: 8 (S, V) complex
            tensors per RF interval), each interval's relaxation and RF split is recomputed in the
            backward pass instead (torch.utils.checkpoint; ~1.3x compute, memory ~ amplitudes only).
        probe_weighting: amplitude estimate of the pre-pass: 'max' (default: the largest
            magnitude over six probe voxels: mean and longest T1/T2, B1 range) or 'pd' (PD-weighted
            mean magnitude over up to 16 (T1, T2) clusters of the phantom: a pathway living only in
            CSF counts with the CSF fraction; fewer states, an estimate of the object-level signal).
        compress_tissues: propagate the amplitudes once per distinct (T1, T2, D, B1, initial Mz/PD)
            tuple of the phantom instead of once per voxel (exact: the amplitudes depend on nothing
            else and scale with PD; True, default); False = per voxel (reference path for tests).
        fused_signal_adjoint: evaluate the batched 'gemm' signal's state x kernel products as one
            autograd node with a hand-written adjoint (:class:`dtoc.sim.pdg_signal_batch._BatchedGemm`:
            fewer passes over the state x voxel arrays in the backward pass); False = generic
            autograd chain.  Same result up to rounding (tests/test_sim_perf_equivalence.py).
        calibrate_emission: after the bound-based pruning, evaluate once (float32, no autograd, nominal
            gradient, equilibrium Mz = PD) the actual signal of every emitting state on the phantom
            given to :func:`dtoc.sim.pdg.build_graph`, keep as emitters only the states whose peak
            |signal| / sum(PD) >= ``min_emitted_signal``, and prune again with these measured values
            in place of the emission bounds (a state only feeding dropped emitters goes too).  The
            bounds ignore phase cancellation across voxels and use the longest T2 of the phantom;
            the measured values do not, so fewer states reach the same image error
            (docs/simulator.md).  Applies to intervals evaluated by the batched 'gemm' path (the
            others keep their bounds).  Default False.
        tissue_quantum: round every voxel's B1 and initial Mz / PD to multiples of this before the
            tissue tuples are formed (``compress_tissues``), so that a smooth B1 map or a steady-state
            initial Mz (dummy cycles) no longer makes every voxel its own tuple.  An approximation:
            relative flip-angle error <= tissue_quantum / 2, initial-Mz error <= tissue_quantum / 2 x PD
            (docs/simulator.md quantifies the image error).  Default 0 (exact, no rounding).
        schedule: how the main pass is dispatched.  'per_interval': the amplitudes interval by interval
            (:mod:`dtoc.sim.pdg_evolve`), cache-sized signal batches of ~2M elements, their matrix products
            block by block (no padding); many small operations, the fastest on a CPU.  'batched': the
            fused propagation (:mod:`dtoc.sim.pdg_fused`, a constant number of operations per RF
            interval), at most ``signal_batches`` signal batches per ADC sample count and one batched
            matrix product per bucket of similar blocks: few large operations, for a GPU.  'auto'
            (default): 'per_interval' on the CPU, 'batched' on any other device.  The same values up to
            rounding (tests/test_sim_fused.py); docs/simulator.md ("Schedules").
        signal_batches: with the 'batched' schedule, at most this many signal batches per ADC sample
            count (each bounded by 4 x ``chunk_elems``, the kernel budget); None (default): 1 (one batch
            per sample count while the budget holds it).
    """

    min_magnitude: float = 1e-6
    min_latent_signal: float = 1e-5
    min_emitted_signal: float = 1e-5
    max_states: int = 4096
    merge_k_rad_per_m: float = 1e-3
    merge_tau_s: float = 1e-9
    chunk_elems: int = 2**22
    signal_method: str = "auto"
    taylor_tol: float = 1e-9
    window_samples: int = 64
    line_aware: bool = True
    voxel_size_z_m: float | None = None
    object_spectrum: bool = True
    probe_weighting: str = "max"
    checkpoint_bytes: float = 2e9
    compress_tissues: bool = True
    fused_signal_adjoint: bool = True
    calibrate_emission: bool = False
    tissue_quantum: float = 0.0
    schedule: str = "auto"
    signal_batches: int | None = None

    def batched(self, device) -> bool:
        """Whether the main pass on ``device`` takes the 'batched' schedule (see ``schedule``)."""
        if self.schedule not in ("auto", "batched", "per_interval"):
            raise ValueError(f"PDGConfig.schedule must be 'auto', 'batched' or 'per_interval', not {self.schedule!r}")
        if self.schedule == "auto":
            import torch

            return torch.device(device).type != "cpu"
        return self.schedule == "batched"

    @classmethod
    def fast(cls, **overrides) -> PDGConfig:
        """Preset with about MRzeroCore-default accuracy: signal thresholds 1e-4, magnitude 1e-5.

        Paper GRE (32x32, 32 TRs, RF spoiling) on the 3 T brain phantom: image NRMSE 1.4 % against
        :meth:`strict` (the defaults: 0.22 %), ~3x fewer states than the defaults (docs/simulator.md).
        """
        return cls(**{**dict(min_magnitude=1e-5, min_latent_signal=1e-4, min_emitted_signal=1e-4), **overrides})

    @classmethod
    def strict(cls, **overrides) -> PDGConfig:
        """Reference preset: thresholds 1e-8 (magnitude 1e-9), no state cap; ~5x the states of the defaults."""
        return cls(
            **{
                **dict(min_magnitude=1e-9, min_latent_signal=1e-8, min_emitted_signal=1e-8, max_states=100000),
                **overrides,
            }
        )
