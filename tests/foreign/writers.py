"""pypulseq scripts of our own, in the style of the pypulseq examples users start from (not copied from them):
a 2D spoiled GRE and a single-shot 2D EPI, each returning the signed ``.seq`` bytes.

What makes them "foreign" to dtoc: no FOV/matrix/limit definitions, RF made with the writers' default
``use`` (undefined), the usual k-space layout of pypulseq scripts (phase encodes ``(k - N/2) dk``, readout
centre at sample N/2), and an oblique-free 2D slice on z.
"""

from __future__ import annotations

import math

import numpy as np


def _system(pp):
    return pp.Opts(
        max_grad=32,
        grad_unit="mT/m",
        max_slew=130,
        slew_unit="T/m/s",
        rf_ringdown_time=20e-6,
        rf_dead_time=100e-6,
        adc_dead_time=10e-6,
    )


def _bytes(seq) -> bytes:
    import os
    import tempfile

    from dtoc.seq.pulseq import quiet

    with tempfile.TemporaryDirectory() as d:
        p = os.path.join(d, "x.seq")
        with quiet():
            seq.write(p)
        with open(p, "rb") as f:
            return f.read()


def gre(n: int = 32, fov: float = 0.22, slice_thickness: float = 5e-3, tr: float = 12e-3, te: float = 5e-3) -> bytes:
    """Spoiled 2D GRE, n x n, RF spoiling 117 deg, readout on x, phase on y, slice on z."""
    import pypulseq as pp

    sys = _system(pp)
    seq = pp.Sequence(sys)
    rf, gz, gzr = pp.make_sinc_pulse(
        flip_angle=math.radians(10),
        duration=2e-3,
        slice_thickness=slice_thickness,
        apodization=0.5,
        time_bw_product=4,
        system=sys,
        return_gz=True,
        delay=sys.rf_dead_time,
    )
    dk = 1 / fov
    gx = pp.make_trapezoid("x", flat_area=n * dk, flat_time=3.2e-3, system=sys)
    adc = pp.make_adc(n, duration=gx.flat_time, delay=gx.rise_time, system=sys)
    gxpre = pp.make_trapezoid("x", area=-gx.area / 2, duration=1e-3, system=sys)
    spoil = pp.make_trapezoid("x", area=2 * n * dk, system=sys)
    gzspoil = pp.make_trapezoid("z", area=4 / slice_thickness, system=sys)
    pe_areas = (np.arange(n) - n / 2) * dk
    te_fill = te - pp.calc_duration(gxpre) - gz.fall_time - gz.flat_time / 2 - pp.calc_duration(gx) / 2
    te_fill = math.ceil(te_fill / sys.grad_raster_time) * sys.grad_raster_time
    tr_fill = (
        tr
        - pp.calc_duration(gz)
        - pp.calc_duration(gxpre)
        - pp.calc_duration(gx)
        - pp.calc_duration(spoil, gzspoil)
        - te_fill
    )
    tr_fill = math.ceil(tr_fill / sys.grad_raster_time) * sys.grad_raster_time
    phase = 0.0
    inc = 0.0
    for i in range(n):
        rf.phase_offset = math.radians(phase)
        adc.phase_offset = math.radians(phase)
        inc = (inc + 117) % 360
        phase = (phase + inc) % 360
        seq.add_block(rf, gz)
        gy = pp.make_trapezoid("y", area=pe_areas[i], duration=1e-3, system=sys)
        seq.add_block(gxpre, gy, gzr)
        seq.add_block(pp.make_delay(te_fill))
        seq.add_block(gx, adc)
        gyr = pp.make_trapezoid("y", area=-pe_areas[i], duration=1e-3, system=sys)
        seq.add_block(spoil, gyr, gzspoil)
        seq.add_block(pp.make_delay(tr_fill))
    return _bytes(seq)


def epi(n: int = 32, fov: float = 0.22, slice_thickness: float = 3e-3) -> bytes:
    """Single-shot 2D EPI, n x n, blipped, readout on x (flat-top sampling), phase on y, slice on z."""
    import pypulseq as pp

    sys = _system(pp)
    seq = pp.Sequence(sys)
    rf, gz, gzr = pp.make_sinc_pulse(
        flip_angle=math.radians(90),
        duration=3e-3,
        slice_thickness=slice_thickness,
        apodization=0.5,
        time_bw_product=4,
        system=sys,
        return_gz=True,
        delay=sys.rf_dead_time,
    )
    dk = 1 / fov
    dwell = 4e-6
    ro_time = n * dwell
    blip_dur = math.ceil(2 * math.sqrt(dk / sys.max_slew) / 10e-6 / 2) * 10e-6 * 2
    gy_blip = pp.make_trapezoid("y", area=dk, duration=blip_dur, system=sys)
    gx = pp.make_trapezoid("x", flat_area=n * dk, flat_time=math.ceil(ro_time / 10e-6) * 10e-6, system=sys)
    adc = pp.make_adc(n, duration=ro_time, delay=gx.rise_time + (gx.flat_time - ro_time) / 2, system=sys)
    gxpre = pp.make_trapezoid("x", area=-gx.area / 2, system=sys)
    gypre = pp.make_trapezoid("y", area=-n / 2 * dk, system=sys)
    gxpre, gypre = pp.align(right=[gxpre], left=[gypre])[0], gypre
    seq.add_block(rf, gz)
    seq.add_block(gxpre, gypre, gzr)
    for i in range(n):
        seq.add_block(gx, adc)
        if i < n - 1:
            seq.add_block(gy_blip)
        gx = pp.scale_grad(gx, -1)
    seq.add_block(pp.make_delay(1e-3))
    return _bytes(seq)
