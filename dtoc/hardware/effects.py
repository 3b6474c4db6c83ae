"""Effects of the hardware twin: each maps (demanded-so-far gradient, accumulated B0) to new ones.

Every effect is a :class:`torch.nn.Module` with

    forward(g_mT_per_m: (B, 3, T), b0_uT: (B, T), dt_s: float) -> (G_mT_per_m (B, 3, T), b0_uT (B, T))

It receives the gradient produced by the previous effect of the chain (the demanded waveform for the
first) and the B0 offset accumulated so far, and returns the new gradient and B0 with its own contribution.
Samples are at ``t_n = n * dt_s``; the waveform is piecewise linear between samples and **zero outside**
``[0, (T-1) dt]`` (so a non-zero first sample is a jump at t = 0).  Parameters are float64
:class:`torch.nn.Parameter` s (cast to the waveform's dtype/device on use), so identification can fit
them; every effect is differentiable w.r.t. the waveform and its parameters (``slew_limit`` and
``delay`` almost everywhere).  Axes: ``axis`` is the output axis ('x'|'y'|'z'; None = all three with
the same parameters), ``input_axis`` the source axis of cross and B0 terms.

Units: gradient mT/m, B0 uT, time s, slew T/m/s.  Kinds and parameter names follow docs/contracts.md §3.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch
from torch import nn

from dtoc.constants import AXES
from dtoc.errors import InputError
from dtoc.hardware.convolution import fft_convolve, kernel_spectrum, resample_kernel
from dtoc.hardware.recursion import exp_response, pole_response
from dtoc.util.cplx import cexp


def axis_index(name: str | None, what: str = "axis") -> int | None:
    """'x'|'y'|'z'|None -> 0|1|2|None (InputError otherwise)."""
    if name is None:
        return None
    if name not in AXES:
        raise InputError(f"{what} must be one of 'x', 'y', 'z' or null, got {name!r}")
    return AXES.index(name)


def _to_param(name: str, value: Any, kind: str, positive: bool = False, vector: bool = False) -> nn.Parameter:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"effect {kind!r}: parameter {name!r} must be a number, got {value!r}") from None
    if arr.ndim > (1 if vector else 0) or arr.size == 0:
        raise InputError(
            f"effect {kind!r}: parameter {name!r} must be a {'number or list' if vector else 'number'}, got {value!r}"
        )
    if not np.all(np.isfinite(arr)):
        raise InputError(f"effect {kind!r}: parameter {name!r} must be finite, got {value!r}")
    if positive and np.any(arr <= 0):
        raise InputError(f"effect {kind!r}: parameter {name!r} must be > 0, got {value!r}")
    return nn.Parameter(torch.as_tensor(arr, dtype=torch.float64))


def _jsonable(p: torch.Tensor) -> Any:
    v = p.detach().cpu().double().numpy()
    return float(v) if v.ndim == 0 else v.tolist()


class Effect(nn.Module):
    """Base class: stores kind, axes and the names of its parameters."""

    kind: str = ""
    param_names: tuple[str, ...] = ()

    def __init__(self, axis: str | None = None, input_axis: str | None = None):
        super().__init__()
        self.axis = axis
        self.input_axis = input_axis
        self._ax = axis_index(axis, "axis")
        self._in = axis_index(input_axis, "input_axis")

    def params_dict(self) -> dict[str, Any]:
        """JSON-serialisable parameter values (floats or lists)."""
        return {n: _jsonable(getattr(self, n)) for n in self.param_names}

    def spec(self) -> dict[str, Any]:
        """The model-file entry of this effect."""
        return {"kind": self.kind, "axis": self.axis, "input_axis": self.input_axis, "params": self.params_dict()}

    def _p(self, name: str, like: torch.Tensor) -> torch.Tensor:
        return getattr(self, name).to(dtype=like.dtype, device=like.device)

    def _replace_axes(self, g: torch.Tensor, new_sel: torch.Tensor) -> torch.Tensor:
        """Put ``new_sel`` (B, A, T) back into the selected axes of ``g`` (A = 3 when axis is None)."""
        if self._ax is None:
            return new_sel
        parts = [g[:, i : i + 1] if i != self._ax else new_sel for i in range(3)]
        return torch.cat(parts, dim=1)

    def _sel(self, g: torch.Tensor) -> torch.Tensor:
        return g if self._ax is None else g[:, self._ax : self._ax + 1]

    def extra_repr(self) -> str:
        return f"axis={self.axis}, input_axis={self.input_axis}, params={self.params_dict()}"


class Gain(Effect):
    """``gain`` {factor}: ``G[a] = factor * g[a]`` (dimensionless) on ``axis`` (None: all axes)."""

    kind = "gain"
    param_names = ("factor",)

    def __init__(self, factor: float, axis: str | None = None):
        super().__init__(axis)
        self.factor = _to_param("factor", factor, self.kind)

    def forward(self, g, b0, dt_s):
        return self._replace_axes(g, self._sel(g) * self._p("factor", g)), b0


class Offset(Effect):
    """``offset`` {mT_per_m}: ``G[a] = g[a] + mT_per_m`` (a constant field gradient, mT/m, at every sample)."""

    kind = "offset"
    param_names = ("mT_per_m",)

    def __init__(self, mT_per_m: float, axis: str | None = None):
        super().__init__(axis)
        self.mT_per_m = _to_param("mT_per_m", mT_per_m, self.kind)

    def forward(self, g, b0, dt_s):
        return self._replace_axes(g, self._sel(g) + self._p("mT_per_m", g)), b0


class Delay(Effect):
    """``delay`` {seconds}: ``G[a](t) = g[a](t - seconds)`` (positive = late), any real delay.

    The demanded waveform is piecewise linear between samples, so its delayed copy at the sample times is
    the linear interpolation ``(1-f) g[n-m] + f g[n-m-1]`` with ``seconds/dt = m + f`` (0 <= f < 1): exact
    for the played (PWL) waveform at every sample, no ringing, no circular wrap.  Edges: the waveform is
    zero before t = 0 and after its last sample (zero padding).  Differentiable in ``seconds`` except at
    multiples of dt (where the one-sided derivative of the segment to the left is used).
    """

    kind = "delay"
    param_names = ("seconds",)

    def __init__(self, seconds: float, axis: str | None = None):
        super().__init__(axis)
        self.seconds = _to_param("seconds", seconds, self.kind)

    @staticmethod
    def _shift(x: torch.Tensor, m: int) -> torch.Tensor:
        """y[n] = x[n - m], zero-filled."""
        T = x.shape[-1]
        if m == 0:
            return x
        if abs(m) >= T:
            return torch.zeros_like(x)
        if m > 0:
            return torch.nn.functional.pad(x[..., : T - m], (m, 0))
        return torch.nn.functional.pad(x[..., -m:], (0, -m))

    def forward(self, g, b0, dt_s):
        d = self._p("seconds", g) / dt_s
        # the integer shift from the parameter where it lives (the host): the same division in the
        # waveform's dtype, no read of a device tensor (a synchronisation per forward on a GPU)
        m = math.floor(float(self.seconds.detach().to(g.dtype) / dt_s))
        f = d - m
        x = self._sel(g)
        out = (1 - f) * self._shift(x, m) + f * self._shift(x, m + 1)
        return self._replace_axes(g, out), b0


class DelayBandlimited(Delay):
    """``delay_bandlimited`` {seconds}: ``G[a](t) = g[a](t - seconds)`` for a *band-limited* waveform (the
    samples of a smooth field, e.g. a field-camera measurement of sinusoidal or filtered waveforms): the
    Fourier shift ``exp(-2 pi i f seconds)`` on a zero-padded (2T) record, exact for a waveform band-limited
    below Nyquist that is zero outside the record.  ``delay`` (linear interpolation) is exact for the
    piecewise-linear waveforms a Pulseq interpreter plays; this one for smooth data.
    """

    kind = "delay_bandlimited"

    def forward(self, g, b0, dt_s):
        x = self._sel(g)
        T = x.shape[-1]
        n = 2 * T
        f = torch.fft.rfftfreq(n, d=dt_s, dtype=x.dtype, device=x.device)
        X = torch.fft.rfft(x, n=n)
        ph = cexp(torch.zeros_like(f), -2 * math.pi * f * self._p("seconds", x))
        out = torch.fft.irfft(X * ph, n=n)[..., :T]
        return self._replace_axes(g, out), b0


class _ExpBase(Effect):
    """Shared exponential machinery: ``alpha`` and ``tau_s`` are numbers or equal-length lists."""

    alpha_name = "alpha"
    param_names = ("alpha", "tau_s")

    def __init__(self, alpha, tau_s, axis=None, input_axis=None):
        super().__init__(axis, input_axis)
        a = _to_param(self.alpha_name, alpha, self.kind, vector=True)
        t = _to_param("tau_s", tau_s, self.kind, positive=True, vector=True)
        if a.shape != t.shape:
            raise InputError(f"effect {self.kind!r}: {self.alpha_name!r} and 'tau_s' must have the same length")
        setattr(self, self.alpha_name, a)
        self.tau_s = t

    #: True: driven by the demanded waveform (the chain's input); False (``*_chain`` kinds): by the
    #: output of the effects before it.
    driven_by_demand = True

    def _drive(self, g: torch.Tensor, demand: torch.Tensor | None) -> torch.Tensor:
        """The waveform whose slew drives the eddy currents: ``demand`` for the contract's kinds (``g``
        when the effect is used alone), ``g`` (the previous effect's output) for the ``*_chain`` kinds."""
        return demand if (self.driven_by_demand and demand is not None) else g

    def _eddy(self, src: torch.Tensor, dt_s: float) -> torch.Tensor:
        """sum_n alpha_n (dsrc/dt conv exp(-t/tau_n)); src (B, A, T) -> (B, A, T)."""
        alpha = self._p(self.alpha_name, src).reshape(-1, 1)
        tau = self._p("tau_s", src).reshape(-1, 1)
        e = exp_response(src.unsqueeze(-2), dt_s, tau)  # (B, A, K, T)
        return (alpha * e).sum(-2)


class ExpEddy(_ExpBase):
    """``exp_eddy`` {alpha, tau_s} (self term, paper Eq. 1), on ``axis`` (None: all three axes).

    ``G(t) = G_prev(t) - sum_n alpha_n * (dg/dt conv H(t) exp(-t/tau_n))(t)`` with ``g`` the **demanded**
    waveform (the chain's input, docs/contracts.md §3) and ``G_prev`` the output of the effects before it
    (``g`` itself when it comes first); alpha dimensionless (> 0 lowers the realized gradient after a
    ramp-up), tau in s; several time constants as lists.  Exact for the PWL waveform by the recursive
    update of :mod:`dtoc.hardware.recursion`; a step of height g from t = 0 gives ``g (1 - alpha exp(-t/tau))``.
    The variant ``exp_eddy_chain`` is driven by ``G_prev`` instead (eddy currents induced by the field the
    chain has produced so far, e.g. after a GIRF).
    """

    kind = "exp_eddy"

    def __init__(self, alpha, tau_s, axis: str | None = None):
        super().__init__(alpha, tau_s, axis)

    def forward(self, g, b0, dt_s, demand=None):
        src = self._sel(self._drive(g, demand))
        return self._replace_axes(g, self._sel(g) - self._eddy(src, dt_s)), b0


class CrossEddy(_ExpBase):
    """``cross_eddy`` {alpha, tau_s}: ``G[axis] -= sum_n alpha_n (dg[input_axis]/dt conv H(t) exp(-t/tau_n))``.

    Same sign convention and drive as ``exp_eddy`` (the demanded ``g``; ``cross_eddy_chain``: the output
    of the effects before it); alpha dimensionless ((mT/m) on ``axis`` per (mT/m) on ``input_axis``), tau
    in s.  ``axis`` and ``input_axis`` are required.
    """

    kind = "cross_eddy"

    def __init__(self, alpha, tau_s, axis: str, input_axis: str):
        if axis is None or input_axis is None:
            raise InputError(f"effect {self.kind!r} needs both 'axis' and 'input_axis'")
        super().__init__(alpha, tau_s, axis, input_axis)

    def forward(self, g, b0, dt_s, demand=None):
        src = self._drive(g, demand)[:, self._in : self._in + 1]
        tgt = g[:, self._ax : self._ax + 1]
        return self._replace_axes(g, tgt - self._eddy(src, dt_s)), b0


class B0Eddy(_ExpBase):
    """``b0_eddy`` {alpha_uT_per_mT_per_m, tau_s}: ``b0 -= sum_n alpha_n (dg[input_axis]/dt conv H(t) exp(-t/tau_n))``.

    A spatially uniform field (uT) driven by the demanded gradient on ``input_axis`` (``b0_eddy_chain``:
    by the output of the effects before it); alpha in uT per (mT/m), tau in s; same sign convention as
    ``exp_eddy``.  ``axis`` must be None.
    """

    kind = "b0_eddy"
    alpha_name = "alpha_uT_per_mT_per_m"
    param_names = ("alpha_uT_per_mT_per_m", "tau_s")

    def __init__(self, alpha_uT_per_mT_per_m, tau_s, input_axis: str, axis: str | None = None):
        if input_axis is None or axis is not None:
            raise InputError(f"effect {self.kind!r} needs 'input_axis' and no 'axis'")
        super().__init__(alpha_uT_per_mT_per_m, tau_s, None, input_axis)

    def forward(self, g, b0, dt_s, demand=None):
        src = self._drive(g, demand)[:, self._in : self._in + 1]
        return g, b0 - self._eddy(src, dt_s)[:, 0]


class ExpEddyChain(ExpEddy):
    """``exp_eddy_chain``: as ``exp_eddy``, driven by the output of the effects before it."""

    kind = "exp_eddy_chain"
    driven_by_demand = False


class CrossEddyChain(CrossEddy):
    """``cross_eddy_chain``: as ``cross_eddy``, driven by the output of the effects before it."""

    kind = "cross_eddy_chain"
    driven_by_demand = False


class B0EddyChain(B0Eddy):
    """``b0_eddy_chain``: as ``b0_eddy``, driven by the output of the effects before it."""

    kind = "b0_eddy_chain"
    driven_by_demand = False


class Resonance(Effect):
    """``resonance`` {f0_hz, q, amplitude, phase_rad}: a damped mechanical resonance of the gradient coil,
    driven by the slew of the demanded waveform, on ``axis`` (None: all three axes).

    ``G[a](t) = G_prev[a](t) + amplitude * Re(exp(i phase) * (dg_a/dt conv H(t) exp(p t)))`` with the pole
    ``p = -w0/(2q) + i w0 sqrt(1 - 1/(4 q^2))``, ``w0 = 2 pi f0_hz``: a step of height ``dG`` rings as
    ``amplitude * dG * exp(-w0 t / 2q) cos(w_d t + phase)``.  ``f0_hz`` (Hz) > 0, ``q`` > 0.5 (underdamped),
    ``amplitude`` dimensionless, ``phase_rad`` (rad).  Exact for the PWL waveform
    (:func:`dtoc.hardware.recursion.pole_response`).
    """

    kind = "resonance"
    param_names = ("f0_hz", "q", "amplitude", "phase_rad")
    driven_by_demand = True

    def __init__(self, f0_hz, q, amplitude, phase_rad=0.0, axis: str | None = None):
        super().__init__(axis)
        self.f0_hz = _to_param("f0_hz", f0_hz, self.kind, positive=True)
        self.q = _to_param("q", q, self.kind, positive=True)
        if float(self.q.detach()) <= 0.5:
            raise InputError(f"effect 'resonance': q must be > 0.5 (underdamped), got {q!r}")
        self.amplitude = _to_param("amplitude", amplitude, self.kind)
        self.phase_rad = _to_param("phase_rad", phase_rad, self.kind)

    def pole(self, like: torch.Tensor) -> torch.Tensor:
        """The complex pole p (1/s)."""
        w0 = 2 * math.pi * self._p("f0_hz", like)
        q = self._p("q", like)
        return torch.complex(-w0 / (2 * q), w0 * torch.sqrt(1 - 1 / (4 * q * q)))

    def forward(self, g, b0, dt_s, demand=None):
        src = self._sel(demand if demand is not None else g)
        r = pole_response(src, dt_s, self.pole(src))
        ph = self._p("phase_rad", src)
        ring = self._p("amplitude", src) * (torch.cos(ph) * r.real - torch.sin(ph) * r.imag)
        return self._replace_axes(g, self._sel(g) + ring.to(g.dtype)), b0


class TimeBase(Effect):
    """``time_base`` {ppm}: the *measurement's* clock runs off by ``ppm`` parts per million, so the field is
    sampled at ``t_n (1 + ppm 1e-6)`` instead of ``t_n``: ``G[a](t_n) = G_prev[a](t_n (1 + ppm 1e-6))``, a
    delay that grows linearly with time (-ppm 1e-6 t).  Linear interpolation of the PWL waveform, on every
    axis (``axis`` None) or one.  A property of the measuring device (field camera, ADC), not of the
    gradient chain: ``dtoc identify`` applies it to the measurement and never writes it into a hardware model.
    """

    kind = "time_base"
    param_names = ("ppm",)

    def __init__(self, ppm: float, axis: str | None = None):
        super().__init__(axis)
        self.ppm = _to_param("ppm", ppm, self.kind)

    def forward(self, g, b0, dt_s):
        x = self._sel(g)
        T = x.shape[-1]
        n = torch.arange(T, dtype=x.dtype, device=x.device)
        pos = n * (1 + self._p("ppm", x) * 1e-6)  # sample position (units of dt) actually measured
        i0 = torch.clamp(torch.floor(pos.detach()).long(), 0, T - 1)
        i1 = torch.clamp(i0 + 1, 0, T - 1)
        f = pos - i0.to(x.dtype)
        out = (1 - f) * x[..., i0] + f * x[..., i1]
        out = torch.where(pos <= T - 1, out, torch.zeros_like(out))  # zero after the last sample
        return self._replace_axes(g, out), b0


class SlewLimit(Effect):
    """``slew_limit`` {max_slew_T_per_m_per_s}: the amplifier cannot slew faster than the limit (non-linear).

    Recursive clamp of the increment, per axis (``axis`` None: each axis separately):
    ``G[0] = g[0]``, ``G[n+1] = G[n] + clip(g[n+1] - G[n], -s, s)`` with ``s = max_slew * 1e3 * dt``
    (mT/m per sample; 1 T/m/s = 1e3 mT/m/s).  While limited, the output ramps at the maximum slew and
    catches up with the demand when it can.  Implementation: the (non-differentiable) switching pattern
    is found in numpy (Python loop only over limited stretches); the output is then written as
    ``G[n] = g[m(n)] + c(n) * s`` (m(n): last sample where G followed g, c(n): net signed count of
    limited steps) and evaluated in torch, which gives the exact derivative of the recursion w.r.t. the
    waveform and the limit almost everywhere.
    """

    kind = "slew_limit"
    param_names = ("max_slew_T_per_m_per_s",)

    def __init__(self, max_slew_T_per_m_per_s: float, axis: str | None = None):
        super().__init__(axis)
        self.max_slew_T_per_m_per_s = _to_param(
            "max_slew_T_per_m_per_s", max_slew_T_per_m_per_s, self.kind, positive=True
        )

    @staticmethod
    def _pattern(g: np.ndarray, s: float) -> tuple[np.ndarray, np.ndarray]:
        """Anchor indices and signed step counts, g (C, T)."""
        C, T = g.shape
        anchor = np.broadcast_to(np.arange(T), (C, T)).copy()
        count = np.zeros((C, T), dtype=np.float64)
        tol = s * (1 + 1e-9)
        for c in range(C):
            x = g[c]
            viol = np.flatnonzero(np.abs(np.diff(x)) > tol)
            n = 0
            vi = 0
            while vi < len(viol):
                p = int(viol[vi])
                if p < n:
                    vi += 1
                    continue
                G_prev = x[p]
                k = p + 1
                cnt = 0
                while k < T:
                    d = x[k] - G_prev
                    if abs(d) <= tol:
                        break
                    cnt += 1 if d > 0 else -1
                    G_prev = x[p] + cnt * s
                    anchor[c, k] = p
                    count[c, k] = cnt
                    k += 1
                n = k
                vi += 1
        return anchor, count

    def forward(self, g, b0, dt_s):
        x = self._sel(g)
        B, A, T = x.shape
        s = self._p("max_slew_T_per_m_per_s", x) * 1e3 * dt_s
        flat = x.reshape(B * A, T)
        anchor, count = self._pattern(flat.detach().cpu().double().numpy(), float(s.detach()))
        idx = torch.as_tensor(anchor, device=x.device)
        cnt = torch.as_tensor(count, dtype=x.dtype, device=x.device)
        out = flat.gather(-1, idx) + cnt * s
        return self._replace_axes(g, out.reshape(B, A, T)), b0


class Girf(Effect):
    """``girf``: measured linear response, 3x3 with optional B0 row (docs/contracts.md §2).

    ``G[o](t) = sum_i (h[o, i] * g[i])(t)``, ``b0(t) += sum_i (h0[i] * g[i])(t)``, where ``h[o, i, l]`` is the
    per-sample response on output axis o to input axis i at time ``t0_s + l*dt_s`` after the impulse
    (``h[o, o].sum()`` = DC gain, ~1) and ``h0[i, l]`` is in uT per (mT/m) per sample.  The kernel is
    resampled onto the waveform grid when ``dt`` differs or ``t0`` is not a multiple of it (see
    :mod:`dtoc.hardware.convolution`) and applied by zero-padded FFT convolution (the waveform is zero
    outside its samples).  ``h`` and ``h0`` are parameters (identification may refine them).
    Axes whose response is exactly ideal (unit tap at t = 0, no cross/B0 terms; e.g. z of a 2-axis
    published GIRF) are passed through unchanged (their parameters then have no effect).
    ``file`` remembers where the kernel came from (model files reference it).
    """

    kind = "girf"
    param_names = ()

    def __init__(self, h, dt_s: float, t0_s: float = 0.0, h0=None, file: str | None = None):
        super().__init__(None, None)
        h = np.asarray(h, dtype=np.float64)
        if h.ndim != 3 or h.shape[:2] != (3, 3) or h.shape[2] < 1:
            raise InputError(f"girf: h must have shape (3, 3, L), got {h.shape}")
        if not (np.isfinite(dt_s) and dt_s > 0):
            raise InputError(f"girf: dt must be > 0, got {dt_s}")
        self.h = nn.Parameter(torch.as_tensor(h))
        if h0 is not None:
            h0 = np.asarray(h0, dtype=np.float64)
            if h0.shape != (3, h.shape[2]):
                raise InputError(f"girf: h0 must have shape (3, {h.shape[2]}), got {h0.shape}")
            self.h0 = nn.Parameter(torch.as_tensor(h0))
        else:
            self.h0 = None
        self.dt_s = float(dt_s)
        self.t0_s = float(t0_s)
        self.file = file
        self.passthrough = self._ideal_axes(h, self.h0, self.dt_s, self.t0_s)

    @staticmethod
    def _ideal_axes(h: np.ndarray, h0, dt_s: float, t0_s: float) -> tuple[int, ...]:
        """Axes with an exactly ideal response (unit tap at t = 0, no cross or B0 terms), e.g. an axis
        absent from a published GIRF: they are passed through unchanged instead of being band-limited
        by the kernel's resampling."""
        out = []
        i0 = -t0_s / dt_s
        if abs(i0 - round(i0)) > 1e-6 or not 0 <= round(i0) < h.shape[2]:
            return ()
        i0 = int(round(i0))
        h0n = None if h0 is None else h0.detach().numpy()
        for a in range(3):
            delta = np.zeros(h.shape[2])
            delta[i0] = 1.0
            others = [b for b in range(3) if b != a]
            if (
                np.array_equal(h[a, a], delta)
                and not np.any(h[a, others])
                and not np.any(h[others, a])
                and (h0n is None or not np.any(h0n[a]))
            ):
                out.append(a)
        return tuple(out)

    def kernels(self, dt_s: float, like: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None, int]:
        """(h (3,3,L2), h0 (1,3,L2) or None, shift) on the grid dt_s, dtype/device of ``like``."""
        hs = self.h if self.h0 is None else torch.cat([self.h, self.h0.unsqueeze(0)], dim=0)  # (3|4, 3, L)
        hs = hs.to(dtype=like.dtype, device=like.device)
        hr, shift = resample_kernel(hs, self.dt_s, self.t0_s, dt_s)
        return hr[:3], (hr[3:] if self.h0 is not None else None), shift

    def _full_kernel(self, dt_s: float, g: torch.Tensor):
        """Resampled (3|4, 3, L2) kernel, shift and its spectrum; cached while the kernel is frozen
        (no gradient w.r.t. h/h0 requested), e.g. inside an optimizer loop over the waveform."""
        frozen = not (
            torch.is_grad_enabled() and (self.h.requires_grad or (self.h0 is not None and self.h0.requires_grad))
        )
        key = (
            float(dt_s),
            g.shape[-1],
            g.dtype,
            str(g.device),
            self.h._version,
            None if self.h0 is None else self.h0._version,
        )
        if frozen and getattr(self, "_cache_key", None) == key:
            return self._cache_val
        h, h0, shift = self.kernels(dt_s, g)
        full = h if h0 is None else torch.cat([h, h0], dim=0)
        if frozen:
            full = full.detach()
        spec = kernel_spectrum(full, g.shape[-1])
        if frozen:
            self._cache_key, self._cache_val = key, (full, shift, spec)
        return full, shift, spec

    def forward(self, g, b0, dt_s):
        full, shift, spec = self._full_kernel(dt_s, g)
        h0 = full[3:] if full.shape[0] == 4 else None
        out = fft_convolve(g, full, shift, spectrum=spec)
        if self.passthrough:
            keep = [g[:, a : a + 1] if a in self.passthrough else out[:, a : a + 1] for a in range(3)]
            out = torch.cat(keep + ([out[:, 3:]] if h0 is not None else []), dim=1)
        if h0 is None:
            return out, b0
        return out[:, :3], b0 + out[:, 3]

    def spec(self) -> dict[str, Any]:
        return {"kind": self.kind, "axis": None, "input_axis": None, "params": {}, "file": self.file}

    def extra_repr(self) -> str:
        return f"L={self.h.shape[-1]}, dt_s={self.dt_s}, t0_s={self.t0_s}, h0={self.h0 is not None}, file={self.file}"


class Lti(Effect):
    """``lti`` {taps, dt_s, t0_s}: non-parametric linear correction filter, additive, per axis.

    ``G[a] = g[a] + (taps[a] * g[a])`` with ``taps[a, l]`` the per-sample correction at time
    ``t0_s + l*dt_s`` (dimensionless; zero taps = identity).  ``axis`` None: taps (3, L), one filter per
    axis; ``axis`` given: taps (L,).  Resampled and applied like ``girf`` (zero-padded FFT).
    """

    kind = "lti"
    param_names = ("taps",)

    def __init__(self, taps, dt_s: float, t0_s: float = 0.0, axis: str | None = None):
        super().__init__(axis)
        t = np.asarray(taps, dtype=np.float64)
        want = 2 if axis is None else 1
        if t.ndim != want or (axis is None and t.shape[0] != 3) or t.shape[-1] < 1 or not np.all(np.isfinite(t)):
            raise InputError(
                f"effect 'lti': taps must be finite with shape {'(3, L)' if axis is None else '(L,)'}, got {t.shape}"
            )
        if not (np.isfinite(dt_s) and dt_s > 0):
            raise InputError(f"effect 'lti': dt_s must be > 0, got {dt_s}")
        self.taps = nn.Parameter(torch.as_tensor(t))
        self.dt_s = float(dt_s)
        self.t0_s = float(t0_s)

    def params_dict(self) -> dict[str, Any]:
        return {"taps": _jsonable(self.taps), "dt_s": self.dt_s, "t0_s": self.t0_s}

    def forward(self, g, b0, dt_s):
        x = self._sel(g)  # (B, A, T)
        taps = self.taps.to(dtype=g.dtype, device=g.device).reshape(-1, self.taps.shape[-1])  # (A, L)
        tr, shift = resample_kernel(taps, self.dt_s, self.t0_s, dt_s)
        A = tr.shape[0]
        h = torch.diag_embed(tr.transpose(0, 1)).permute(1, 2, 0) if A > 1 else tr.reshape(1, 1, -1)
        return self._replace_axes(g, x + fft_convolve(x, h, shift)), b0


#: kind -> class; the model file's "kind" picks one.
EFFECTS: dict[str, type[Effect]] = {
    c.kind: c
    for c in (
        Delay,
        DelayBandlimited,
        Gain,
        Offset,
        ExpEddy,
        CrossEddy,
        B0Eddy,
        ExpEddyChain,
        CrossEddyChain,
        B0EddyChain,
        Girf,
        Lti,
        SlewLimit,
        Resonance,
        TimeBase,
    )
}
