"""Build base sequences from specs (:mod:`dtoc.seq.spec`) with pypulseq.

Every gradient is an extended trapezoid (or trapezoid) with its vertices on raster edges, so the file
plays exactly the piecewise-linear waveform the IR holds (no corner loss, docs/contracts.md §4).  Waveforms are
designed at the spec's ``system`` limits; a spec whose *ideal* waveforms cannot meet them (the 0.73 ms
EPI) is still built - it is an optimization target - and :func:`build` warns with the violation
figures (``dtoc check`` then rejects the file).  pypulseq's own limit checks are bypassed for that
reason; dtoc checks limits itself (:func:`dtoc.seq.check.check_ir_limits`).

Output is deterministic: the same spec gives byte-identical files (pypulseq writes no timestamps).
"""

from __future__ import annotations

import math
import os
import tempfile
import warnings
from pathlib import Path

import numpy as np

from dtoc.constants import GAMMA_HZ_PER_T
from dtoc.errors import InputError
from dtoc.seq.check import check_ir_limits
from dtoc.seq.pulseq import quiet, representable_amplitudes, seq_bytes
from dtoc.seq.read import from_pypulseq, read_pypulseq
from dtoc.seq.spec import BaseSpec, EpiSpec, GreSpec

_EPS = 1e-9


class SpecLimitWarning(UserWarning):
    """The built (ideal) waveforms exceed the spec's system limits."""


def _hz(g_mT_per_m: float) -> float:
    return g_mT_per_m * 1e-3 * GAMMA_HZ_PER_T


def _ceil_r(t: float, r: float) -> float:
    return math.ceil(t / r - 1e-6) * r


def _round_r(t: float, r: float) -> float:
    return round(t / r) * r


def _ext(pp, channel, times, amps, opts):
    return pp.make_extended_trapezoid(
        channel=channel, times=np.asarray(times, dtype=float), amplitudes=representable_amplitudes(amps), system=opts
    )


def _trap_in(area: float, T: float, gmax: float, smax: float, r: float):
    """Shortest-ramp symmetric trapezoid of ``area`` (1/m) lasting exactly ``T`` (s): (ramp, amp [Hz/m]) or None."""
    if abs(area) < 1e-12:
        return (0.0, 0.0)
    n = int(round(T / r))
    for k in range(1, n // 2 + 1):
        ramp = k * r
        amp = area / (T - ramp)
        if abs(amp) <= gmax * (1 + 1e-9) and abs(amp) / ramp <= smax * (1 + 1e-9):
            return ramp, amp
    return None


def _prewinder(area: float, g_end: float, T: float, gmax: float, smax: float, r: float):
    """Vertices of a lobe 0 -> -Gp (flat) -> g_end within ``T`` whose area is ``area`` (1/m, < 0).

    Ramps are the shortest raster multiples meeting ``smax``; the flat amplitude is solved exactly.
    Returns (times, amps) or None if infeasible (amplitude above gmax or no room for the ramps).
    """
    gp = 0.5 * gmax
    for _ in range(50):
        r1 = _ceil_r(abs(gp) / smax, r) or r
        r2 = _ceil_r(abs(gp - g_end) / smax, r) or r
        flat = T - r1 - r2
        if flat < -_EPS:
            return None
        # area = gp*(r1/2 + flat + r2/2) + g_end*r2/2 with gp < 0
        new = (area - g_end * r2 / 2) / (r1 / 2 + flat + r2 / 2)
        if abs(new - gp) < 1e-9 * max(1.0, abs(new)):
            gp = new
            break
        gp = new
    r1 = _ceil_r(abs(gp) / smax, r) or r
    r2 = _ceil_r(abs(gp - g_end) / smax, r) or r
    flat = T - r1 - r2
    if flat < -_EPS or abs(gp) > gmax * (1 + 1e-9):
        return None
    if abs(r1 / 2 + flat + r2 / 2) < _EPS:
        return None
    gp = (area - g_end * r2 / 2) / (r1 / 2 + flat + r2 / 2)
    if abs(gp) / r1 > smax * (1 + 1e-6) or abs(gp - g_end) / r2 > smax * (1 + 1e-6) or abs(gp) > gmax * (1 + 1e-9):
        return None
    if flat < _EPS:
        return [0.0, r1, T], [0.0, gp, g_end]
    return [0.0, r1, r1 + flat, T], [0.0, gp, gp, g_end]


def _common_definitions(seq, spec: BaseSpec) -> None:
    seq.set_definition("Name", spec.name)
    seq.set_definition("Kind", spec.kind)
    fov = spec.fov_mm * 1e-3
    seq.set_definition("FOV", [fov, fov, spec.slice_thickness_mm * 1e-3])
    seq.set_definition("MatrixSize", [spec.matrix, spec.matrix, 1])
    seq.set_definition("ReadoutAxis", "x")
    seq.set_definition("PhaseAxis", "y")
    seq.set_definition("SliceAxis", "z")
    seq.set_definition("FlipAngleDeg", float(spec.flip_angle_deg))
    seq.set_definition("MaxGrad_mT_per_m", float(spec.system.max_grad_mT_per_m))
    seq.set_definition("MaxSlew_T_per_m_per_s", float(spec.system.max_slew_T_per_m_per_s))


# ---------------------------------------------------------------------------------------------- GRE
def _build_gre(spec: GreSpec):
    from dtoc.seq.pulseq import import_pypulseq

    pp = import_pypulseq()

    sysd = spec.system
    opts = sysd.to_pypulseq_opts(enforce_limits=False)
    r = sysd.grad_raster_s
    gmax, smax = _hz(sysd.max_grad_mT_per_m), sysd.max_slew_T_per_m_per_s * GAMMA_HZ_PER_T
    n = spec.matrix
    fov = spec.fov_mm * 1e-3
    dk = 1.0 / fov  # 1/m
    dwell = spec.dwell_us * 1e-6
    t_adc = n * dwell
    if abs(t_adc / r - round(t_adc / r)) > 1e-6:
        raise InputError(
            f"{spec.name}: ADC duration matrix x dwell_us = {t_adc * 1e6:g} us is not a multiple of the gradient raster"
        )
    t_rf_period = _round_r(spec.rf_period_ms * 1e-3, r)
    guard = max(sysd.rf_dead_time_s, sysd.rf_ringdown_time_s)
    rf_dur = spec.rf_duration_ms * 1e-3 if spec.rf_duration_ms else t_rf_period - 2 * guard
    rf_delay = _round_r((t_rf_period - rf_dur) / 2, sysd.rf_raster_s)
    if (
        rf_dur <= 0
        or rf_delay < sysd.rf_dead_time_s - _EPS
        or t_rf_period - rf_delay - rf_dur < sysd.rf_ringdown_time_s - _EPS
    ):
        raise InputError(
            f"{spec.name}: rf_period_ms {spec.rf_period_ms:g} cannot hold the pulse with the system's RF dead time and ring-down"
        )
    t_rf_center = rf_delay + rf_dur / 2
    g_ro = dk / dwell  # Hz/m: one dk per dwell
    # ADC start from TE: sample n/2 at t_adc0 + (n/2 + 0.5) dwell
    t_adc0 = t_rf_center + spec.te_ms * 1e-3 - (n / 2 + 0.5) * dwell
    t_adc0_r = _round_r(t_adc0, r)
    t_pre = t_adc0_r - t_rf_period
    pre_area = -(n / 2 + 0.5) * dk
    ky = (np.arange(spec.repetitions) % n - n / 2) * dk
    te_actual = t_adc0_r + (n / 2 + 0.5) * dwell - t_rf_center
    te_min = None
    for k in range(1, 10000):
        T = k * r
        if _prewinder(pre_area, g_ro, T, gmax, smax, r) and _trap_in(float(np.max(np.abs(ky))), T, gmax, smax, r):
            te_min = t_rf_period + T + (n / 2 + 0.5) * dwell - t_rf_center
            break
    if te_min is None:
        raise InputError(f"{spec.name}: no prewinder fits the system limits for this FOV/matrix")
    if t_pre < -_EPS or te_actual < te_min - 1e-9:
        raise InputError(
            f"{spec.name}: te_ms {spec.te_ms:g} is shorter than the minimum {te_min * 1e3:.3f} ms for this spec"
        )
    pre = _prewinder(pre_area, g_ro, t_pre, gmax, smax, r)
    # spoiler lobe on x: g_ro -> gs (flat) -> 0 within spoiler_duration
    gs = _hz(spec.spoiler_mT_per_m)
    t_sp = _round_r(spec.spoiler_duration_ms * 1e-3, r)
    r3 = _ceil_r(abs(gs - g_ro) / smax, r)
    r4 = _ceil_r(abs(gs) / smax, r) or r
    if gs > 0 and t_sp < r3 + r4 - _EPS:
        raise InputError(f"{spec.name}: spoiler_duration_ms {spec.spoiler_duration_ms:g} is too short for its ramps")
    t_rest = _round_r(spec.tr_ms * 1e-3, r) - t_rf_period - t_pre - t_adc
    t_ramp_down = _ceil_r(g_ro / smax, r)
    need = t_sp if gs > 0 else t_ramp_down
    if t_rest < need - _EPS:
        raise InputError(
            f"{spec.name}: tr_ms {spec.tr_ms:g} is too short (needs at least {(spec.tr_ms * 1e-3 - t_rest + need) * 1e3:.3f} ms)"
        )
    if gs > 0:
        sp_t = [0.0, r3, t_sp - r4, t_sp] if r3 > 0 else [0.0, t_sp - r4, t_sp]
        sp_a = [g_ro, gs, gs, 0.0] if r3 > 0 else [g_ro, gs, 0.0]
    else:
        sp_t, sp_a = [0.0, t_ramp_down], [g_ro, 0.0]
    rew_T = max(t_sp, t_ramp_down)

    seq = pp.Sequence(system=opts)
    rf_inc = 0.0
    rf_phase = 0.0
    for j in range(spec.repetitions):
        rf = pp.make_block_pulse(
            flip_angle=math.radians(spec.flip_angle_deg), duration=rf_dur, delay=rf_delay, system=opts, use="excitation"
        )
        rf.phase_offset = math.radians(rf_phase % 360.0)
        seq.add_block(rf, pp.make_delay(t_rf_period))
        evs = [_ext(pp, "x", pre[0], pre[1], opts), pp.make_delay(t_pre)]
        pe = _trap_in(float(ky[j]), t_pre, gmax, smax, r)
        if pe is None:
            raise InputError(f"{spec.name}: phase encoding does not fit the prewinder time")
        if pe[1] != 0.0:
            evs.append(_ext(pp, "y", [0, pe[0], t_pre - pe[0], t_pre], [0, pe[1], pe[1], 0], opts))
        seq.add_block(*evs)
        adc = pp.make_adc(num_samples=n, dwell=dwell, delay=0.0, system=opts)
        adc.phase_offset = math.radians(rf_phase % 360.0)
        seq.add_block(_ext(pp, "x", [0.0, t_adc], [g_ro, g_ro], opts), adc)
        evs = [_ext(pp, "x", sp_t, sp_a, opts), pp.make_delay(t_rest)]
        if spec.rewind_phase and ky[j] != 0.0:
            rw = _trap_in(float(-ky[j]), rew_T, gmax, smax, r)
            if rw is None:
                raise InputError(f"{spec.name}: phase rewinder does not fit the spoiler time")
            evs.append(_ext(pp, "y", [0, rw[0], rew_T - rw[0], rew_T], [0, rw[1], rw[1], 0], opts))
        seq.add_block(*evs)
        rf_inc = (rf_inc + spec.rf_spoiling_inc_deg) % 360.0
        rf_phase = (rf_phase + rf_inc) % 360.0
    _common_definitions(seq, spec)
    seq.set_definition("TE", float(te_actual))
    seq.set_definition("TR", float(t_rf_period + t_pre + t_adc + t_rest))
    seq.set_definition("RFSpoilingIncDeg", float(spec.rf_spoiling_inc_deg))
    return seq


# ---------------------------------------------------------------------------------------------- EPI
def _build_epi(spec: EpiSpec):
    from dtoc.seq.pulseq import import_pypulseq

    pp = import_pypulseq()

    sysd = spec.system
    opts = sysd.to_pypulseq_opts(enforce_limits=False)
    opts_real = sysd.to_pypulseq_opts(enforce_limits=True)
    r = sysd.grad_raster_s
    gmax, smax = _hz(sysd.max_grad_mT_per_m), sysd.max_slew_T_per_m_per_s * GAMMA_HZ_PER_T
    n = spec.matrix
    fov = spec.fov_mm * 1e-3
    dk = 1.0 / fov
    dwell = spec.dwell_us * 1e-6
    t_adc = n * dwell
    if abs(t_adc / r - round(t_adc / r)) > 1e-6:
        raise InputError(
            f"{spec.name}: ADC duration matrix x dwell_us = {t_adc * 1e6:g} us is not a multiple of the gradient raster"
        )
    esp = spec.echo_spacing_ms * 1e-3
    if abs(esp / r - round(esp / r)) > 1e-6:
        raise InputError(
            f"{spec.name}: echo_spacing_ms {spec.echo_spacing_ms:g} is not a multiple of the gradient raster"
        )
    esp = _round_r(esp, r)
    t_tr = esp - t_adc
    if t_tr < 2 * r - _EPS:
        raise InputError(
            f"{spec.name}: echo_spacing_ms {spec.echo_spacing_ms:g} leaves no time to reverse the readout (ADC lasts {t_adc * 1e3:g} ms)"
        )
    g_ro = dk / dwell
    if g_ro > gmax * (1 + 1e-9):
        raise InputError(
            f"{spec.name}: readout gradient {g_ro / GAMMA_HZ_PER_T * 1e3:.2f} mT/m exceeds the system's max_grad_mT_per_m"
        )
    # excitation
    try:
        rf, gz, gzr = pp.make_sinc_pulse(
            flip_angle=math.radians(spec.flip_angle_deg),
            duration=spec.rf_duration_ms * 1e-3,
            slice_thickness=spec.slice_thickness_mm * 1e-3,
            apodization=0.5,
            time_bw_product=spec.rf_time_bw_product,
            system=opts_real,
            return_gz=True,
            use="excitation",
        )
    except Exception as e:  # noqa: BLE001
        raise InputError(f"{spec.name}: slice-selective excitation does not fit the system: {e}") from None
    t_exc = _ceil_r(max(pp.calc_duration(rf), pp.calc_duration(gz)), r)
    t_rf_center = rf.delay + rf.center
    # readout transition (x) and blip (y) within t_tr
    t_ramp = _ceil_r(g_ro / smax, r)
    blip_area = dk
    t_b = 2 * _ceil_r(math.sqrt(blip_area / smax), r)
    # prephaser block: shortest that fits x prewinder (ending at +g_ro), y prephaser and z rephaser
    pre_area_x = -(n / 2 + 0.5) * dk
    pre_area_y = -(n / 2) * dk
    t_gzr = _ceil_r(pp.calc_duration(gzr), r)
    t_pre = None
    for k in range(1, 100000):
        T = k * r
        if T < t_gzr - _EPS:
            continue
        if _prewinder(pre_area_x, g_ro, T, gmax, smax, r) and _trap_in(pre_area_y, T, gmax, smax, r):
            t_pre = T
            break
    if t_pre is None:
        raise InputError(f"{spec.name}: no prephaser fits the system limits")
    te_min = t_exc + t_pre + (n / 2) * esp + (n / 2 + 0.5) * dwell - t_rf_center
    t_fill = 0.0
    if spec.te_ms is not None:
        if spec.te_ms * 1e-3 < te_min - 1e-9:
            raise InputError(
                f"{spec.name}: te_ms {spec.te_ms:g} is shorter than the minimum {te_min * 1e3:.3f} ms for this spec"
            )
        t_fill = _round_r(spec.te_ms * 1e-3 - te_min, r)
    te_actual = te_min + t_fill

    seq = pp.Sequence(system=opts)
    seq.add_block(rf, gz, pp.make_delay(t_exc))
    pre_t, pre_a = _prewinder(pre_area_x, g_ro, t_pre, gmax, smax, r)
    ry, ay = _trap_in(pre_area_y, t_pre, gmax, smax, r)
    gzr.delay = 0.0
    seq.add_block(
        _ext(pp, "x", np.asarray(pre_t) + t_fill, pre_a, opts),
        _ext(pp, "y", [0, ry, t_pre - ry, t_pre], [0, ay, ay, 0], opts),
        gzr,
        pp.make_delay(t_pre + t_fill),
    )
    if 2 * t_ramp <= t_tr + _EPS:
        tr_t = [0.0, t_ramp, t_tr - t_ramp, t_tr] if t_tr - 2 * t_ramp > _EPS else [0.0, t_ramp, t_tr]
        shape = [1.0, 0.0, 0.0, -1.0] if len(tr_t) == 4 else [1.0, 0.0, -1.0]
    else:  # cannot reverse within the slew limit: straight line (over-limit target)
        tr_t, shape = [0.0, t_tr], [1.0, -1.0]
    if t_b <= t_tr + _EPS:
        b0 = math.floor((t_tr - t_b) / 2 / r + 1e-6) * r
        bl_t = [b0, b0 + t_b / 2, b0 + t_b]
        bl_amp = 2 * blip_area / t_b
    else:
        half = math.floor(t_tr / 2 / r + 1e-6) * r
        bl_t = [0.0, half, t_tr]
        bl_amp = 2 * blip_area / t_tr
    sign = 1.0
    for j in range(n):
        adc = pp.make_adc(num_samples=n, dwell=dwell, delay=0.0, system=opts)
        seq.add_block(_ext(pp, "x", [0.0, t_adc], [sign * g_ro, sign * g_ro], opts), adc)
        if j < n - 1:
            seq.add_block(
                _ext(pp, "x", tr_t, [sign * g_ro * s for s in shape], opts),
                _ext(pp, "y", bl_t, [0.0, bl_amp, 0.0], opts),
                pp.make_delay(t_tr),
            )
            sign = -sign
    seq.add_block(_ext(pp, "x", [0.0, t_ramp], [sign * g_ro, 0.0], opts))
    _common_definitions(seq, spec)
    seq.set_definition("TE", float(te_actual))
    seq.set_definition("EchoSpacing", float(esp))
    return seq


# ---------------------------------------------------------------------------------------------- API
def build(spec: BaseSpec, warn: bool = True):
    """Build the pypulseq ``Sequence`` of a spec.  Warns (:class:`SpecLimitWarning`) when the ideal
    waveforms exceed the spec's system limits; raises :class:`InputError` when the spec is infeasible
    (TE too short, TR too short, pieces that do not fit)."""
    with quiet():
        if isinstance(spec, GreSpec):
            seq = _build_gre(spec)
        elif isinstance(spec, EpiSpec):
            seq = _build_epi(spec)
        else:
            raise InputError(f"unknown spec type {type(spec).__name__}")
    if warn:
        viol = check_ir_limits(from_pypulseq(seq), spec.system)
        if viol:
            worst = max(viol, key=lambda v: v.value / v.limit)
            warnings.warn(
                f"{spec.name}: ideal waveforms exceed the system limits in {len(viol)} place(s); worst: "
                f"{worst.rule} {worst.axis or ''} {worst.value:.4g} > {worst.limit:.4g} {worst.unit} (block {worst.block})",
                SpecLimitWarning,
                stacklevel=2,
            )
    return seq


def build_ir(spec: BaseSpec, **kwargs):
    """Build a spec in memory and return its :class:`SequenceIR` (``source`` = the built Sequence).

    The IR is read back from the written bytes, so it is exactly what the golden ``.seq`` holds.
    """
    kwargs.pop("require_signature", None)  # built in memory: always signed
    data = seq_bytes(build(spec, warn=False))
    fd, tmp = tempfile.mkstemp(suffix=".seq")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        seq, _ = read_pypulseq(tmp)
    finally:
        os.unlink(tmp)
    ir = from_pypulseq(seq, **kwargs)
    ir.meta["spec_name"] = spec.name
    return ir


def build_to_file(spec: BaseSpec, out: str | Path, force: bool = False, version: str | None = None) -> Path:
    """Build ``spec`` and write the signed ``.seq`` atomically (refuses to overwrite without ``force``): Pulseq
    1.5.0, or format ``version`` (:func:`dtoc.seq.write.seq_bytes_of`: refused by name where it cannot state
    the sequence, read back before it is written)."""
    from dtoc.util.atomic import atomic_write_bytes, check_output_path

    check_output_path(out, force)
    if version is None:
        return atomic_write_bytes(out, seq_bytes(build(spec)), force=force)
    from dtoc.seq.write import seq_bytes_of

    return atomic_write_bytes(out, seq_bytes_of(build_ir(spec), version=version), force=force)


__all__ = ["build", "build_ir", "build_to_file", "seq_bytes", "SpecLimitWarning", "representable_amplitudes"]
