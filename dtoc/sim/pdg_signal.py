"""Signal of the emitting PDG states at the ADC samples (torch), and voxel data.

For an emitting transverse state j of interval n (start t_n) and an ADC sample at t (dt = t - t_n):

    s_c(t) = sum_j vox(k_j(t)) exp(-i k0_j(t)) sum_v C_c(v) A_j(v) exp(-dt/T2(v) - |tau_j + dt|/T2'(v)
             - D(v) b_j(t)) exp(-i (kx_j(t) x_v + ky_j(t) y_v + omega_v (tau_j + dt)))

with k_j(t) = k_j(t_n) + gamma * integral_{t_n}^t G (exact PWL), b_j(t) = integral_{t_n}^t |k_j|^2,
vox the voxel-shape factor (box: product of sinc(k_a d_a / 2)), C_c the coil sensitivity.  Two
evaluations: 'direct' (exact exponentials of every (state, sample, voxel) triple, chunked) and
'separable' (:mod:`dtoc.sim.pdg_separable`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch


@dataclass
class VoxelData:
    """Per-voxel tensors of the simulated (PD > 0) voxels, flattened in (iy, ix) order."""

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

    @property
    def n(self) -> int:
        return int(self.pd.shape[0])

    @property
    def n_coils(self) -> int:
        return 1 if self.coil is None else int(self.coil.shape[0])

    @classmethod
    def from_phantom(cls, ph, initial_mz, dtype, device, cfg) -> "VoxelData":
        ny, nx = ph.pd.shape
        mask = np.asarray(ph.pd) > 0
        flat = np.where(mask.ravel())[0]
        iy, ix = np.divmod(flat, nx)
        T = lambda a: torch.as_tensor(np.asarray(a, dtype=np.float64).ravel()[flat], dtype=dtype, device=device)  # noqa: E731
        with np.errstate(divide="ignore"):
            r1 = 1.0 / np.asarray(ph.t1_s, dtype=np.float64)
            r2 = 1.0 / np.asarray(ph.t2_s, dtype=np.float64)
            r2d = 1.0 / np.asarray(ph.t2dash_s, dtype=np.float64)
        xx, yy = ph.positions_m()
        if initial_mz is None:
            mz0 = T(ph.pd)
        else:
            m = initial_mz.detach().cpu().numpy() if isinstance(initial_mz, torch.Tensor) else np.asarray(initial_mz)
            if m.shape != (ny, nx):
                raise ValueError(f"initial_mz has shape {m.shape}, expected {(ny, nx)}")
            mz0 = T(m)
        coil = None
        if ph.coil_sens is not None:
            cs = np.asarray(ph.coil_sens).reshape(ph.coil_sens.shape[0], -1)[:, flat]
            cd = torch.complex64 if dtype == torch.float32 else torch.complex128
            coil = torch.as_tensor(cs, dtype=cd, device=device)
        b0 = np.asarray(ph.b0_hz, dtype=np.float64)
        sel = mask
        return cls(
            index=torch.as_tensor(flat, device=device), iy=iy, ix=ix, shape=(ny, nx), pd=T(ph.pd), mz0=mz0, r1=T(r1), r2=T(r2),
            r2d=T(r2d), d=T(ph.d_m2_per_s), omega=T(2 * np.pi * b0), b1=T(ph.b1), x=T(xx), y=T(yy),
            xg=torch.as_tensor(xx[0], dtype=dtype, device=device), yg=torch.as_tensor(yy[:, 0], dtype=dtype, device=device), coil=coil,
            voxel_m=(ph.fov_m[0] / nx, ph.fov_m[1] / ny, cfg.voxel_size_z_m), voxel_shape=ph.voxel_shape,
            has_b0=bool(np.any(b0[sel] != 0)), has_t2d=bool(np.any(np.isfinite(np.asarray(ph.t2dash_s)[sel]))),
            has_diffusion=bool(np.any(np.asarray(ph.d_m2_per_s)[sel] > 0)),
        )

    def observe_mz(self, A, K, tau_s) -> torch.Tensor:
        """Voxel-mean Mz (V,) of longitudinal states A (Z, V) with k K (Z, 4) and dephasing time tau (Z,)."""
        tau = torch.as_tensor(tau_s, dtype=self.r2d.dtype, device=A.device)
        k = K.to(self.x.dtype)
        ph = -(k[:, 0:1] * self.x[None] + k[:, 1:2] * self.y[None] + tau[:, None] * self.omega[None])
        mag = -(tau.abs()[:, None] * self.r2d[None])
        E = torch.exp(torch.complex(mag, ph))
        vf = voxel_factor(K, self).to(A.dtype)
        return (A * E * vf[:, None]).sum(0).real


def voxel_factor(k: torch.Tensor, vox: VoxelData) -> torch.Tensor:
    """Complex factor (...) of dephasing k (..., 4): voxel-shape attenuation times exp(-i k0)."""
    k = k.to(vox.x.dtype)
    f = torch.ones(k.shape[:-1], dtype=k.dtype, device=k.device)
    if vox.voxel_shape != "none":
        for a, d in enumerate(vox.voxel_m):
            if d is None or d <= 0:
                continue
            if vox.voxel_shape == "box":
                f = f * torch.sinc(k[..., a] * (d / (2 * np.pi)))
            else:  # band-limited ('sinc') voxel: rect in k
                f = f * (k[..., a].abs() <= np.pi / d).to(k.dtype)
    return f * torch.exp(torch.complex(torch.zeros_like(f), -k[..., 3]))


def _diffusion_b(Kj, mom, n, lo, hi, dtt_t):
    """(J, T) b-integrals integral_{t_n}^t |k_j|^2 dt, float64."""
    u = Kj[:, :3] - mom.I_bound[n][:3][None, :]
    dJ1 = mom.J1_adc[lo:hi] - mom.J1_bound[n][None, :]
    dJ2 = mom.J2_adc[lo:hi] - mom.J2_bound[n]
    return (u * u).sum(1)[:, None] * dtt_t[None, :] + 2.0 * u @ dJ1.T + dJ2[None, :]


def emit_signal(iv, A, K, mom, n, vox: VoxelData, graph, bounds_t, cfg) -> torch.Tensor:
    """(C, T) signal of the emitting states of interval ``n`` at its ADC samples (before ADC phase)."""
    method = cfg.signal_method
    if method == "auto":
        method = "direct"
    if method == "separable":
        from dtoc.sim.pdg_separable import emit_signal_separable

        return emit_signal_separable(iv, A, K, mom, n, vox, graph, bounds_t, cfg)
    if method != "direct":
        raise ValueError(f"signal_method {cfg.signal_method!r}: expected 'auto', 'direct' or 'separable'")
    return emit_signal_direct(iv, A, K, mom, n, vox, graph, bounds_t, cfg)


def emit_signal_direct(iv, A, K, mom, n, vox: VoxelData, graph, bounds_t, cfg) -> torch.Tensor:
    """Exact evaluation, chunked over samples so that J x T_chunk x V <= cfg.chunk_elems."""
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
    Aj = A.index_select(0, J)  # (J, V)
    AC = Aj[None] if vox.coil is None else vox.coil[:, None, :] * Aj[None]  # (C, J, V)
    nJ, T = kt.shape[0], kt.shape[1]
    step = max(1, int(cfg.chunk_elems // max(1, nJ * vox.n)))
    out = []
    ktr = kt.to(rdt)
    tau_t = torch.as_tensor(tau, dtype=rdt, device=dev)
    dtr = torch.as_tensor(dtt, dtype=rdt, device=dev)
    for t0 in range(0, T, step):
        sl = slice(t0, min(T, t0 + step))
        kk = ktr[:, sl]
        ta = tau_t[:, sl]
        mag = -dtr[sl][None, :, None] * vox.r2[None, None, :] - ta.abs()[:, :, None] * vox.r2d[None, None, :]
        if bD is not None:
            mag = mag - bD[:, sl, None] * vox.d[None, None, :]
        ph = -(kk[:, :, 0:1] * vox.x[None, None, :] + kk[:, :, 1:2] * vox.y[None, None, :] + ta[:, :, None] * vox.omega[None, None, :])
        E = torch.exp(torch.complex(mag, ph))  # (J, t, V)
        s = torch.einsum("jtv,cjv->cjt", E, AC)
        out.append((s * vf[None, :, sl]).sum(1))
    return torch.cat(out, dim=1)
