"""Signal of the emitting PDG states at the ADC samples (torch), and voxel data.

For an emitting transverse state j of interval n (start t_n) and an ADC sample at t (dt = t - t_n):

    s_c(t) = sum_j vox(k_j(t)) exp(-i k0_j(t)) sum_v C_c(v) A_j(v) exp(-dt/T2(v) - |tau_j + dt|/T2'(v)
             - D(v) b_j(t)) exp(-i (kx_j(t) x_v + ky_j(t) y_v + omega_v (tau_j + dt)))

with k_j(t) = k_j(t_n) + gamma * integral_{t_n}^t G (exact PWL), b_j(t) = integral_{t_n}^t |k_j|^2,
vox the voxel-shape factor (box: product of sinc(k_a d_a / 2)), C_c the coil sensitivity.  Two
evaluations, one strategy each, chosen in one place (:func:`signal_method`): 'direct' (exact
exponentials of every (state, sample, voxel) triple, chunked: the reference), 'gemm' (one shared kernel
per interval, :func:`emit_signal_gemm`; batched across intervals by :mod:`dtoc.sim.pdg_signal_batch`)
and 'separable' (the same with the spatial phase factored per axis, for long readouts of few states).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
import torch

from dtoc.errors import InputError
from dtoc.util.cplx import cabs, cexp, cexp_of, cis, cneg, sinc


@dataclass
class VoxelData:
    """Per-voxel tensors of the simulated (PD > 0) voxels, flattened in (iy, ix) order ((iz, iy, ix) in 3D)."""

    index: torch.Tensor  # (V,) flat indices into the (ny, nx) grid
    iy: np.ndarray
    ix: np.ndarray
    shape: tuple
    pd: torch.Tensor
    mz0: torch.Tensor
    r1: torch.Tensor
    r2: torch.Tensor
    r2d: torch.Tensor
    d: torch.Tensor
    omega: torch.Tensor  # rad/s
    b1: torch.Tensor
    x: torch.Tensor
    y: torch.Tensor
    xg: torch.Tensor  # (nx,) grid x positions
    yg: torch.Tensor  # (ny,)
    coil: torch.Tensor | None  # (C, V) complex
    voxel_m: tuple
    voxel_shape: str
    has_b0: bool
    has_t2d: bool
    has_diffusion: bool
    # 3D phantom ((nz, ny, nx) maps): z of every voxel, the z grid and the slice index (None in 2D)
    z: torch.Tensor | None = None
    zg: torch.Tensor | None = None
    iz: np.ndarray | None = None
    # per-simulate cache of constant signal-kernel factors (see :func:`_time_factor`)
    cache: dict = field(default_factory=dict, repr=False)
    # host (numpy) copies of r1, r2, d, b1, pd, mz0 with the tensors' values (same dtype), and the largest
    # D: read on the host without a device synchronisation (tissue tuples, Taylor scaling)
    host: dict = field(default_factory=dict, repr=False)
    d_max: float = 0.0

    @property
    def n(self) -> int:
        return int(self.pd.shape[0])

    @property
    def n_coils(self) -> int:
        return 1 if self.coil is None else int(self.coil.shape[0])

    def ix_t(self) -> torch.Tensor:
        """(V,) column index of every simulated voxel on the grid (torch, cached)."""
        t = self.cache.get("ix")
        if t is None:
            t = self.cache["ix"] = torch.as_tensor(self.ix, device=self.pd.device)
        return t

    def iy_t(self) -> torch.Tensor:
        """(V,) row index of every simulated voxel on the grid (torch, cached)."""
        t = self.cache.get("iy")
        if t is None:
            t = self.cache["iy"] = torch.as_tensor(self.iy, device=self.pd.device)
        return t

    def spatial_phase(self, kx: torch.Tensor, ky: torch.Tensor) -> torch.Tensor:
        """(..., V) complex exp(-i (kx x_v + ky y_v)) for k (...,) in rad/m, separably.

        exp(-i kx x) exp(-i ky y) on the Cartesian voxel grid: (... x (nx + ny)) exponentials and one
        complex multiply per voxel instead of one complex exponential per voxel.
        """
        shape = kx.shape
        out = _SpatialPhase.apply(
            kx.reshape(-1), ky.reshape(-1), self.xg, self.yg, self.ix_t(), self.iy_t(), self.x, self.y
        )
        return out.reshape(*shape, self.n)

    def spatial_phase_of(self, k: torch.Tensor) -> torch.Tensor:
        """(..., V) complex exp(-i k.r_v) for k (..., >=3) rad/m: :meth:`spatial_phase` times the z factor
        of a 3D phantom (plain autograd for kz), or :meth:`spatial_phase` alone in 2D."""
        sp = self.spatial_phase(k[..., 0], k[..., 1])
        if self.z is None or self.zg is None:
            return sp
        iz = self.cache.get("iz")
        if iz is None:
            iz = self.cache["iz"] = torch.as_tensor(self.iz, device=self.pd.device)
        kz = k[..., 2].reshape(-1)
        zf = cis(-self.zg[:, None] * kz[None, :]).index_select(0, iz).T  # (M, V)
        return sp * zf.reshape(*k.shape[:-1], self.n)

    def phase_of(self, k: torch.Tensor) -> torch.Tensor:
        """(..., V) spatial phase k.r_v (rad) for k (..., >=2) rad/m (x, y; and z for a 3D phantom)."""
        ph = k[..., 0:1] * self.x + k[..., 1:2] * self.y
        if self.z is not None:
            ph = ph + k[..., 2:3] * self.z
        return ph

    @classmethod
    def from_phantom(cls, ph, initial_mz, dtype, device, cfg) -> VoxelData:
        ny, nx = ph.pd.shape[-2:]
        mask = np.asarray(ph.pd) > 0
        flat = np.where(mask.ravel())[0]
        iz, iyx = np.divmod(flat, ny * nx)
        iy, ix = np.divmod(iyx, nx)
        np_dt = np.float32 if dtype == torch.float32 else np.float64
        host: dict = {}

        def T(a, name: str | None = None) -> torch.Tensor:
            v = np.asarray(a, dtype=np.float64).ravel()[flat].astype(np_dt)
            if name is not None:
                host[name] = v
            return torch.as_tensor(v, device=device)

        with np.errstate(divide="ignore"):
            r1 = 1.0 / np.asarray(ph.t1_s, dtype=np.float64)
            r2 = 1.0 / np.asarray(ph.t2_s, dtype=np.float64)
            r2d = 1.0 / np.asarray(ph.t2dash_s, dtype=np.float64)
        xx, yy = ph.positions_m()
        if initial_mz is None:
            mz0 = T(ph.pd, "mz0")
        else:
            m = initial_mz.detach().cpu().numpy() if isinstance(initial_mz, torch.Tensor) else np.asarray(initial_mz)
            if m.shape != ph.pd.shape:
                raise InputError(f"simulate: initial_mz has shape {m.shape}, expected {ph.pd.shape}")
            mz0 = T(m, "mz0")
        coil = None
        if ph.coil_sens is not None:
            cs = np.asarray(ph.coil_sens).reshape(ph.coil_sens.shape[0], -1)[:, flat]
            cd = torch.complex64 if dtype == torch.float32 else torch.complex128
            coil = torch.as_tensor(cs, dtype=cd, device=device)
        b0 = np.asarray(ph.b0_hz, dtype=np.float64)
        sel = mask
        axes = ph.axis_positions_m()
        zg = torch.as_tensor(axes[2], dtype=dtype, device=device) if ph.pd.ndim == 3 else None
        return cls(
            index=torch.as_tensor(flat, device=device),
            iy=iy,
            ix=ix,
            shape=(ny, nx),
            pd=T(ph.pd, "pd"),
            mz0=mz0,
            r1=T(r1, "r1"),
            r2=T(r2, "r2"),
            r2d=T(r2d),
            d=T(ph.d_m2_per_s, "d"),
            omega=T(2 * np.pi * b0),
            b1=T(ph.b1, "b1"),
            x=T(xx),
            y=T(yy),
            xg=torch.as_tensor(axes[0], dtype=dtype, device=device),
            yg=torch.as_tensor(axes[1], dtype=dtype, device=device),
            coil=coil,
            voxel_m=(ph.fov_m[0] / nx, ph.fov_m[1] / ny, ph.voxel_size_z_m if ph.is_3d else cfg.voxel_size_z_m),
            voxel_shape=ph.voxel_shape,
            has_b0=bool(np.any(b0[sel] != 0)),
            has_t2d=bool(np.any(np.isfinite(np.asarray(ph.t2dash_s)[sel]))),
            has_diffusion=bool(np.any(np.asarray(ph.d_m2_per_s)[sel] > 0)),
            z=None if zg is None else zg[torch.as_tensor(iz, device=device)],
            zg=zg,
            iz=None if zg is None else iz,
            host=host,
            d_max=float(host["d"].max()) if host["d"].size else 0.0,
        )

    def observe_mz(self, A, K, tau_s) -> torch.Tensor:
        """Voxel-mean Mz (V,) of longitudinal states A (Z, V) with k K (Z, 4) and dephasing time tau (Z,)."""
        tau = torch.as_tensor(tau_s, dtype=self.r2d.dtype, device=A.device)
        k = K.to(self.x.dtype)
        ph = -(self.phase_of(k) + tau[:, None] * self.omega[None])
        mag = -(tau.abs()[:, None] * self.r2d[None])
        E = cexp(mag, ph)
        vf = voxel_factor(K, self).to(A.dtype)
        return (A * E * vf[:, None]).sum(0).real


class _SpatialPhase(torch.autograd.Function):
    """exp(-i (kx x_v + ky y_v)) (M, V) from per-axis factors, with a fused adjoint.

    Forward: (nx, M) and (ny, M) factors, gathered by rows (contiguous copies), multiplied in the
    voxel-major layout and transposed once.  Backward (torch's convention, G = dL/dRe +
    i dL/dIm): dL/dkx = sum_v x_v Im(conj(G) SP), dL/dky = sum_v y_v Im(conj(G) SP) -- one complex
    product and two matrix-vector products instead of the generic chain.
    """

    @staticmethod
    def forward(ctx, kx, ky, xg, yg, ix, iy, x, y):
        sp = (
            cis(-xg[:, None] * kx[None, :]).index_select(0, ix) * cis(-yg[:, None] * ky[None, :]).index_select(0, iy)
        ).T.contiguous()
        ctx.save_for_backward(sp, x, y)
        return sp  # (M, V)

    @staticmethod
    def backward(ctx, G):
        sp, x, y = ctx.saved_tensors
        q = (G.conj() * sp).imag  # (M, V)
        gx = q @ x if ctx.needs_input_grad[0] else None
        gy = q @ y if ctx.needs_input_grad[1] else None
        return gx, gy, None, None, None, None, None, None


def voxel_factor(k: torch.Tensor, vox: VoxelData) -> torch.Tensor:
    """Complex factor (...) of dephasing k (..., 4): voxel-shape attenuation times exp(-i k0)."""
    k = k.to(vox.x.dtype)
    f = torch.ones(k.shape[:-1], dtype=k.dtype, device=k.device)
    if vox.voxel_shape != "none":
        for a, d in enumerate(vox.voxel_m):
            if d is None or d <= 0:
                continue
            if vox.voxel_shape == "box":
                f = f * sinc(k[..., a] * (d / (2 * np.pi)))
            else:  # band-limited ('sinc') voxel: rect in k
                f = f * (k[..., a].abs() <= np.pi / d).to(k.dtype)
    return f * cexp(torch.zeros_like(f), -k[..., 3])


def _diffusion_b(Kj, mom, n, lo, hi, dtt_t):
    """(J, T) b-integrals integral_{t_n}^t |k_j|^2 dt, float64."""
    u = Kj[:, :3] - mom.I_bound[n][:3][None, :]
    dJ1 = mom.J1_adc[lo:hi] - mom.J1_bound[n][None, :]
    dJ2 = mom.J2_adc[lo:hi] - mom.J2_bound[n]
    return (u * u).sum(1)[:, None] * dtt_t[None, :] + 2.0 * u @ dJ1.T + dJ2[None, :]


SIGNAL_METHODS = ("gemm", "separable", "direct")


def signal_method(cfg, n_samples: int, n_emitting: int) -> str:
    """The signal evaluation of one interval: ``cfg.signal_method``, or for 'auto' 'separable' on long
    readouts of few states (single-shot EPI: no T x V exponentials) and 'gemm' (one shared kernel) else."""
    method = cfg.signal_method
    if method == "auto":
        return "separable" if (n_samples >= 256 and n_emitting <= 8) else "gemm"
    if method not in SIGNAL_METHODS:
        raise InputError(f"PDGConfig.signal_method {method!r}: expected 'auto', {', '.join(map(repr, SIGNAL_METHODS))}")
    return method


def emit_signal(iv, A, K, mom, n, vox: VoxelData, graph, bounds_t, cfg) -> torch.Tensor:
    """(C, T) signal of the emitting states of interval ``n`` at its ADC samples (before ADC phase)."""
    method = signal_method(cfg, iv.adc_stop - iv.adc_start, iv.emit.size)
    if method == "separable" and vox.z is not None:
        method = "gemm"  # the separable product factors x and y on the full 2D grid only
    if method == "direct":
        return emit_signal_direct(iv, A, K, mom, n, vox, graph, bounds_t, cfg)
    return emit_signal_gemm(iv, A, K, mom, n, vox, graph, bounds_t, cfg, separable=method == "separable")


class ExactStates(NamedTuple):
    """Per-state inputs of the exact evaluation (states of one or several intervals, T samples each).

    Attributes:
        kt: (J, T, 4) k at every sample (real dtype); tau: (J, T) dephasing time at every sample, s;
        dt: (J, T) time since the interval start, s; bD: (J, T) diffusion b-integral (None: no diffusion);
        A: (J, V) complex amplitudes; vf: (J, T) complex voxel factor.
    """

    kt: torch.Tensor
    tau: torch.Tensor
    dt: torch.Tensor
    bD: torch.Tensor | None
    A: torch.Tensor
    vf: torch.Tensor


def emit_signal_direct(iv, A, K, mom, n, vox: VoxelData, graph, bounds_t, cfg, states: ExactStates | None = None):
    """Exact evaluation, chunked over samples so that J x T_chunk x V <= cfg.chunk_elems.

    Per interval: (C, T) signal of the emitting states of ``iv`` (interval ``n``).  With ``states``
    (the batched path's strongly dephased states of several intervals, :class:`ExactStates`; the other
    arguments then unused): (J, C, T), the signal of every state."""
    if states is None:
        dev = A.device
        rdt = vox.x.dtype
        J = torch.as_tensor(iv.emit, device=dev)
        lo, hi = iv.adc_start, iv.adc_stop
        Kj = K.index_select(0, J)  # (J, 4) float64
        mt = mom.I_adc[lo:hi] - mom.I_bound[n][None, :]  # (T, 4)
        kt = Kj[:, None, :] + mt[None, :, :]  # (J, T, 4)
        dtt = graph.adc_times_s[lo:hi] - bounds_t[n]
        dtt_t = torch.as_tensor(dtt, dtype=torch.float64, device=dev)
        tau = iv.tau_s[iv.emit][:, None] + dtt[None, :]  # (J, T) numpy
        vf = voxel_factor(kt, vox)  # (J, T) complex
        bD = _diffusion_b(Kj, mom, n, lo, hi, dtt_t).to(rdt) if vox.has_diffusion else None
        dtr = torch.as_tensor(dtt, dtype=rdt, device=dev)[None, :].expand(kt.shape[0], -1)
        st = ExactStates(kt.to(rdt), torch.as_tensor(tau, dtype=rdt, device=dev), dtr, bD, A.index_select(0, J), vf)
        return _exact(st, vox, cfg).sum(0)
    return _exact(states, vox, cfg)


def _exact(st: ExactStates, vox: VoxelData, cfg) -> torch.Tensor:
    """(J, C, T) exact signal of every state of ``st`` (see :func:`emit_signal_direct`)."""
    AC = st.A[None] if vox.coil is None else vox.coil[:, None, :] * st.A[None]  # (C, J, V)
    nJ, T = st.kt.shape[0], st.kt.shape[1]
    step = max(1, int(cfg.chunk_elems // max(1, nJ * vox.n)))
    out = []
    for t0 in range(0, T, step):
        sl = slice(t0, min(T, t0 + step))
        ta = st.tau[:, sl]
        mag = -st.dt[:, sl, None] * vox.r2[None, None, :] - ta.abs()[:, :, None] * vox.r2d[None, None, :]
        if st.bD is not None:
            mag = mag - st.bD[:, sl, None] * vox.d[None, None, :]
        ph = -(vox.phase_of(st.kt[:, sl]) + ta[:, :, None] * vox.omega[None, None, :])
        E = cexp(mag, ph)  # (J, t, V)
        out.append(torch.einsum("jtv,cjv->jct", E, AC) * st.vf[:, None, sl])
    return torch.cat(out, dim=2)


# ------------------------------------------------------------------------------------------------
# 'gemm' evaluation: one shared (sample x voxel) kernel per interval, states as a matrix product
# ------------------------------------------------------------------------------------------------
def emit_signal_gemm(iv, A, K, mom, n, vox: VoxelData, graph, bounds_t, cfg, separable: bool = False) -> torch.Tensor:
    """Same signal as :func:`emit_signal_direct`, with the voxel sum as one matrix product.

    Within an interval every state's k is k_j(t) = k_j(t_n) + m(t) with the *common* moment m(t), so

        exp(-i k_j(t).r) = exp(-i k_j(t_n).r) exp(-i m(t).r),
        exp(-|tau_j + dt| / T2') = exp(-|tau_j| / T2') exp(-dt / T2')   (tau_j >= 0; mirrored for tau_j + dt <= 0),
        exp(-i omega (tau_j + dt)) = exp(-i omega tau_j) exp(-i omega dt),

    so s_j(t) = vox_j(t) sum_v C_j(v) Kern(t, v): a (states x voxels) @ (voxels x samples) product
    with one kernel of T x V exponentials shared by all states.  States whose tau crosses 0 inside the
    interval (spin echoes) use both kernels with complementary sample masks.  Diffusion, whose
    b-value is state-specific in time, is Taylor-expanded around the window centre, one extra
    matrix product per order (order chosen so that the truncation is below ``cfg.taylor_tol``);
    states with D |db| > 0.5 inside the window (strongly dephased) are evaluated exactly by
    :func:`emit_signal_direct`, the others still as matrix products.  With ``separable`` the kernel product is evaluated by
    :func:`_apply_kernel_separable` (no T x V exponentials).
    """
    dev = A.device
    rdt = vox.x.dtype
    cdt = A.dtype
    lo, hi = iv.adc_start, iv.adc_stop
    T = hi - lo
    Jn = torch.as_tensor(iv.emit, device=dev)
    Kj = K.index_select(0, Jn)  # (J, 4) float64
    mt = mom.I_adc[lo:hi] - mom.I_bound[n][None, :]  # (T, 4) float64
    dtt = graph.adc_times_s[lo:hi] - bounds_t[n]
    tau = iv.tau_s[iv.emit]
    t_mask_plus = (tau[:, None] + dtt[None, :]) >= 0  # (J, T): samples where |tau + dt| = tau + dt
    use_t2d = vox.has_t2d
    if use_t2d and T:
        # states whose |tau + dt| keeps one sign over the window need one kernel class only: evaluate
        # the groups (all plus / all minus / crossing zero) separately instead of masking both classes
        allp, allm = t_mask_plus.all(1), (~t_mask_plus).all(1)
        groups = [m for m in (allp, allm, ~(allp | allm)) if m.any()]
        if len(groups) > 1:
            out = emit_signal_gemm(_subset(iv, groups[0]), A, K, mom, n, vox, graph, bounds_t, cfg, separable)
            for m in groups[1:]:
                out = out + emit_signal_gemm(_subset(iv, m), A, K, mom, n, vox, graph, bounds_t, cfg, separable)
            return out
    vf = voxel_factor(Kj[:, None, :] + mt[None, :, :], vox)  # (J, T) complex
    # diffusion: b_j(t) = b_j(t_mid) + delta_j(t)
    dif = None
    if vox.has_diffusion:
        dtt_t = torch.as_tensor(dtt, dtype=torch.float64, device=dev)
        b = _diffusion_b(Kj, mom, n, lo, hi, dtt_t)  # (J, T) float64
        bm = b[:, T // 2 : T // 2 + 1]
        delta = b - bm
        xs = vox.d_max * delta.detach().abs().amax(1).cpu().numpy() if T else np.zeros(len(iv.emit))
        far = xs > _DIFF_TAYLOR_MAX
        if far.any():
            # states whose in-window diffusion change is large (strongly dephased, e.g. spoiled
            # pathways seen through the voxel sinc): exact per-state evaluation for those only
            s_far = emit_signal_direct(_subset(iv, far), A, K, mom, n, vox, graph, bounds_t, cfg)
            if far.all():
                return s_far
            return s_far + emit_signal_gemm(_subset(iv, ~far), A, K, mom, n, vox, graph, bounds_t, cfg, separable)
        # per-state Taylor order: the term of order r is a matrix product over the states that need it
        orders = np.array([taylor_order(float(x), cfg.taylor_tol) for x in xs], dtype=np.int64)
        rows = [torch.as_tensor(np.where(orders >= r)[0], device=dev) for r in range(1, int(orders.max(initial=0)) + 1)]
        dif = (bm[:, 0].to(rdt), delta.to(rdt), rows, max(vox.d_max, 1e-300))
    # per-state voxel weights C_j(v) (without the T2' part, which depends on the kernel class)
    Aj = A.index_select(0, Jn)
    kj = Kj.to(rdt)
    tau_t = torch.as_tensor(tau, dtype=rdt, device=dev)
    ph = -(vox.phase_of(kj) + tau_t[:, None] * vox.omega[None])
    mag0 = torch.zeros_like(ph)
    if dif is not None:
        mag0 = mag0 - dif[0][:, None] * vox.d[None]
    # kernel classes: plus (|tau + dt| = tau + dt) and minus (|tau + dt| = -(tau + dt))
    use_t2d = vox.has_t2d
    out = torch.zeros((vox.n_coils, T), dtype=cdt, device=dev)
    if not use_t2d or t_mask_plus.all():
        kinds = [+1.0]
    elif not t_mask_plus.any():
        kinds = [-1.0]
    else:
        kinds = [+1.0, -1.0]
    mt_r = mt.to(rdt)
    dtr = torch.as_tensor(dtt, dtype=rdt, device=dev)
    step = max(1, int(cfg.chunk_elems // max(1, vox.n)))
    for sgn in kinds:
        if use_t2d:
            # plus: exp(-tau R2') exp(-dt R2'); minus: exp(+tau R2') exp(+dt R2')
            mag_c = mag0 - sgn * tau_t[:, None] * vox.r2d[None]
            mag_c = torch.clamp(mag_c, max=80.0)
        else:
            mag_c = mag0
        C = cexp(mag_c, ph) * Aj  # (J, V)
        if vox.coil is not None:
            C = vox.coil[:, None, :] * C[None]  # (Co, J, V)
        else:
            C = C[None]
        Co, J, V = C.shape
        mats = [C.reshape(Co * J, V)]
        counts = [J]
        if dif is not None:
            dn = vox.d / dif[3]  # scaled to <= 1: D^r and delta^r separately under/overflow float32
            dr = torch.ones_like(vox.d)
            for rr in dif[2]:  # Taylor terms C (D/Dmax)^r of exp(-D delta), states of order >= r only
                dr = dr * dn
                mats.append((C.index_select(1, rr) * dr[None, None, :]).reshape(-1, V))
                counts.append(int(rr.numel()))
        if len(kinds) == 1:
            tm = None
        else:
            tm = t_mask_plus if sgn > 0 else ~t_mask_plus
        if separable:
            Cm = torch.cat(mats, 0) if len(mats) > 1 else mats[0]  # (nterm*Co*J, V)
            Gs = torch.split(
                _apply_kernel_separable(Cm, sgn, use_t2d, mt_r, dtt, vox, cfg), [Co * c for c in counts], 0
            )
        else:
            rate = vox.r2 + (sgn * vox.r2d if use_t2d else 0.0)
            # large problems: recompute each kernel chunk in the backward pass instead of storing
            # T x V complex numbers (a 128x128 EPI on a 256x256 phantom would keep 17 GB)
            ckpt = torch.is_grad_enabled() and T * V > 4 * cfg.chunk_elems
            if ckpt or T > step:
                Cm = torch.cat(mats, 0) if len(mats) > 1 else mats[0]  # (nterm*Co*J, V)
                res = []
                for t0 in range(0, T, step):
                    sl = slice(t0, min(T, t0 + step))
                    if ckpt:
                        from torch.utils.checkpoint import checkpoint

                        res.append(checkpoint(_kernel_product, Cm, mt_r[sl], dtr[sl], rate, vox, use_reentrant=False))
                    else:
                        res.append(_kernel_product(Cm, mt_r[sl], dtr[sl], rate, vox))
                G = torch.cat(res, 1) if len(res) > 1 else res[0]
                Gs = torch.split(G, [Co * c for c in counts], 0)
            else:  # one kernel, one product per Taylor term (no concatenated copy of the weights)
                KernT = _kernel(mt_r, dtr, rate, vox, _time_key(dtt, sgn if use_t2d else 0.0)).T
                Gs = tuple(m @ KernT for m in mats)
        s = Gs[0].reshape(Co, J, T)
        if dif is not None and dif[2]:
            ndl = (-dif[3] * dif[1]).to(cdt)  # (J, T): -Dmax delta, |.| <= _DIFF_TAYLOR_MAX
            w = ndl
            for r, rr in enumerate(dif[2], start=1):  # sum_r (-delta)^r / r! * G[r]
                if r > 1:
                    w = w * ndl / r
                s = s.index_add(1, rr, w.index_select(0, rr)[None] * Gs[r].reshape(Co, -1, T))
        s = s * vf[None]
        if tm is not None:
            s = s * torch.as_tensor(tm, device=dev)[None].to(s.real.dtype)
        out = out + s.sum(1)
    return out


_DIFF_TAYLOR_MAX = 0.5  # largest D * |b(t) - b(t_mid)| expanded in a Taylor series (else exact per state)


def taylor_order(x: float, tol: float) -> int:
    """Smallest order R with x^(R+1) / (R+1)! <= tol (remainder of the Taylor series of exp(-x) for x >= 0)."""
    if x <= tol:
        return 0
    r, term = 0, 1.0
    while r < 30:
        term = term * x / (r + 1)
        if term <= tol:
            return r
        r += 1
    return r


def _subset(iv, mask: np.ndarray):
    """Shallow copy of interval graph ``iv`` whose emitting states are ``iv.emit[mask]``."""
    import copy

    sub = copy.copy(iv)
    sub.emit = iv.emit[mask]
    return sub


def _kernel(mt_r, dtr, rate, vox: VoxelData, key=None) -> torch.Tensor:
    """(t, V) kernel Kern(t, v) = exp(-dt rate - i (m(t).r + omega dt)).

    With ``key`` (hashable: the kernel class and the sample times), the factor
    exp(-dt (rate + i omega)), which depends on the fixed ADC times only (no gradient), is computed
    once per simulate call and reused by every interval with the same sample times relative to its
    start (every TR of a GRE); the moment-dependent spatial part exp(-i m(t).r) is separable on the
    voxel grid (:meth:`VoxelData.spatial_phase`: t x (nx + ny) exponentials).  Same values as the
    direct formula up to rounding.
    """
    if key is not None:
        tf = _time_factor(dtr, rate, vox, key)
        if tf is not None:
            return vox.spatial_phase_of(mt_r) * tf
    kph = -(vox.phase_of(mt_r) + dtr[:, None] * vox.omega[None])
    # clamp: the mirrored (tau < 0) kernel grows as exp(+dt/T2'); only masked-out samples can get there
    return cexp(torch.clamp(-dtr[:, None] * rate[None], max=80.0), kph)


_TIME_FACTOR_CACHE_ELEMS = 2**24  # largest total size (complex elements) of the cached time factors per simulate call


def _time_factor(dtr, rate, vox: VoxelData, key):
    """Cached (t, V) exp(-dt (rate + i omega)) (constant: no autograd), or None when the cache is full."""
    ck = ("tf", key)
    tf = vox.cache.get(ck)
    if tf is None:
        used = vox.cache.get("tf_elems", 0)
        if used + dtr.numel() * vox.n > _TIME_FACTOR_CACHE_ELEMS:
            return None
        with torch.no_grad():
            tf = _decay_phase(dtr, rate, vox.omega)
        vox.cache[ck] = tf
        vox.cache["tf_elems"] = used + tf.numel()
    return tf


def _decay_phase(dtr: torch.Tensor, rate: torch.Tensor, omega: torch.Tensor) -> torch.Tensor:
    """(t, V) exp(-dt (rate + i omega)) for times ``dtr`` (t,) s, rates (V,) 1/s and off-resonance (V,) rad/s
    (the exponent's real part clamped at +80: the mirrored T2' kernel only grows on masked-out samples)."""
    return cexp(torch.clamp(-dtr[:, None] * rate[None], max=80.0), -dtr[:, None] * omega[None])


def _time_key(dtt: np.ndarray, sgn: float):
    """Hashable key of an interval's ADC sample times relative to its start (rounded to 1e-15 s) and kernel class."""
    return (float(sgn), dtt.size, np.round(np.asarray(dtt) * 1e15).astype(np.int64).tobytes())


def _kernel_product(Cm, mt_r, dtr, rate, vox: VoxelData) -> torch.Tensor:
    """Cm (M, V) @ Kern^T for one chunk of samples."""
    return Cm @ _kernel(mt_r, dtr, rate, vox).T


def _taylor_terms(x: float, tol: float) -> int:
    """Smallest R with x^R / R! * e^x < tol (remainder of the R-term Taylor series of e^{-x})."""
    r, term = 1, x
    while term * np.exp(x) >= tol and r < 40:
        r += 1
        term = term * x / r
    return r


def _on_grid(Cm, sgn, use_t2d, vox: VoxelData) -> tuple[torch.Tensor, torch.Tensor, float]:
    """The separable evaluations' inputs on the full (ny * nx) voxel grid (zero off the phantom): the weights
    Cm (M, ny nx), the decay rates lam = 1/T2 + sgn/T2' + i omega (ny nx,) and max |lam|."""
    ny, nx = vox.shape
    full = torch.zeros((Cm.shape[0], ny * nx), dtype=Cm.dtype, device=Cm.device).index_copy(1, vox.index, Cm)
    lam_v = torch.complex(vox.r2 + (sgn * vox.r2d if use_t2d else 0.0), vox.omega)  # (V,)
    lam = torch.zeros(ny * nx, dtype=Cm.dtype, device=Cm.device).index_copy(0, vox.index, lam_v)
    lam_max = float(cabs(lam_v.detach()).max()) if lam_v.numel() else 0.0
    return full, lam, lam_max


#: longest line window of the line-aware evaluation, samples (a whole readout line up to this: each window
#: costs one pass over the voxels, its length only lengthens the time series)
_LINE_WINDOW_MAX = 512


def _line_windows(m_pe: np.ndarray, m_ro: np.ndarray, W: int) -> np.ndarray | None:
    """Windows of consecutive samples along which the phase-encoding moment ``m_pe`` (T,) stays within a
    small band (one readout line: k_pe constant up to the realized gradient's perturbation): (nW, 2)
    [start, stop) pairs of at most ``W`` samples, cut where m_pe jumps by more than a tenth of the median
    readout step |diff(m_ro)| (a phase blip between lines); None when a line would hold a single sample."""
    T = m_pe.size
    if T < 4:
        return None
    step = float(np.median(np.abs(np.diff(m_ro))))
    if step <= 0:
        return None
    cuts = np.flatnonzero(np.abs(np.diff(m_pe)) > 0.1 * step) + 1
    starts = np.concatenate([[0], cuts])
    stops = np.concatenate([cuts, [T]])
    if np.min(stops - starts) < 2:
        return None
    out = []
    for a, b in zip(starts, stops):
        for c in range(int(a), int(b), W):
            out.append((c, min(int(b), c + W)))
    return np.asarray(out, dtype=np.int64)


#: when a list: every line-aware evaluation appends its complex multiply-add count (bench.sim.line_aware)
LINE_MACS: list | None = None


def _drift_terms(x: float, tol: float) -> int:
    """Terms of the Jacobi-Anger series of exp(-i x u), |u| <= 1, for a truncation below ``tol``
    (|J_n(x)| <= (x / 2)^n / n!; twice the first dropped bound, with a margin of 2)."""
    n, term = 1, x / 2
    while 4 * term > tol and n < 200:
        n += 1
        term = term * (x / 2) / n
    return n


def _jacobi_anger(z: np.ndarray, n: int) -> np.ndarray:
    """(n, P) coefficients c_k(z) with exp(-i z u) = sum_k c_k(z) T_k(u): c_0 = J_0(z), c_k = 2 (-i)^k J_k(z)."""
    from scipy.special import jv

    k = np.arange(n)[:, None]
    c = jv(k, np.asarray(z, dtype=np.float64)[None, :]) * (2.0 * (-1j) ** k)
    c[0] *= 0.5
    return c


def _chebyshev(u: torch.Tensor, n: int) -> torch.Tensor:
    """(..., n) Chebyshev polynomials T_0..T_{n-1} of u (differentiable; T_{k+1} = 2 u T_k - T_{k-1})."""
    t = [torch.ones_like(u), u]
    for _ in range(2, n):
        t.append(2 * u * t[-1] - t[-2])
    return torch.stack(t[:n], -1)


def _line_batch_products(F, H, X, dlp, dq, mrs):
    """The products of one batch of b line windows: E = F @ H (n_ro, b S, M R), rearranged to
    (b, n_ro, M R S); U = X @ E (b, W, M R S); the window's sum over orders r and drift terms s,
    out[b, w, m] = sum_{r,s} U[b, w, m, r, s] dlp[b, w, r] dq[b, w, s].  Returns (out, E, U)."""
    M, R, S = mrs
    b, W, n_ro = X.shape
    E = torch.bmm(F, H).reshape(n_ro, b, S, M, R).permute(1, 0, 3, 4, 2)  # (b, n_ro, M, R, S)
    E = E.reshape(b, n_ro, M * R * S)
    U = torch.bmm(X, E).reshape(b, W, M, R, S)
    return torch.einsum("bwmrs,bwr,bws->bwm", U, dlp, dq), E, U


class _LineProducts(torch.autograd.Function):
    """The line-window sums of every batch, ``torch.cat`` of :func:`_line_batch_products` over ``batches``
    ((b0, b1, F) per batch: windows [b0, b1) and their constant window factors F), as one autograd node with a
    hand-written adjoint.

    Differentiable inputs: H (n_ro, n_pe, M R) the weights, X (nW, W, n_ro) the readout phases, dq (nW, W, S) the
    drift polynomials; F and dlp (nW, W, R) are constants (no gradient).  Torch's convention for a holomorphic
    product (out = A x gives grad_x = A^H grad_out) with the cotangent carried conjugated, cG = conj(grad_out),
    so that only plain (un-conjugated) saved data enter the products (conj(A)^T B = conj(A^T conj(B))), per
    batch:

        conj(grad_U) = cG dlp dq                (b, W, M, R, S)
        conj(grad_dq) = sum_{m,r} cG U dlp      (b, W, S)
        conj(grad_X) = conj(grad_U) @ E^T       (b, W, n_ro)
        conj(grad_E) = X^T @ conj(grad_U)       (b, n_ro, M R S)
        conj(grad_H)^T += conj(grad_E)^T @ F    (n_ro, M R, n_pe), conj(grad_E) rearranged as the forward's E

    written into (accumulated in, for H) whole-size buffers conjugated (and transposed) once at the end.  dlp and dq hold real
    values (conj(dlp) = dlp, conj(dq) = dq).  Only the tensors the wanted gradients read are saved.  No host
    synchronisation, no branch on a tensor's value; elementwise complex ops are mul and conj only (compiled into
    torch's CUDA build).
    """

    @staticmethod
    def forward(ctx, H, X, dq, dlp, batches, mrs):
        need_h, need_x, need_q = ctx.needs_input_grad[:3]
        outs, saved, bounds = [], [], []
        for b0, b1, F in batches:
            o, E, U = _line_batch_products(F, H, X[b0:b1], dlp[b0:b1], dq[b0:b1], mrs)
            outs.append(o)
            bounds.append((b0, b1))
            saved += [F if need_h else None, E if need_x else None, U if need_q else None]
        ctx.mrs, ctx.bounds, ctx.x_shape = mrs, bounds, X.shape
        ctx.save_for_backward(H if need_h else None, X if need_h else None, dq, dlp, *saved)
        return torch.cat(outs, 0)

    @staticmethod
    def backward(ctx, g):
        M, R, S = ctx.mrs
        H, X, dq, dlp, *saved = ctx.saved_tensors
        cg = g.conj_physical()  # (nW, W, M)
        # conj(grad_H) accumulated transposed, (n_ro, M R, n_pe): the products' row-major output is the long
        # axis n_pe (1.8x faster on the CPU than the (n_pe, M R) one at EPI 128)
        gHT = None if H is None else torch.zeros((H.shape[0], H.shape[2], H.shape[1]), dtype=g.dtype, device=g.device)
        gX = None if saved[1] is None else torch.empty(ctx.x_shape, dtype=g.dtype, device=g.device)
        gq = None if saved[2] is None else torch.empty(dq.shape, dtype=g.dtype, device=g.device)
        for i, (b0, b1) in enumerate(ctx.bounds):
            F, E, U = saved[3 * i : 3 * i + 3]
            b, W = b1 - b0, g.shape[1]
            cgb, dl = cg[b0:b1], dlp[b0:b1]
            cgU = (cgb[:, :, :, None, None] * dl[:, :, None, :, None]) * dq[b0:b1, :, None, None, :]  # (b, W, M, R, S)
            if gq is not None:
                gq[b0:b1] = torch.einsum("bwm,bwmrs,bwr->bws", cgb, U, dl)
            cgU = cgU.reshape(b, W, M * R * S)
            if gX is not None:
                torch.bmm(cgU, E.transpose(1, 2), out=gX[b0:b1])
            if gHT is not None:
                n_ro = ctx.x_shape[2]
                cgE = torch.bmm(X[b0:b1].transpose(1, 2), cgU)  # (b, n_ro, M R S)
                cgE = cgE.reshape(b, n_ro, M, R, S).permute(1, 2, 3, 0, 4).reshape(n_ro, M * R, b * S)
                gHT.baddbmm_(cgE, F)
        gH = None
        if gHT is not None:
            gH = torch.empty(H.shape, dtype=g.dtype, device=g.device)
            torch.conj_physical(gHT.transpose(1, 2), out=gH)
        for t in (gX, gq):
            if t is not None:
                t.conj_physical_()
        return gH, gX, gq, None, None, None


def _line_products(H, X, dq, dlp, batches, mrs):
    """(nW, W, M) line-window sums of all batches (:func:`_line_batch_products` per batch), through
    :class:`_LineProducts` where a gradient is wanted; without, each batch's F is used and released in turn."""
    if torch.is_grad_enabled() and (H.requires_grad or X.requires_grad or dq.requires_grad):
        return _LineProducts.apply(H, X, dq, dlp, batches, mrs)
    return torch.cat([_line_batch_products(F, H, X[b0:b1], dlp[b0:b1], dq[b0:b1], mrs)[0] for b0, b1, F in batches], 0)


def _apply_kernel_lines(Cm, sgn, use_t2d, mt_r, dtt, vox: VoxelData, cfg, pe: int, wins: np.ndarray):
    """(M, T) = Cm (M, V) @ Kern(t, v)^T for readouts along lines of (nearly) constant phase-encoding moment.

    Within a line window w (samples of one readout line, centre time tc_w, phase-encoding moment m_w = the
    window's mid-range), with p the phase-encoded and q the readout coordinate of voxel v,

        Kern(t, v) = exp(-tc_w lam_v) sum_r (-(dt - tc_w) lam_v)^r / r!
                     x exp(-i m_w p_v) sum_s c_s(D p_v) T_s((m_pe(t) - m_w) / D)  x  exp(-i m_ro(t) q_v),

    (c_s the Jacobi-Anger coefficients of exp(-i z u), :func:`_jacobi_anger`; T_s Chebyshev polynomials; D
    the largest drift |m_pe(t) - m_w|), so the sum over the phase-encoded axis is one matrix product per
    readout column q: E[q; (w, s), (m, r)] = sum_p F[q; (w, s), p] H[q; p, (m, r)] with the window factors
    F = exp(-tc_w lam) exp(-i m_w p) c_s(D p) (constants: no autograd) and the weights
    H = Cm lam^r (-1)^r / r! (formed once); then one (W x n_ro) @ (n_ro x M R S) product per window.
    n_lines x V x M R S + T x n_ro x M R S complex multiply-adds, against T x V x M R of
    :func:`_apply_kernel_separable`.  exp(-tc_w lam) is advanced from window to window by one multiplication
    (float64; the factors of the distinct window spacings cached) instead of V exponentials per window.  Both
    truncations are below ``cfg.taylor_tol`` (the drift series two terms longer under autograd).
    """
    dev = Cm.device
    ny, nx = vox.shape
    M = Cm.shape[0]
    cdt = Cm.dtype
    rdt = mt_r.dtype
    ro = 1 - pe
    n_pe, n_ro = (ny, nx) if pe == 1 else (nx, ny)
    g_pe = vox.yg if pe == 1 else vox.xg
    g_ro = vox.xg if pe == 1 else vox.yg

    def ro_pe(a: torch.Tensor) -> torch.Tensor:
        """(..., ny * nx) grid -> (..., n_ro, n_pe)."""
        a = a.reshape(*a.shape[:-1], ny, nx)
        return a.transpose(-1, -2) if pe == 1 else a

    full, lam, lam_max = _on_grid(Cm, sgn, use_t2d, vox)
    lam = lam.detach()
    T = dtt.size
    nW = wins.shape[0]
    W = int((wins[:, 1] - wins[:, 0]).max())
    # gather indices (nW, W): every window padded with its last sample (results of padded slots dropped)
    idx = np.minimum(wins[:, :1] + np.arange(W)[None, :], wins[:, 1:] - 1)
    valid = (wins[:, :1] + np.arange(W)[None, :]) < wins[:, 1:]
    dt_p = dtt[idx]
    tc = 0.5 * (dt_p.min(1) + dt_p.max(1))
    dl = dt_p - tc[:, None]
    R = _taylor_terms(float(np.abs(dl).max()) * lam_max, cfg.taylor_tol)
    idx_t = torch.as_tensor(idx.reshape(-1), device=dev)
    m_pe = mt_r[:, pe].index_select(0, idx_t).reshape(nW, W)
    m_ro = mt_r[:, ro].index_select(0, idx_t).reshape(nW, W, 1)
    m_c = 0.5 * (m_pe.detach().amax(1) + m_pe.detach().amin(1))  # (nW,) window centre moment (constant)
    delta = m_pe - m_c[:, None]  # (nW, W), differentiable
    p_max = max(float(g_pe.abs().max()) if g_pe.numel() else 0.0, 1e-300)
    # the expansion interval |delta| <= d_max (never 0: the series' first-order term carries the derivative)
    d_obs = float(delta.detach().abs().max())
    d_max = max(d_obs, 1e-3 / p_max)
    exact = d_obs == 0.0 and not mt_r.requires_grad  # constant lines, no derivative: the factor is 1
    S = 1 if exact else _drift_terms(d_max * p_max, cfg.taylor_tol)
    if mt_r.requires_grad:
        S += 2  # the derivative's series: T_n' grows as n^2, two more terms keep it below the tolerance
    # weights H (n_ro, n_pe, M R): Cm (-lam)^r / r!, formed once
    powers = torch.stack([cneg(lam) ** r / math.factorial(r) for r in range(R)], 0)  # (R, V)
    # (contiguous: the batched product would copy each of its n_ro strided matrices out, in every batch)
    H = ro_pe(full[:, None, :] * powers[None]).permute(2, 3, 0, 1).reshape(n_ro, n_pe, M * R).contiguous()
    with torch.no_grad():
        Pc = cis(-m_c[:, None] * g_pe[None, :].detach())  # (nW, n_pe)
        pw = (
            torch.ones((1, n_pe), dtype=cdt, device=dev)
            if exact
            else torch.as_tensor(_jacobi_anger(d_max * g_pe.detach().cpu().numpy(), S), device=dev).to(cdt)
        )  # (S, n_pe)
        lam64 = lam.to(torch.complex128)
    dlp = torch.as_tensor(np.stack([dl**r for r in range(R)], -1), dtype=rdt, device=dev).to(cdt)  # (nW, W, R)
    if LINE_MACS is not None:  # benchmark accounting: complex multiply-adds of the two products below
        LINE_MACS.append(nW * S * ny * nx * M * R + nW * W * n_ro * M * R * S)
    bs = max(1, int(cfg.chunk_elems // max(1, S * ny * nx)))

    def batches():
        """(b0, b1, F) per batch of windows [b0, b1): F (n_ro, b S, n_pe) their window factors (constants)."""
        decay = None
        steps: dict = {}
        for b0 in range(0, nW, bs):
            b1 = min(nW, b0 + bs)
            with torch.no_grad():
                rows = []
                for w in range(b0, b1):  # exp(-tc_w lam), advanced by the cached factor of each window spacing
                    if decay is None:
                        decay = cexp_of(-float(tc[w]) * lam64)
                    else:
                        d = float(tc[w] - tc[w - 1])
                        key = round(d * 1e15)
                        f = steps.get(key)
                        if f is None:
                            f = steps[key] = cexp_of(-d * lam64)
                        decay = decay * f
                    rows.append(decay)
                B = ro_pe(torch.stack(rows, 0).to(cdt)).transpose(0, 1)  # (n_ro, b, n_pe)
                F = torch.empty((n_ro, b1 - b0, S, n_pe), dtype=cdt, device=dev)
                torch.mul(B[:, :, None, :], (Pc[b0:b1, None, :] * pw[None])[None], out=F)
            yield b0, b1, F.reshape(n_ro, (b1 - b0) * S, n_pe)

    X = cis(-m_ro * g_ro)  # (nW, W, n_ro)
    dq = _chebyshev(delta / d_max, S).to(cdt)  # (nW, W, S): T_s(delta / d_max)
    Sm = _line_products(H, X, dq, dlp, batches(), (M, R, S))  # (nW, W, M)
    vt = torch.as_tensor(valid.reshape(-1), device=dev)
    sel = torch.as_tensor(idx.reshape(-1)[valid.reshape(-1)], device=dev)
    res = torch.zeros((T, M), dtype=cdt, device=dev).index_copy(0, sel, Sm.reshape(nW * W, M)[vt])
    return res.T


def _apply_kernel_separable(Cm, sgn, use_t2d, mt_r, dtt, vox: VoxelData, cfg) -> torch.Tensor:
    """(M, T) = Cm (M, V) @ Kern(t, v)^T without forming Kern (voxels on the full Cartesian grid).

    Kern(t, v) = exp(-dt lam(v)) exp(-i mx(t) x_v) exp(-i my(t) y_v), lam = 1/T2 + sgn/T2' + i omega.
    Samples are grouped in windows of ``cfg.window_samples``; inside a window with centre tc,
    exp(-dt lam) = exp(-tc lam) sum_r (-(dt - tc) lam)^r / r! with R terms (remainder below
    ``cfg.taylor_tol``), and the voxel sum factorises per axis: batched (W x nx) @ (nx x M R ny)
    products, then a sum over y with the (W x ny) y-phase factors.  Cost T V M R complex
    multiply-adds as matrix products, no T x V exponentials.
    """
    dev = Cm.device
    ny, nx = vox.shape
    M = Cm.shape[0]
    cdt = Cm.dtype
    rdt = mt_r.dtype
    if cfg.line_aware and dtt.size >= 4:
        # readout lines (EPI, Cartesian): contract the phase-encoded axis once per line
        md = mt_r.detach().cpu().numpy()
        ro = int(np.argmax(np.median(np.abs(np.diff(md[:, :2], axis=0)), axis=0)))  # moves at every sample
        pe = 1 - ro
        wins = _line_windows(md[:, pe], md[:, ro], _LINE_WINDOW_MAX)
        if wins is not None:
            g_pe = (vox.yg if pe == 1 else vox.xg).detach().abs().max().item()
            x_d = 0.5 * max(float(np.ptp(md[a:b, pe])) for a, b in wins) * g_pe
            # worth it while the drift series stays short: cost ~ S (1 / samples per line + 1 / n_pe) of the
            # per-sample path's
            per_line = int(np.median(wins[:, 1] - wins[:, 0]))
            if 4 * _drift_terms(x_d, cfg.taylor_tol) <= min(ny if pe == 1 else nx, per_line):
                return _apply_kernel_lines(Cm, sgn, use_t2d, mt_r, dtt, vox, cfg, pe, wins)
    full, lam, lam_max = _on_grid(Cm, sgn, use_t2d, vox)
    T = dtt.size
    W = max(1, min(int(cfg.window_samples), T))
    nW = -(-T // W)
    pad = nW * W - T
    dt_p = np.concatenate([dtt, np.full(pad, dtt[-1])]).reshape(nW, W)
    tc = 0.5 * (dt_p.min(1) + dt_p.max(1))  # (nW,)
    dl = dt_p - tc[:, None]  # (nW, W)
    R = _taylor_terms(float(np.abs(dl).max()) * lam_max, cfg.taylor_tol)
    fact = np.cumprod([1.0] + [1.0 / r for r in range(1, R)])
    powers = torch.stack([cneg(lam) ** r * float(fact[r]) for r in range(R)], 0)  # (R, V)
    mt_p = torch.cat([mt_r, mt_r[-1:].expand(pad, -1)], 0) if pad else mt_r
    mx = mt_p[:, 0].reshape(nW, W, 1)
    my = mt_p[:, 1].reshape(nW, W, 1)
    X = cexp(torch.zeros_like(mx * vox.xg), -mx * vox.xg)  # (nW, W, nx)
    Y = cexp(torch.zeros_like(my * vox.yg), -my * vox.yg)  # (nW, W, ny)
    dlp = torch.as_tensor(np.stack([dl**r for r in range(R)], -1), dtype=rdt, device=dev).to(cdt)  # (nW, W, R)
    tc_t = torch.as_tensor(tc, dtype=rdt, device=dev).to(cdt)
    # batches of windows bounded by chunk_elems for the (b, M, R, V) tensor
    per_w = max(1, M * R * ny * nx)
    bs = max(1, int(cfg.chunk_elems // per_w))
    out = []
    for b0 in range(0, nW, bs):
        b1 = min(nW, b0 + bs)
        base = full[None] * cexp_of(-tc_t[b0:b1, None] * lam[None])[:, None, :]  # (b, M, V)
        D = (base[:, :, None, :] * powers[None, None]).reshape(b1 - b0, M * R * ny, nx)  # (b, M R ny, nx)
        U = (X[b0:b1] @ D.transpose(1, 2)).reshape(b1 - b0, W, M, R, ny)
        V_ = (U * Y[b0:b1, :, None, None, :]).sum(-1)  # (b, W, M, R)
        sw = (V_ * dlp[b0:b1, :, None, :]).sum(-1)  # (b, W, M)
        out.append(sw.permute(2, 0, 1).reshape(M, -1))
    return torch.cat(out, 1)[:, :T]
