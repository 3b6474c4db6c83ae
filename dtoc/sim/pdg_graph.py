"""The PDG pre-pass (numpy): states, RF splitting edges, merging, pruning, emitting states.

Model (docs/simulator.md): between two RF centres the magnetisation is a sum of configuration
states.  A *transverse* state j contributes ``a_j(v) exp(-i (k_j . r + omega tau_j))`` to M+ = Mx + i My
of voxel v, a *longitudinal* state contributes ``Re(a_j(v) exp(-i (k_j . r + omega tau_j)))`` to Mz.
k_j (rad/m) is the state's dephasing and tau_j (s) its dephasing time (the time it has spent
transverse, counted with sign: a conjugated state has -tau).  Gradients shift k of transverse states,
time shifts their tau; longitudinal states keep both.  An instantaneous RF rotation (flip alpha,
phase phi) maps each state to up to three children (edge kinds, right-handed rotation about
(cos phi, sin phi, 0), Weigel's EPG matrix):

===== ============ ============================== ==============
kind  parent -> ch coefficient on parent amplitude pattern
===== ============ ============================== ==============
0     + -> +       cos^2(a/2)                     same
1     + -> +       e^{2i phi} sin^2(a/2) * conj   conjugated (k, tau -> -k, -tau)
2     + -> z       -i e^{-i phi} sin a            same
3     z -> +       -i e^{i phi} sin a / 2         same
4     z -> +       -i e^{i phi} sin a / 2 * conj  conjugated
5     z -> z       cos a                          same
===== ============ ============================== ==============

Children with the same (type, nominal k, nominal tau) are merged.  The pre-pass runs on the nominal
(demanded) gradient only; the main pass (:mod:`dtoc.sim.pdg_main`) recomputes every state's k from
the realized gradient along its *representative* parent (the edge carrying the largest amplitude
bound), so k stays differentiable w.r.t. the gradient.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from dtoc.constants import GAMMA_RAD_PER_S_PER_MT
from dtoc.seq.ir import SequenceIR
from dtoc.sim.pdg_config import PDGConfig
from dtoc.sim.pdg_graph_step import emission_native, native_in_use, prune_native, split_step, unique_bits
from dtoc.sim.pdg_rows import CONJ, first_max_by_group


@dataclass
class IntervalGraph:
    """States alive between two consecutive RF centres (or the sequence start/end).

    Attributes:
        t_start_s, t_end_s: interval bounds, s (RF centres; 0 and the sequence end at the ends).
        is_z: (S,) True for longitudinal states.
        tau_s: (S,) nominal dephasing time at the interval start, s.
        k_nom_rad_per_m: (S, 3) nominal dephasing at the interval start, rad/m.
        eq_index: index of the equilibrium state (longitudinal, k = 0, tau = 0), which receives
            T1 recovery; always present.
        edge_child, edge_parent, edge_kind: (E,) RF splitting edges from the previous interval's
            states (at its end) into this interval's states (empty for interval 0).
        rep_parent: (S,) representative parent (index into the previous interval) giving the
            state's k; -1 for the equilibrium state and for states of interval 0.
        rep_conj: (S,) True when the representative edge conjugates (k -> -k).
        emit: (J,) indices of transverse states evaluated at this interval's ADC samples.
        adc_start, adc_stop: slice of the time-sorted ADC samples inside this interval.
        mag: (S,) amplitude bound (units of PD).
    """

    t_start_s: float
    t_end_s: float
    is_z: np.ndarray
    tau_s: np.ndarray
    k_nom_rad_per_m: np.ndarray
    eq_index: int
    edge_child: np.ndarray
    edge_parent: np.ndarray
    edge_kind: np.ndarray
    rep_parent: np.ndarray
    rep_conj: np.ndarray
    emit: np.ndarray
    adc_start: int
    adc_stop: int
    mag: np.ndarray

    @property
    def n_states(self) -> int:
        return int(self.is_z.shape[0])


@dataclass
class PDGGraph:
    """Result of :func:`build_graph`: one :class:`IntervalGraph` per RF interval.

    Attributes:
        intervals: NI = n_rf + 1 interval graphs (interval n starts at RF n-1).
        rf_order: indices into ``ir.rf`` in time order (RF n of the graph = ``ir.rf[rf_order[n]]``).
        adc_times_s: (N_adc,) ADC sample times sorted ascending, s.
        adc_order: (N_adc,) index into the IR-ordered ADC samples of each sorted sample.
        adc_phase_rad: (N_adc,) receiver phase of each sorted sample, rad.
        tau_ignored: True when the phantom had neither B0 nor finite T2', so states were merged
            regardless of tau (then the graph must not be used with a phantom that has either).
        config: the configuration used.
        n_fine: fine-grid length of the IR it was built for (consistency check).
    """

    intervals: list[IntervalGraph]
    rf_order: np.ndarray
    adc_times_s: np.ndarray
    adc_order: np.ndarray
    adc_phase_rad: np.ndarray
    tau_ignored: bool
    config: PDGConfig
    n_fine: int
    meta: dict = field(default_factory=dict)

    @property
    def n_states_total(self) -> int:
        return int(sum(iv.n_states for iv in self.intervals))

    @property
    def n_emitting_total(self) -> int:
        return int(sum(iv.emit.size for iv in self.intervals))

    def summary(self) -> dict:
        """Counts for logs and reports."""
        s = [iv.n_states for iv in self.intervals]
        return {
            "intervals": len(self.intervals),
            "states_total": int(sum(s)),
            "states_max": int(max(s)) if s else 0,
            "emitting_total": self.n_emitting_total,
            "edges_total": int(sum(iv.edge_child.size for iv in self.intervals)),
            "tau_ignored": self.tau_ignored,
        }


# ------------------------------------------------------------------------------------------------
def rf_edge_magnitude_bounds(flip_rad: float, b1_samples: np.ndarray) -> np.ndarray:
    """(6,) max over the B1 samples of |coefficient| of each edge kind (see module table)."""
    a = flip_rad * np.asarray(b1_samples, dtype=np.float64)
    c2 = np.cos(a / 2) ** 2
    s2 = np.sin(a / 2) ** 2
    s = np.abs(np.sin(a))
    c = np.abs(np.cos(a))
    return np.array([c2.max(), s2.max(), s.max(), 0.5 * s.max(), 0.5 * s.max(), c.max()])


def rf_edge_coefficients_np(flip_rad: float, phase_rad: float, b1: np.ndarray) -> np.ndarray:
    """(6, P) complex edge coefficients (module table) for relative B1 values ``b1`` (P,)."""
    a = flip_rad * np.asarray(b1, dtype=np.float64)
    e1 = np.exp(1j * phase_rad)
    return np.stack(
        [
            np.cos(a / 2) ** 2 + 0j,
            e1 * e1 * np.sin(a / 2) ** 2,
            -1j * np.conj(e1) * np.sin(a),
            -0.5j * e1 * np.sin(a),
            -0.5j * e1 * np.sin(a),
            np.cos(a) + 0j,
        ]
    )


def voxel_envelope(k_rad_per_m: np.ndarray, voxel_m: tuple, shape: str) -> np.ndarray:
    """Upper bound of the voxel-shape attenuation for dephasing k (..., 3) -> (...).

    'box': |sinc(k d / 2)| <= min(1, 2 / (|k| d)) per axis; 'sinc' voxel: 1 inside |k| <= pi/d else 0;
    'none': 1.  Axes with voxel size None are not attenuated.
    """
    k = np.asarray(k_rad_per_m, dtype=np.float64)
    return voxel_envelope_axes((k[..., 0], k[..., 1], k[..., 2]), voxel_m, shape)


def voxel_envelope_axes(k_axes: tuple, voxel_m: tuple, shape: str) -> np.ndarray:
    """:func:`voxel_envelope` of k given per axis (kx, ky, kz), rad/m, arrays that broadcast together (an
    axis constant along a readout can be passed with a length-1 dimension: same values, less work)."""
    k = [np.abs(np.asarray(ka, dtype=np.float64)) for ka in k_axes]
    env = np.ones(np.broadcast_shapes(*(ka.shape for ka in k)))
    if shape == "none":
        return env
    for a, d in enumerate(voxel_m):
        if d is None or d <= 0:
            continue
        if shape == "box":
            with np.errstate(divide="ignore"):
                env = env * np.minimum(1.0, 2.0 / (k[a] * d))
        else:
            env = env * (k[a] <= np.pi / d + 1e-9)
    return env


@dataclass
class _Bounds:
    """Relaxation bounds used for pruning (longest times of the phantom) and probe voxels.

    Probe voxels (T1, T2, B1) are simulated with complex amplitudes in the pre-pass, so that the
    amplitude estimate of a merged state includes the cancellation of its contributions (RF
    spoiling); the estimate is the largest magnitude over the probes.
    """

    t1: float = np.inf
    t2: float = np.inf
    t2d: float = np.inf
    b1: np.ndarray = field(default_factory=lambda: np.ones(1))
    voxel_m: tuple = (None, None, None)
    voxel_shape: str = "box"
    probe_t1: np.ndarray = field(default_factory=lambda: np.array([np.inf]))
    probe_t2: np.ndarray = field(default_factory=lambda: np.array([np.inf]))
    probe_b1: np.ndarray = field(default_factory=lambda: np.ones(1))
    probe_w: np.ndarray | None = None  # PD weights of the probes ('pd' weighting), else None (max)

    def amp_estimate(self, amp: np.ndarray) -> np.ndarray:
        """(S,) amplitude estimate from (S, P) complex probe amplitudes."""
        if self.probe_w is None:
            a = np.abs(amp)
            m = a[:, 0].copy()
            for p in range(1, a.shape[1]):  # column by column: ~10x faster than .max(axis=1) on few columns
                np.maximum(m, a[:, p], out=m)
            return m
        return np.abs(amp) @ self.probe_w

    def e1(self, dt):
        return np.exp(-np.asarray(dt) / self.t1)

    def e2(self, dt):
        return np.exp(-np.asarray(dt) / self.t2)


class ObjectSpectrum:
    """Estimate of how much signal a state of dephasing k can give, relative to k = 0.

    |sum_v pd(v) exp(-i k.r_v)| / sum_v pd(v), times the voxel-shape factor, from a 2x zero-padded
    FFT of the PD map (3D FFT for a 3D phantom) (nearest grid point, max over the 2x2 neighbours; periodic beyond the voxel
    Nyquist, as the voxel sum is).  This is an *estimate* (the state's amplitude map is not PD), used
    only for pruning; docs/simulator.md quantifies the resulting error.
    """

    def __init__(self, phantom, floor: float = 0.0):
        ny, nx = phantom.pd.shape[-2:]
        pad = 2
        pd = phantom.pd
        tot = float(pd.sum()) or 1.0
        if pd.ndim == 3:  # a 3D phantom: the same estimate over (kz, ky, kx)
            F = np.abs(np.fft.fftn(pd, s=tuple(pad * n for n in pd.shape))) / tot
            F = np.maximum.reduce([np.roll(F, s, (0, 1, 2)) for s in np.ndindex(2, 2, 2)])
            self.dz = phantom.fov_m[2] / pd.shape[0]
            self.step_z = 2 * np.pi / (pad * pd.shape[0] * self.dz)
        else:
            F = np.abs(np.fft.fft2(pd, s=(pad * ny, pad * nx)))
            F = F / tot
            # conservative: max over each point and its +1 neighbours
            F = np.maximum.reduce([F, np.roll(F, 1, 0), np.roll(F, 1, 1), np.roll(np.roll(F, 1, 0), 1, 1)])
        self.F = np.maximum(F, floor)
        self.dx, self.dy = phantom.fov_m[0] / nx, phantom.fov_m[1] / ny
        self.step_x = 2 * np.pi / (pad * nx * self.dx)
        self.step_y = 2 * np.pi / (pad * ny * self.dy)
        self.shape = phantom.voxel_shape

    def row_max(self) -> np.ndarray:
        """The largest value of each row (ky) of a 2D spectrum, computed once."""
        if not hasattr(self, "_row_max"):
            self._row_max = self.F.max(axis=1)
        return self._row_max

    def max_value(self) -> float:
        """The spectrum's largest value, computed once."""
        if not hasattr(self, "_max"):
            self._max = float(self.F.max())
        return self._max

    def bound_at_ky(self, ky: np.ndarray, dist_x: np.ndarray) -> np.ndarray:
        """An upper bound of :meth:`at_axes` over every kx with abs(kx) >= ``dist_x`` at the given ``ky`` (same
        row of the spectrum, same y factor) and any kz: the row's maximum times the x factor's envelope
        (abs(sinc(u)) <= 1 / (pi abs(u))).  3D phantoms: 1."""
        if self.F.ndim == 3:
            return np.ones(np.shape(ky))
        val = self.row_max()[np.round(ky / self.step_y).astype(np.int64) % self.F.shape[-2]]
        if self.shape == "box":
            with np.errstate(divide="ignore"):
                xb = np.minimum(1.0, 2.0 / (dist_x * self.dx))
            val = val * xb * np.abs(np.sinc(ky * self.dy / (2 * np.pi)))
        elif self.shape == "sinc":
            val = val * (np.abs(ky) <= np.pi / self.dy)
        return np.minimum(val, 1.0)

    def __call__(self, k: np.ndarray) -> np.ndarray:
        """k (..., 3) rad/m -> (...) estimate in [0, 1]."""
        return self.at_axes(k[..., 0], k[..., 1], k[..., 2])

    def at_axes(self, kx: np.ndarray, ky: np.ndarray, kz: np.ndarray) -> np.ndarray:
        """The estimate for k given per axis, rad/m, arrays that broadcast together."""
        ix = np.round(kx / self.step_x).astype(np.int64) % self.F.shape[-1]
        iy = np.round(ky / self.step_y).astype(np.int64) % self.F.shape[-2]
        if self.F.ndim == 3:
            iz = np.round(kz / self.step_z).astype(np.int64) % self.F.shape[0]
            val = self.F[iz, iy, ix]
        else:
            val = self.F[iy, ix]
        if self.shape == "box":
            val = val * np.abs(np.sinc(kx * self.dx / (2 * np.pi)) * np.sinc(ky * self.dy / (2 * np.pi)))
            if self.F.ndim == 3:
                val = val * np.abs(np.sinc(kz * self.dz / (2 * np.pi)))
        elif self.shape == "sinc":
            val = val * ((np.abs(kx) <= np.pi / self.dx) & (np.abs(ky) <= np.pi / self.dy))
            if self.F.ndim == 3:
                val = val * (np.abs(kz) <= np.pi / self.dz)
        return np.minimum(val, 1.0)


def _distance_to_zero(a0: np.ndarray, a1: np.ndarray) -> np.ndarray:
    """Smallest abs(x) over x in [a0, a1] (elementwise; a0 <= a1), shrunk by 1e-9 relative: a lower bound of abs()
    of any value computed inside the range."""
    return np.where((a0 <= 0) & (a1 >= 0), 0.0, np.minimum(np.abs(a0), np.abs(a1))) * (1.0 - 1e-9)


def _bounds(ir: SequenceIR, config: PDGConfig, phantom) -> _Bounds:
    b = _Bounds()
    zsize = config.voxel_size_z_m
    if phantom is not None:
        m = phantom.pd > 0
        if not m.any():
            m = np.ones_like(phantom.pd, dtype=bool)
        b.t1 = float(np.max(phantom.t1_s[m]))
        b.t2 = float(np.max(phantom.t2_s[m]))
        b.t2d = float(np.max(phantom.t2dash_s[m]))
        lo, hi = float(np.min(phantom.b1[m])), float(np.max(phantom.b1[m]))
        b.b1 = np.linspace(lo, hi, 9) if hi > lo else np.array([lo])
        w = phantom.pd[m]
        with np.errstate(divide="ignore"):
            mt1 = 1.0 / np.average(1.0 / phantom.t1_s[m], weights=w)
            mt2 = 1.0 / np.average(1.0 / phantom.t2_s[m], weights=w)
        mb1 = float(np.average(phantom.b1[m], weights=w))
        if config.probe_weighting == "pd":
            # PD-weighted clusters: 4 x 4 quantile bins of (T1, T2), B1 = bin mean
            t1v, t2v, b1v = phantom.t1_s[m], phantom.t2_s[m], phantom.b1[m]
            q1 = np.quantile(t1v, [0.25, 0.5, 0.75])
            q2 = np.quantile(t2v, [0.25, 0.5, 0.75])
            lab = np.searchsorted(q1, t1v) * 4 + np.searchsorted(q2, t2v)
            T1s, T2s, B1s, Ws = [], [], [], []
            for c in np.unique(lab):
                sel = lab == c
                ww = w[sel]
                T1s.append(1.0 / np.average(1.0 / t1v[sel], weights=ww))
                T2s.append(1.0 / np.average(1.0 / t2v[sel], weights=ww))
                B1s.append(np.average(b1v[sel], weights=ww))
                Ws.append(ww.sum())
            b.probe_t1, b.probe_t2, b.probe_b1 = np.array(T1s), np.array(T2s), np.array(B1s)
            b.probe_w = np.array(Ws) / np.sum(Ws)
        else:
            b.probe_t1 = np.array([mt1, b.t1, b.t1, b.t1, mt1, mt1])
            b.probe_t2 = np.array([mt2, b.t2, b.t2, b.t2, mt2, mt2])
            b.probe_b1 = np.array([mb1, mb1, lo, hi, lo, hi])
        ny, nx = phantom.shape[-2:]
        b.voxel_m = (phantom.fov_m[0] / nx, phantom.fov_m[1] / ny, phantom.voxel_size_z_m if phantom.is_3d else zsize)
        b.voxel_shape = phantom.voxel_shape
    elif ir.geometry is not None:
        vx, vy, vz = ir.geometry.voxel_m
        b.voxel_m = (vx, vy, zsize if vz is None else vz)
    return b


def nominal_integrals(ir: SequenceIR, *times: np.ndarray) -> list[np.ndarray]:
    """(Q, 3) gamma * integral_0^t of the demanded gradient, rad/m, for each array of query times (exact PWL).

    The numpy form of :func:`dtoc.seq.kspace.pwl_integral_at` (the same operations in the same order, so the same
    bits: tests/test_prepass_equivalence.py), with the running integral computed once for all the arrays and
    without torch's start-up cost in a fresh process."""
    g = np.asarray(ir.grad_mT_per_m, dtype=np.float64)
    dt = ir.dt_fine_s
    M = g.shape[-1]
    C = np.empty_like(g)  # running integral at the samples, built in place (long files: few whole-length passes)
    C[:, 0] = 0.0
    inc = C[:, 1:]
    np.add(g[:, 1:], g[:, :-1], out=inc)
    np.multiply(inc, 0.5 * dt, out=inc)
    np.cumsum(inc, axis=-1, out=inc)
    out = []
    for ts in times:
        t = np.clip(np.asarray(ts, dtype=np.float64), 0.0, (M - 1) * dt)
        m = np.clip(np.floor(t / dt + 1e-9).astype(np.int64), 0, max(M - 2, 0))
        tau = t - m * dt
        g0 = g[:, m]
        g1 = g[:, m + 1] if M > 1 else g0
        out.append((GAMMA_RAD_PER_S_PER_MT * (C[:, m] + tau * g0 + 0.5 * tau * tau * (g1 - g0) / dt)).T)
    return out


def build_graph(
    ir: SequenceIR,
    config: PDGConfig,
    phantom=None,
    *,
    final_z_readout: bool = False,
    measure_emission: Callable | None = None,
) -> PDGGraph:
    """Build the PDG of ``ir`` (see :func:`dtoc.sim.pdg.build_graph`).

    ``final_z_readout`` (used by the dummy-cycle steady state): longitudinal states at the end of the
    sequence count as observed (with the voxel envelope), so pruning keeps what shapes the final Mz.
    ``measure_emission(ir, phantom, graph, config) -> {interval: peaks}``: the measured emission of the
    first graph's emitters (:func:`dtoc.sim.pdg_calibrate.emission_peaks`), used for a second prune when
    ``config.calibrate_emission`` (None: no calibration).
    """
    cfg = config
    bnd = _bounds(ir, cfg, phantom)
    tau_ignored = bool(
        phantom is not None
        and not np.any(phantom.b0_hz[phantom.pd > 0])
        and np.all(np.isinf(phantom.t2dash_s[phantom.pd > 0]))
    )

    # --- events --------------------------------------------------------------------------------
    rf_t = np.array([r.t_center_s for r in ir.rf], dtype=np.float64)
    rf_order = np.argsort(rf_t, kind="stable")
    rf_t = rf_t[rf_order]
    bounds_t = np.concatenate([[0.0], rf_t, [ir.duration_s]])
    NI = len(bounds_t) - 1
    adc_t_ir = ir.adc_times_s
    adc_ph_ir = np.concatenate([np.full(a.num_samples, a.phase_rad) for a in ir.adc]) if ir.adc else np.zeros(0)
    adc_order = np.argsort(adc_t_ir, kind="stable")
    adc_t = adc_t_ir[adc_order]
    adc_ph = adc_ph_ir[adc_order]
    # sample at exactly an RF centre belongs to the interval after it
    adc_lo = np.searchsorted(adc_t, bounds_t[:-1], side="left")
    adc_hi = np.searchsorted(adc_t, bounds_t[1:], side="left")
    adc_hi[-1] = adc_t.size
    adc_lo[0] = 0

    I_b, I_adc = nominal_integrals(ir, bounds_t, adc_t)  # (NI+1, 3), (N_adc, 3)
    m_int = I_b[1:] - I_b[:-1]  # (NI, 3) nominal moment per interval
    dt_int = np.diff(bounds_t)

    qk, qt = cfg.merge_k_rad_per_m, cfg.merge_tau_s

    def keys(is_z, k, tau):
        tk = np.zeros_like(tau, dtype=np.int64) if tau_ignored else np.round(tau / qt).astype(np.int64)
        return np.concatenate([is_z[:, None].astype(np.int64), np.round(k / qk).astype(np.int64), tk[:, None]], axis=1)

    # --- forward pass --------------------------------------------------------------------------
    raw: list[dict[str, Any]] = []  # per interval dict of arrays
    is_z = np.array([True])
    k = np.zeros((1, 3))
    tau = np.zeros(1)
    probe_t1, probe_t2, probe_b1 = bnd.probe_t1, bnd.probe_t2, bnd.probe_b1
    if bnd.probe_w is None:
        # the estimate is the largest magnitude over the probes: identical probes (a phantom without B1 map has 2
        # distinct of 6) give identical columns, so each is propagated once (same maxima, bit for bit)
        _, first = np.unique(np.stack([probe_t1, probe_t2, probe_b1], axis=1), axis=0, return_index=True)
        pi = np.sort(first)
        probe_t1, probe_t2, probe_b1 = probe_t1[pi], probe_t2[pi], probe_b1[pi]
    P = probe_t1.size
    amp = np.ones((1, P), dtype=np.complex128)
    mag = np.ones(1)
    eq = 0
    e_child = e_par = e_kind = np.zeros(0, dtype=np.int64)
    e_cand: np.ndarray = np.zeros(0)
    for n in range(NI):
        raw.append(
            dict(is_z=is_z, k=k, tau=tau, mag=mag, eq=eq, e_child=e_child, e_par=e_par, e_kind=e_kind, e_cand=e_cand)
        )
        if n == NI - 1:
            break
        dt = dt_int[n]
        tr = ~is_z
        k_end = k + tr[:, None] * m_int[n][None, :]
        tau_end = tau + tr * dt
        pe1 = np.exp(-dt / probe_t1)
        pe2 = np.exp(-dt / probe_t2)
        amp_end = amp * np.where(tr[:, None], pe2[None, :], pe1[None, :])
        amp_end[eq] += 1.0 - pe1
        rf = ir.rf[rf_order[n]]
        pc = rf_edge_coefficients_np(rf.flip_angle_rad, rf.phase_rad, probe_b1)  # (6, P)
        st = split_step(
            is_z,
            k_end,
            tau_end,
            amp_end,
            pc,
            qk,
            qt,
            tau_ignored,
            cfg.min_magnitude,
            cfg.max_states,
            bnd.amp_estimate,
            keys,
        )
        is_z, k, tau, mag, amp, eq = st.is_z, st.k, st.tau, st.mag, st.amp, st.eq
        e_child, e_par, e_kind, e_cand = st.e_child, st.e_par, st.e_kind, st.e_cand

    # --- emission and latent bounds (backward) --------------------------------------------------
    spec = ObjectSpectrum(phantom) if (phantom is not None and cfg.object_spectrum) else None
    em = _Emission(raw, bnd, spec, adc_t, adc_lo, adc_hi, bounds_t, I_adc, I_b, cfg.min_emitted_signal, final_z_readout)
    ctx = dict(
        raw=raw,
        ir=ir,
        rf_order=rf_order,
        bnd=bnd,
        dt_int=dt_int,
        adc_lo=adc_lo,
        adc_hi=adc_hi,
        bounds_t=bounds_t,
        cfg=cfg,
    )
    emit_b: list[Any] = [None] * NI
    latent = _latent(ctx, emit_b, em.of)
    intervals, keeps = _prune(ctx, emit_b, latent)

    def graph_of(ivs):
        return PDGGraph(
            intervals=ivs,
            rf_order=rf_order,
            adc_times_s=adc_t,
            adc_order=adc_order,
            adc_phase_rad=adc_ph,
            tau_ignored=tau_ignored,
            config=cfg,
            n_fine=ir.n_fine,
        )

    graph = graph_of(intervals)
    if (
        measure_emission is not None
        and cfg.calibrate_emission
        and phantom is not None
        and not final_z_readout
        and adc_t.size
        and graph.n_emitting_total
    ):
        peaks = measure_emission(ir, phantom, graph, cfg)
        tot = float(np.sum(phantom.pd)) or 1.0
        emit_c = []
        for n, R in enumerate(raw):
            if n not in peaks:  # not evaluated by the batched path: keep the bounds (all of them evaluated)
                emit_c.append(np.where(keeps[n], em.of(n, None), 0.0))
                continue
            e = np.zeros(R["is_z"].size)
            src = np.where(keeps[n])[0][intervals[n].emit]  # raw index of each emitting state
            e[src] = peaks[n] / tot / np.maximum(R["mag"][src], 1e-300)
            emit_c.append(e)
        intervals, _ = _prune(ctx, emit_c, _latent(ctx, emit_c), restrict=keeps)
        graph = graph_of(intervals)
        graph.meta["calibrated_intervals"] = len(peaks)
    return graph


#: the emission bound is evaluated for at most this many (state, ADC sample) pairs at a time (memory bound)
EXACT_CHUNK_ELEMS = 2**22


class _Emission:
    """Emission bounds of the raw states of :func:`build_graph`: per state, the largest signal it can give at its
    interval's ADC samples per unit amplitude (voxel envelope, object spectrum, T2 and T2' decay; final
    longitudinal states when the final Mz is observed)."""

    def __init__(self, raw, bnd, spec, adc_t, adc_lo, adc_hi, bounds_t, I_adc, I_b, min_emitted, final_z_readout):
        self.raw, self.bnd, self.spec = raw, bnd, spec
        self.adc_t, self.adc_lo, self.adc_hi, self.bounds_t = adc_t, adc_lo, adc_hi, bounds_t
        self.I_adc, self.I_b = I_adc, I_b
        self.min_emitted, self.final_z_readout = min_emitted, final_z_readout

    def envelope(self, kx, ky, kz):
        e = voxel_envelope_axes((kx, ky, kz), self.bnd.voxel_m, self.bnd.voxel_shape)
        return e if self.spec is None else np.minimum(e, self.spec.at_axes(kx, ky, kz))

    def _window(self, n: int):
        lo, hi = self.adc_lo[n], self.adc_hi[n]
        return self.adc_t[lo:hi] - self.bounds_t[n], self.I_adc[lo:hi] - self.I_b[n]

    def exact(self, n: int, idx: np.ndarray) -> np.ndarray:
        """Emission bound of the transverse states ``idx`` of interval ``n`` at its ADC samples (max over them)."""
        if native_in_use() and idx.size:
            return self._exact_native(n, idx)
        R, bnd = self.raw[n], self.bnd
        out = np.empty(idx.size)
        dtt, mt = self._window(n)
        fixed = [bool(np.all(mt[:, a] == mt[0, a])) for a in range(3)]
        # chunk over states to bound memory (S x T)
        step = max(1, int(EXACT_CHUNK_ELEMS // max(1, dtt.size)))
        for s0 in range(0, idx.size, step):
            ks = R["k"][idx[s0 : s0 + step]]
            # per axis (S, T), or (S, 1) where the nominal gradient is off during the window (same values)
            env = self.envelope(*(ks[:, a, None] + (mt[None, :1, a] if fixed[a] else mt[None, :, a]) for a in range(3)))
            tt = np.abs(R["tau"][idx[s0 : s0 + step]][:, None] + dtt[None, :])
            env = env * bnd.e2(dtt)[None, :] * np.exp(-tt / bnd.t2d)
            out[s0 : s0 + step] = env.max(axis=1)
        return out

    def _exact_native(self, n: int, idx: np.ndarray, best: np.ndarray | None = None) -> np.ndarray:
        """:meth:`exact` with the compiled core (``emission`` in ``dtoc/sim/_pdg_split.c``): every exactly rounded
        operation there, the transcendental functions numpy's -- the T2' decay once per distinct tau and sample, the
        spectrum's sincs only at the samples that can still hold a state's maximum (each state's sample of largest
        upper bound, then those whose bound exceeds the value found there).  With ``best`` (the states' bounds
        through their children, see :meth:`of`), a state or sample whose upper bound can change neither its latent
        bound nor its emitter decision is left out as :meth:`of` leaves out states: the latent bounds and decisions
        are those of the exact values, bit for bit; a value at or below ``best`` may be returned lower."""
        R, bnd, spec = self.raw[n], self.bnd, self.spec
        dtt, mt = self._window(n)
        step = max(1, int(EXACT_CHUNK_ELEMS // max(1, dtt.size)))  # states per call: bounded (states x samples)
        if idx.size > step:
            return np.concatenate(
                [
                    self._exact_native(n, idx[s0 : s0 + step], None if best is None else best[s0 : s0 + step])
                    for s0 in range(0, idx.size, step)
                ]
            )
        mt = np.ascontiguousarray(mt)
        S, T = idx.size, dtt.size
        ks = np.ascontiguousarray(R["k"][idx])
        fixed = [bool(np.all(mt[:, a] == mt[0, a])) for a in range(3)]
        vshape = {"box": 1, "sinc": 2}.get(bnd.voxel_shape, 0)
        vd = [0.0 if (d is None or d <= 0) else float(d) for d in bnd.voxel_m]
        if spec is None:
            sshape, s3d, nsz, steps, sd, F = -1, 0, (1, 1, 1), (1.0, 1.0, 1.0), (1.0, 1.0, 1.0), None
            fmax, rowmax = 1.0, None
        else:
            s3d = int(spec.F.ndim == 3)
            sshape = {"box": 1, "sinc": 2}.get(spec.shape, 0)
            nsz = (spec.F.shape[-1], spec.F.shape[-2], spec.F.shape[0] if s3d else 1)
            steps = (spec.step_x, spec.step_y, spec.step_z if s3d else 1.0)
            sd = (spec.dx, spec.dy, spec.dz if s3d else 1.0)
            F = np.ascontiguousarray(spec.F, dtype=np.float64).reshape(-1)
            fmax, rowmax = spec.max_value(), None if s3d else np.ascontiguousarray(spec.row_max(), dtype=np.float64)
        ut, it = unique_bits(R["tau"][idx])
        etau = np.exp(-np.abs(ut[:, None] + dtt[None, :]) / bnd.t2d)
        e2 = np.ascontiguousarray(bnd.e2(dtt))
        thr = float(self.min_emitted) if best is not None else 0.0
        params = (S, T, *fixed, vshape, *vd, sshape, s3d, *nsz, *steps, *sd, thr, fmax)
        common = (
            ks,
            mt,
            e2,
            it,
            np.ascontiguousarray(etau),
            F,
            None if best is None else np.ascontiguousarray(best, dtype=np.float64),
            np.ascontiguousarray(R["mag"][idx], dtype=np.float64),
            np.ascontiguousarray((e2[None, :] * etau).max(axis=1)),
            rowmax,
        )
        out = np.empty(S)
        tstar = np.empty(S, dtype=np.int64)
        ub = np.empty((S, T))
        ns = np.empty(S, dtype=np.int64)
        N = emission_native(1, params, (*common, out, tstar, ub, ns))
        if sshape != 1 or N == 0:
            return out

        def sincs(s_idx: np.ndarray, t_idx: np.ndarray) -> np.ndarray:
            """(C, 3) numpy's sinc of each axis' k at the elements (state, sample), as exact() forms them."""
            sv = np.zeros((s_idx.size, 3))
            for a in range(3 if s3d else 2):
                kk = ks[s_idx, a] + (mt[0, a] if fixed[a] else mt[t_idx, a])
                sv[:, a] = np.sinc(kk * sd[a] / (2 * np.pi))
            return sv

        ns = ns[:N]
        cs = np.empty(S * T, dtype=np.int64)
        ct = np.empty(S * T, dtype=np.int64)
        nc = emission_native(2, params, (*common, ns, tstar, ub, sincs(ns, tstar[ns]), out, cs, ct))
        if nc:
            cs, ct = cs[:nc], ct[:nc]
            emission_native(3, params, (*common, cs, ct, sincs(cs, ct), out))
        return out

    def bound(self, n: int, idx: np.ndarray) -> np.ndarray:
        """An upper bound of :meth:`exact` of the states ``idx`` of interval ``n`` from the range of the moment over
        the window (the voxel envelope is non-increasing in abs(k); where ky is constant, the spectrum row's maximum
        times the y factor and the x factor's envelope; T2 at the first sample, T2' at the smallest abs(tau)), with
        a relative margin far above the rounding of the exact evaluation."""
        R, bnd = self.raw[n], self.bnd
        dtt, mt = self._window(n)
        ks = R["k"][idx]
        dist = _distance_to_zero(ks + mt.min(axis=0)[None, :], ks + mt.max(axis=0)[None, :])
        ub = voxel_envelope_axes((dist[:, 0], dist[:, 1], dist[:, 2]), bnd.voxel_m, bnd.voxel_shape)
        if self.spec is not None and np.all(mt[:, 1] == mt[0, 1]):  # ky constant over the window: its spectrum row
            ub = np.minimum(ub, self.spec.bound_at_ky(ks[:, 1] + mt[0, 1], dist[:, 0]))
        tau = R["tau"][idx]
        ub = ub * bnd.e2(dtt.min()) * np.exp(-_distance_to_zero(tau + dtt.min(), tau + dtt.max()) / bnd.t2d)
        return ub * (1.0 + 1e-6)

    def of(self, n: int, best: np.ndarray | None) -> np.ndarray:
        """(S,) emission bounds of interval ``n``.  With ``best`` (the bound through the children, see
        :func:`_latent`), a state whose upper bound can change neither its latent bound (bound <= best) nor its
        emitter decision (amplitude x bound below ``min_emitted_signal``) is not evaluated: 0, which gives the same
        latent bound and the same decision as its exact value."""
        R = self.raw[n]
        e = np.zeros(R["is_z"].size)
        tr = np.flatnonzero(~R["is_z"])
        if self.adc_hi[n] > self.adc_lo[n] and tr.size and native_in_use():
            # the compiled core bounds every state sample by sample (tighter than bound()) and leaves out the same
            use = best is not None and self.min_emitted > 0
            e[tr] = self._exact_native(n, tr, best[tr] if use and best is not None else None)
        elif self.adc_hi[n] > self.adc_lo[n] and tr.size:
            if best is not None and self.min_emitted > 0:
                ub = self.bound(n, tr)
                tr = tr[(ub > best[tr]) | (R["mag"][tr] * ub >= self.min_emitted)]
            e[tr] = self.exact(n, tr)
        if self.final_z_readout and n == len(self.raw) - 1:
            zi = np.where(R["is_z"])[0]
            kz_ = R["k"][zi]
            e[zi] = self.envelope(kz_[:, 0], kz_[:, 1], kz_[:, 2]) * np.exp(-np.abs(R["tau"][zi]) / self.bnd.t2d)
        return e


def _latent(ctx, emit_b: list, emission_of: Callable | None = None) -> list:
    """Per interval, per state: bound on what the state can still contribute to any ADC sample (its own
    emission ``emit_b`` or, through the RF-splitting edges, that of any descendant), per unit amplitude.
    ``emission_of(n, best) -> (S,)``: computes ``emit_b[n]`` (stored there) from the bound ``best`` through the
    children, backwards (None: ``emit_b`` is given)."""
    raw, ir, rf_order, bnd, dt_int = ctx["raw"], ctx["ir"], ctx["rf_order"], ctx["bnd"], ctx["dt_int"]
    NI = len(raw)
    latent: list[Any] = [None] * NI
    for n in range(NI - 1, -1, -1):
        R = raw[n]
        best = None
        if n + 1 < NI:
            C = raw[n + 1]
            rf = ir.rf[rf_order[n]]
            cm = rf_edge_magnitude_bounds(rf.flip_angle_rad, bnd.b1)
            dt = dt_int[n]
            decay = np.where(R["is_z"], bnd.e1(dt), bnd.e2(dt))
            via = cm[C["e_kind"]] * latent[n + 1][C["e_child"]] * decay[C["e_par"]]
            best = np.zeros(R["is_z"].size)
            np.maximum.at(best, C["e_par"], via)
        if emission_of is not None:
            emit_b[n] = emission_of(n, best)
        latent[n] = emit_b[n].copy() if best is None else np.maximum(emit_b[n], best)
    return latent


def _prune(ctx, emit_b, latent, restrict=None) -> tuple[list, list]:
    """Drop the states whose amplitude bound x latent bound is below ``min_latent_signal`` (and those
    left without a kept parent), re-index, mark the emitters; ``restrict``: per interval, a mask of
    the raw states that may be kept at all.  Returns the interval graphs and the per-interval keep
    masks over the raw states."""
    raw, cfg, adc_lo, adc_hi, bounds_t = ctx["raw"], ctx["cfg"], ctx["adc_lo"], ctx["adc_hi"], ctx["bounds_t"]
    NI = len(raw)
    intervals: list[IntervalGraph] = []
    keeps = []
    prev_keep: Any = None
    prev_newi: Any = None
    native = native_in_use()
    for n in range(NI):
        R = raw[n]
        S = R["is_z"].size
        if native and n > 0:
            has_adc = bool(adc_hi[n] > adc_lo[n])
            rs = None if restrict is None else restrict[n]
            keepm, newi, arrs = prune_native(
                R,
                latent[n],
                rs,
                prev_keep,
                prev_newi,
                emit_b[n],
                cfg.min_latent_signal,
                cfg.min_emitted_signal,
                has_adc,
            )
            intervals.append(
                IntervalGraph(
                    t_start_s=float(bounds_t[n]),
                    t_end_s=float(bounds_t[n + 1]),
                    adc_start=int(adc_lo[n]),
                    adc_stop=int(adc_hi[n]),
                    **arrs,
                )
            )
            prev_keep, prev_newi = keepm, newi
            keeps.append(keepm)
            continue
        keepm = R["mag"] * latent[n] >= cfg.min_latent_signal
        if restrict is not None:
            keepm &= restrict[n]
        keepm[R["eq"]] = True
        if n == 0:
            ec = ep = ek = np.zeros(0, dtype=np.int64)
            rep = np.full(S, -1)
            rconj = np.zeros(S, dtype=bool)
            newi = np.cumsum(keepm) - 1
        else:
            ok = keepm[R["e_child"]] & prev_keep[R["e_par"]]
            has_in = np.zeros(S, dtype=bool)
            has_in[R["e_child"][ok]] = True
            keepm &= has_in | (np.arange(S) == R["eq"])
            ok &= keepm[R["e_child"]]
            newi = np.cumsum(keepm) - 1
            ec = newi[R["e_child"][ok]]
            ep = prev_newi[R["e_par"][ok]]
            ek = R["e_kind"][ok]
            cand = R["e_cand"][ok]
            nS = int(keepm.sum())
            best = first_max_by_group(ec, cand, nS)
            has_rep = best >= 0
            rep = np.full(nS, -1)
            rconj = np.zeros(nS, dtype=bool)
            rep[has_rep] = ep[best[has_rep]]
            rconj[has_rep] = CONJ[ek[best[has_rep]]]
        sel = np.where(keepm)[0]
        eqn = int(newi[R["eq"]])
        if n > 0:
            rep[eqn] = -1
        is_z = R["is_z"][sel]
        em = (~R["is_z"]) & (R["mag"] * emit_b[n] >= cfg.min_emitted_signal) & keepm
        emit = newi[np.where(em)[0]] if adc_hi[n] > adc_lo[n] else np.zeros(0, dtype=np.int64)
        intervals.append(
            IntervalGraph(
                t_start_s=float(bounds_t[n]),
                t_end_s=float(bounds_t[n + 1]),
                is_z=is_z,
                tau_s=R["tau"][sel],
                k_nom_rad_per_m=R["k"][sel],
                eq_index=eqn,
                edge_child=ec.astype(np.int64),
                edge_parent=ep.astype(np.int64),
                edge_kind=ek.astype(np.int64),
                rep_parent=rep.astype(np.int64),
                rep_conj=rconj,
                emit=emit.astype(np.int64),
                adc_start=int(adc_lo[n]),
                adc_stop=int(adc_hi[n]),
                mag=R["mag"][sel],
            )
        )
        prev_keep = keepm
        keeps.append(keepm)
        prev_newi = newi
    return intervals, keeps
