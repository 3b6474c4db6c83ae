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
        rf_ringdown_time=30e-6,
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


def radial(n: int = 64, spokes: int = 32, fov: float = 0.22, tr: float = 8e-3) -> bytes:
    """2D radial GRE: ``spokes`` full diameters over 180 deg, ``n`` samples each, golden-free uniform angles."""
    import pypulseq as pp

    sys = _system(pp)
    seq = pp.Sequence(sys)
    rf, gz, gzr = pp.make_sinc_pulse(
        flip_angle=math.radians(10),
        duration=1.5e-3,
        slice_thickness=5e-3,
        apodization=0.5,
        time_bw_product=4,
        system=sys,
        return_gz=True,
        delay=sys.rf_dead_time,
    )
    dk = 1 / fov
    g_ro = pp.make_trapezoid("x", flat_area=n * dk, flat_time=2.56e-3, system=sys)
    adc = pp.make_adc(n, duration=g_ro.flat_time, delay=g_ro.rise_time, system=sys)
    g_pre = pp.make_trapezoid("x", area=-g_ro.area / 2, duration=1e-3, system=sys)
    g_sp = pp.make_trapezoid("x", area=2 * n * dk, system=sys)
    fill = tr - pp.calc_duration(gz) - pp.calc_duration(g_pre, gzr) - pp.calc_duration(g_ro) - pp.calc_duration(g_sp)
    fill = math.ceil(fill / sys.grad_raster_time) * sys.grad_raster_time
    for i in range(spokes):
        phi = math.pi * i / spokes
        seq.add_block(rf, gz)
        seq.add_block(*pp.rotate(g_pre, angle=phi, axis="z"), gzr)
        seq.add_block(*pp.rotate(g_ro, adc, angle=phi, axis="z"))
        seq.add_block(*pp.rotate(g_sp, angle=phi, axis="z"))
        seq.add_block(pp.make_delay(fill))
    return _bytes(seq)


def spiral(interleaves: int = 1, fov: float = 0.22, n: int = 48, tr: float = 30e-3) -> bytes:
    """2D constant-density Archimedean spiral out (``interleaves`` shots), arbitrary gradients, 4 us ADC dwell,
    rewound to zero at the end of each shot. The waveform is built on the 10 us raster within 30 mT/m and
    120 T/m/s by a simple slew-limited integration (not optimal; users bring far better ones)."""
    import pypulseq as pp

    sys = _system(pp)
    seq = pp.Sequence(sys)
    rf, gz, gzr = pp.make_sinc_pulse(
        flip_angle=math.radians(20),
        duration=1.5e-3,
        slice_thickness=5e-3,
        apodization=0.5,
        time_bw_product=4,
        system=sys,
        return_gz=True,
        delay=sys.rf_dead_time,
    )
    dt = sys.grad_raster_time
    kmax = n / (2 * fov)  # 1/m
    turns = n / (2 * interleaves)
    gam = sys.gamma  # Hz/T
    gmax, smax = 30e-3 * gam, 120 * gam  # Hz/m, Hz/m/s
    # k(theta) = kmax theta / (2 pi turns); advance theta as fast as gmax and smax allow
    th, kx, ky = 0.0, [0.0], [0.0]
    g_prev = np.zeros(2)
    while th < 2 * math.pi * turns:
        r = kmax * th / (2 * math.pi * turns)
        dr = kmax / (2 * math.pi * turns)
        speed = math.hypot(dr, r)  # |dk/dtheta|
        w = min(gmax / max(speed, 1e-9), math.sqrt(smax / max(speed, 1e-9) / max(th, 1.0)) * 0.95)
        th_new = th + w * dt
        r_new = kmax * th_new / (2 * math.pi * turns)
        k_new = np.array([r_new * math.cos(th_new), r_new * math.sin(th_new)])
        g = (k_new - np.array([kx[-1], ky[-1]])) / dt
        if np.linalg.norm(g - g_prev) > smax * dt:  # keep the slew: shorter step
            w *= 0.5
            th_new = th + w * dt
            r_new = kmax * th_new / (2 * math.pi * turns)
            k_new = np.array([r_new * math.cos(th_new), r_new * math.sin(th_new)])
            g = (k_new - np.array([kx[-1], ky[-1]])) / dt
        kx.append(k_new[0])
        ky.append(k_new[1])
        g_prev = g
        th = th_new
    gx = np.diff(kx) / dt
    gy = np.diff(ky) / dt
    # ramp down to zero within the slew limit
    while abs(gx[-1]) > 0 or abs(gy[-1]) > 0:
        step = smax * dt * 0.9
        gx = np.append(gx, np.sign(gx[-1]) * max(abs(gx[-1]) - step, 0.0))
        gy = np.append(gy, np.sign(gy[-1]) * max(abs(gy[-1]) - step, 0.0))
    gx = np.concatenate([[0.0], gx, [0.0]])
    gy = np.concatenate([[0.0], gy, [0.0]])
    seq.set_definition("FOV", [fov, fov, 5e-3])  # as users' spiral scripts do: the image FOV is not in the path
    n_adc = int((len(gx) * dt - 2 * sys.adc_dead_time) / 4e-6) // 4 * 4
    for shot in range(interleaves):
        phi = 2 * math.pi * shot / interleaves
        c, s = math.cos(phi), math.sin(phi)
        gxs = pp.make_arbitrary_grad("x", c * gx - s * gy, system=sys, first=0, last=0)
        gys = pp.make_arbitrary_grad("y", s * gx + c * gy, system=sys, first=0, last=0)
        adc = pp.make_adc(n_adc, dwell=4e-6, delay=sys.adc_dead_time, system=sys)
        seq.add_block(rf, gz)
        seq.add_block(gzr)
        seq.add_block(gxs, gys, adc)
        spoil = pp.make_trapezoid("z", area=4 / 5e-3, system=sys)
        seq.add_block(spoil)
        fill = tr - seq.duration()[0] + shot * tr
        seq.add_block(pp.make_delay(max(math.ceil(fill / dt) * dt, dt)))
    return _bytes(seq)


def _sinc(pp, sys, flip_deg, thickness, duration=2e-3, use=None, phase_deg=0.0):
    kw = {} if use is None else {"use": use}
    return pp.make_sinc_pulse(
        flip_angle=math.radians(flip_deg),
        duration=duration,
        slice_thickness=thickness,
        apodization=0.5,
        time_bw_product=4,
        system=sys,
        return_gz=True,
        delay=sys.rf_dead_time,
        phase_offset=math.radians(phase_deg),
        **kw,
    )


def _fill(pp, sys, t):
    return pp.make_delay(max(math.ceil(t / sys.block_duration_raster) * sys.block_duration_raster, 10e-6))


def se_epi(n: int = 32, fov: float = 0.22, te: float = 60e-3, ramp_sampling: bool = False) -> bytes:
    """Spin-echo EPI: 90 (use undefined) - 180 (use 'refocusing', as users set it) with crushers, then a
    blipped EPI readout; ``ramp_sampling``: the ADC also runs on the ramps (non-uniform k along x)."""
    import pypulseq as pp

    sys = _system(pp)
    seq = pp.Sequence(sys)
    thk = 4e-3
    rf, gz, gzr = _sinc(pp, sys, 90, thk, 3e-3)
    rf180, gz180, _ = _sinc(pp, sys, 180, thk, 3e-3, use="refocusing", phase_deg=90)
    crush = pp.make_trapezoid("z", area=4 / thk, duration=1.5e-3, system=sys)
    dk = 1 / fov
    if ramp_sampling:
        gx = pp.make_trapezoid("x", area=n * dk, system=sys)  # triangle-ish: sample everything
        dur = pp.calc_duration(gx)
        dwell = math.floor((dur - 2 * sys.adc_dead_time) / n / 1e-7) * 1e-7
        adc = pp.make_adc(n, dwell=dwell, delay=math.floor((dur - n * dwell) / 2 / 1e-6) * 1e-6, system=sys)
        # the k-space the samples reach: symmetric by construction, not uniform in k
    else:
        flat = math.ceil((n * 4e-6 + 10e-6) / 20e-6) * 20e-6  # ADC centred on the flat top, on the 1 us raster
        gx = pp.make_trapezoid("x", flat_area=n * dk, flat_time=flat, system=sys)
        adc = pp.make_adc(n, duration=n * 4e-6, delay=gx.rise_time + (flat - n * 4e-6) / 2, system=sys)
    blip = pp.make_trapezoid("y", area=dk, system=sys)
    gxpre = pp.make_trapezoid("x", area=gx.area / 2, system=sys)  # + before the 180: the 180 negates it
    gypre = pp.make_trapezoid("y", area=(n / 2) * dk, system=sys)
    seq.add_block(rf, gz)
    seq.add_block(gzr)
    seq.add_block(gxpre, gypre)
    t_echo_train = n * (pp.calc_duration(gx) + pp.calc_duration(blip))
    t_pre = pp.calc_duration(gz) / 2 + pp.calc_duration(gzr) + pp.calc_duration(gxpre, gypre)
    d1 = te / 2 - t_pre - pp.calc_duration(crush) - pp.calc_duration(gz180) / 2
    seq.add_block(_fill(pp, sys, d1))
    seq.add_block(crush)
    seq.add_block(rf180, gz180)
    seq.add_block(crush)
    d2 = te / 2 - pp.calc_duration(gz180) / 2 - pp.calc_duration(crush) - t_echo_train / 2
    seq.add_block(_fill(pp, sys, d2))
    for i in range(n):
        seq.add_block(gx, adc)
        if i < n - 1:
            seq.add_block(blip)
        gx = pp.scale_grad(gx, -1)
    seq.add_block(pp.make_delay(1e-3))
    return _bytes(seq)


def tse(n: int = 32, etl: int = 8, fov: float = 0.22, esp: float = 10e-3, single_shot: bool = False) -> bytes:
    """Turbo spin echo (CPMG: 90x, 180y trains with use 'refocusing'), linear phase order, ``etl`` echoes per
    shot; ``single_shot``: a HASTE-like single shot of n/2 + 4 echoes (half Fourier)."""
    import pypulseq as pp

    sys = _system(pp)
    seq = pp.Sequence(sys)
    thk = 5e-3
    rf, gz, gzr = _sinc(pp, sys, 90, thk, 2e-3)
    rf180, gz180, _ = _sinc(pp, sys, 180, thk, 2e-3, use="refocusing", phase_deg=90)
    dk = 1 / fov
    gx = pp.make_trapezoid("x", flat_area=n * dk, flat_time=2.56e-3, system=sys)
    adc = pp.make_adc(n, duration=gx.flat_time, delay=gx.rise_time, system=sys)
    gxpre = pp.make_trapezoid("x", area=gx.area / 2, duration=1e-3, system=sys)
    crush = pp.make_trapezoid("z", area=2 / thk, duration=0.8e-3, system=sys)
    lines = np.arange(n) - n // 2
    if single_shot:
        lines = np.arange(-4, n // 2)
        shots = [lines]
    else:
        shots = [lines[s :: n // etl] for s in range(n // etl)]
    for shot in shots:
        seq.add_block(rf, gz)
        seq.add_block(gxpre, gzr)
        seq.add_block(
            _fill(
                pp,
                sys,
                esp / 2
                - pp.calc_duration(gz) / 2
                - pp.calc_duration(gxpre, gzr)
                - pp.calc_duration(gz180) / 2
                - pp.calc_duration(crush),
            )
        )
        for j in shot:
            gy = pp.make_trapezoid("y", area=j * dk, duration=0.8e-3, system=sys)
            gyr = pp.make_trapezoid("y", area=-j * dk, duration=0.8e-3, system=sys)
            seq.add_block(crush)
            seq.add_block(rf180, gz180)
            seq.add_block(crush)
            seq.add_block(gy)
            fill = (esp - pp.calc_duration(gz180) - 2 * pp.calc_duration(crush) - 2 * 0.8e-3 - pp.calc_duration(gx)) / 2
            seq.add_block(_fill(pp, sys, fill))
            seq.add_block(gx, adc)
            seq.add_block(_fill(pp, sys, fill))
            seq.add_block(gyr)
        seq.add_block(pp.make_delay(20e-3))
    return _bytes(seq)


def ute(spokes: int = 32, n: int = 64, fov: float = 0.22) -> bytes:
    """2D UTE-like: a short hard pulse, then centre-out half spokes read from the start of the ramp
    (the ADC starts with the gradient: ramp samples, non-Cartesian)."""
    import pypulseq as pp

    sys = _system(pp)
    seq = pp.Sequence(sys)
    rf = pp.make_block_pulse(flip_angle=math.radians(8), duration=80e-6, delay=sys.rf_dead_time, system=sys)
    dk = 1 / fov
    g = pp.make_trapezoid("x", flat_area=n / 2 * dk, flat_time=1.28e-3, system=sys)
    dwell = math.floor((g.rise_time + g.flat_time) / n / 1e-7) * 1e-7
    adc = pp.make_adc(n, dwell=dwell, delay=sys.adc_dead_time, system=sys)
    sp = pp.make_trapezoid("z", area=8 / 5e-3, system=sys)
    for i in range(spokes):
        phi = 2 * math.pi * i / spokes
        seq.add_block(rf)
        seq.add_block(*pp.rotate(g, adc, angle=phi, axis="z"))
        seq.add_block(sp)
        seq.add_block(pp.make_delay(3e-3))
    return _bytes(seq)


def gre3d(n: int = 16, nz: int = 8, fov: float = 0.22, fovz: float = 0.08, tr: float = 10e-3) -> bytes:
    """3D spoiled GRE, slab-selective, phase encodes on y and z (k-space term only: no 2D grid)."""
    import pypulseq as pp

    sys = _system(pp)
    seq = pp.Sequence(sys)
    rf, gz, gzr = _sinc(pp, sys, 8, fovz, 2e-3)
    dk, dkz = 1 / fov, 1 / fovz
    gx = pp.make_trapezoid("x", flat_area=n * dk, flat_time=1.6e-3, system=sys)
    adc = pp.make_adc(n, duration=gx.flat_time, delay=gx.rise_time, system=sys)
    gxpre = pp.make_trapezoid("x", area=-gx.area / 2, duration=1.2e-3, system=sys)
    spoil = pp.make_trapezoid("x", area=2 * n * dk, system=sys)
    for kz in np.arange(nz) - nz // 2:
        for ky in np.arange(n) - n // 2:
            gy = pp.make_trapezoid("y", area=ky * dk, duration=1.2e-3, system=sys)
            gzp = pp.make_trapezoid("z", area=kz * dkz + gzr.area, duration=1.2e-3, system=sys)
            seq.add_block(rf, gz)
            seq.add_block(gxpre, gy, gzp)
            seq.add_block(gx, adc)
            gyr = pp.make_trapezoid("y", area=-ky * dk, duration=1.2e-3, system=sys)
            gzr2 = pp.make_trapezoid("z", area=-kz * dkz, duration=1.2e-3, system=sys)
            seq.add_block(spoil, gyr, gzr2)
            seq.add_block(
                _fill(pp, sys, tr - 2e-3 - sys.rf_dead_time - 2.4e-3 - pp.calc_duration(gx) - pp.calc_duration(spoil))
            )
    return _bytes(seq)


def gre_multislice_labels(n: int = 16, slices: int = 3, fov: float = 0.22, gap: float = 6e-3) -> bytes:
    """Multi-slice GRE (slice frequency offsets), LIN/SLC labels and a soft delay (TE) in every repetition:
    the 1.5 extensions a user's protocol carries."""
    import pypulseq as pp

    sys = _system(pp)
    seq = pp.Sequence(sys)
    thk = 3e-3
    rf, gz, gzr = _sinc(pp, sys, 15, thk, 2e-3)
    dk = 1 / fov
    gx = pp.make_trapezoid("x", flat_area=n * dk, flat_time=1.6e-3, system=sys)
    adc = pp.make_adc(n, duration=gx.flat_time, delay=gx.rise_time, system=sys)
    gxpre = pp.make_trapezoid("x", area=-gx.area / 2, duration=1e-3, system=sys)
    spoil = pp.make_trapezoid("z", area=4 / thk, system=sys)
    te_delay = pp.make_soft_delay(hint="TE", numID=0, offset=0, factor=1, default_duration=1e-3)
    for i in range(n):
        for s in range(slices):
            rf.freq_offset = gz.amplitude * (s - slices // 2) * gap
            gy = pp.make_trapezoid("y", area=(i - n // 2) * dk, duration=1e-3, system=sys)
            seq.add_block(rf, gz)
            seq.add_block(gxpre, gy, gzr)
            seq.add_block(te_delay)
            seq.add_block(gx, adc, pp.make_label("LIN", "SET", i), pp.make_label("SLC", "SET", s))
            gyr = pp.make_trapezoid("y", area=-(i - n // 2) * dk, duration=1e-3, system=sys)
            seq.add_block(spoil, gyr)
            seq.add_block(pp.make_delay(2e-3))
    return _bytes(seq)


def mprage(
    n: int = 32,
    nz: int = 4,
    fov: float = 0.22,
    fovz: float = 0.16,
    tr: float = 8e-3,
    ti: float = 0.4,
    tr_shot: float = 1.0,
    shots: int | None = None,
) -> bytes:
    """3D MPRAGE-like: per shot (one partition kz) an adiabatic-like inversion (hard 180, use 'inversion'),
    TI, then a train of ``n`` spoiled GRE readouts (phase y, partition z), then the recovery delay to
    ``tr_shot``.  ``shots`` (default ``nz``) sets the duration: shot s encodes partition s mod nz; a long
    protocol is many shots.  RF of the train with use undefined, as users write it."""
    import pypulseq as pp

    sys = _system(pp)
    seq = pp.Sequence(sys)
    inv = pp.make_block_pulse(flip_angle=math.pi, duration=1e-3, system=sys, delay=sys.rf_dead_time, use="inversion")
    inv_spoil = pp.make_trapezoid("z", area=8 / fovz * 4, duration=3e-3, system=sys)
    rf, gz, gzr = _sinc(pp, sys, 8, fovz, 1.2e-3)
    dk, dkz = 1 / fov, 1 / fovz
    gx = pp.make_trapezoid("x", flat_area=n * dk, flat_time=1.28e-3, system=sys)
    adc = pp.make_adc(n, duration=gx.flat_time, delay=gx.rise_time, system=sys)
    gxpre = pp.make_trapezoid("x", area=-gx.area / 2, duration=1.0e-3, system=sys)
    spoil = pp.make_trapezoid("x", area=2 * n * dk, system=sys)
    t_rf = pp.calc_duration(rf, gz)
    t_inv = pp.calc_duration(inv) + pp.calc_duration(inv_spoil)
    fill_tr = tr - t_rf - 2.0e-3 - pp.calc_duration(gx) - pp.calc_duration(spoil)
    fill_ti = ti - t_inv - (n // 2) * tr
    fill_shot = tr_shot - t_inv - fill_ti - n * tr
    if min(fill_tr, fill_ti, fill_shot) < 0:
        raise ValueError("mprage: timing does not fit (tr, ti or tr_shot too short)")
    for s in range(nz if shots is None else shots):
        kz = s % nz - nz // 2
        seq.add_block(inv)
        seq.add_block(inv_spoil)
        seq.add_block(_fill(pp, sys, fill_ti))
        for ky in np.arange(n) - n // 2:
            gy = pp.make_trapezoid("y", area=ky * dk, duration=1.0e-3, system=sys)
            gzp = pp.make_trapezoid("z", area=kz * dkz + gzr.area, duration=1.0e-3, system=sys)
            seq.add_block(rf, gz)
            seq.add_block(gxpre, gy, gzp)
            seq.add_block(gx, adc)
            gyr = pp.make_trapezoid("y", area=-ky * dk, duration=1.0e-3, system=sys)
            gzr2 = pp.make_trapezoid("z", area=-kz * dkz, duration=1.0e-3, system=sys)
            seq.add_block(spoil, gyr, gzr2)
            seq.add_block(_fill(pp, sys, fill_tr))
        seq.add_block(_fill(pp, sys, fill_shot))
    return _bytes(seq)
