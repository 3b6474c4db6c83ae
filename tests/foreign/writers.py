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


def radial(
    n: int = 64, spokes: int = 32, fov: float = 0.22, tr: float = 8e-3, rotation_extension: bool = False
) -> bytes:
    """2D radial GRE: ``spokes`` full diameters over 180 deg, ``n`` samples each, golden-free uniform angles.
    ``rotation_extension``: every spoke is written along x and turned by the 1.5.1 rotation extension (format
    1.5.1, one quaternion per spoke on its prephaser, readout and spoiler blocks) instead of pre-rotated."""
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
    rotated: dict[int, float] = {}  # 1-based block number -> angle about z
    for i in range(spokes):
        phi = math.pi * i / spokes
        seq.add_block(rf, gz)
        if rotation_extension:
            seq.add_block(g_pre, gzr)
            seq.add_block(g_ro, adc)
            seq.add_block(g_sp)
            rotated.update({5 * i + 2: phi, 5 * i + 3: phi, 5 * i + 4: phi})
        else:
            seq.add_block(*pp.rotate(g_pre, angle=phi, axis="z"), gzr)
            seq.add_block(*pp.rotate(g_ro, adc, angle=phi, axis="z"))
            seq.add_block(*pp.rotate(g_sp, angle=phi, axis="z"))
        seq.add_block(pp.make_delay(fill))
    data = _bytes(seq)
    return _with_rotations(data, rotated) if rotation_extension else data


def _sign(body: bytes) -> bytes:
    """``body`` with a Pulseq md5 [SIGNATURE] (the hash of the bytes before the newline preceding it)."""
    import hashlib

    body = body.rstrip(b"\n") + b"\n"
    return body + b"\n[SIGNATURE]\nType md5\nHash " + hashlib.md5(body).hexdigest().encode() + b"\n"


def _unsigned(data: bytes) -> bytes:
    i = data.find(b"\n[SIGNATURE]")
    return data if i < 0 else data[: i + 1]


def _set_version(text: bytes, version: str) -> bytes:
    import re

    ma, mi, rev = version.split(".")
    return re.sub(
        rb"\[VERSION\]\nmajor \d+\nminor \d+\nrevision \d+",
        f"[VERSION]\nmajor {ma}\nminor {mi}\nrevision {rev}".encode(),
        text,
    )


def _with_rotations(data: bytes, rotated: dict[int, float]) -> bytes:
    """A pypulseq 1.5.0 file without extensions, with ``rotated`` blocks turned about z (format 1.5.1)."""
    quats = {b: (math.cos(phi / 2), 0.0, 0.0, math.sin(phi / 2)) for b, phi in rotated.items()}
    return with_extension(data, "ROTATIONS", quats)


def with_extension(data: bytes, kind: str, per_block: dict[int, tuple]) -> bytes:
    """A pypulseq 1.5.0 file without extensions, with the 1.5.1 extension ``kind`` (ROTATIONS: quaternions;
    RF_SHIMS: (num_chan, mag1, phase1, ...)) on the given 1-based blocks; labelled format 1.5.1, signed."""
    lines = _set_version(_unsigned(data), "1.5.1").decode().split("\n")
    b0 = lines.index("[BLOCKS]") + 1
    obj: dict[tuple, int] = {}
    for v in per_block.values():
        obj.setdefault(tuple(v), len(obj) + 1)
    j = b0
    while lines[j].strip():
        t = lines[j].split()
        if int(t[0]) in per_block:
            t[7] = str(obj[tuple(per_block[int(t[0])])])  # one list entry per object, same id
        lines[j] = " ".join(t)
        j += 1
    fmt = lambda v: str(int(v)) if float(v).is_integer() else f"{v:.15g}"  # noqa: E731
    ext = ["[EXTENSIONS]"] + [f"{i} 1 {i} 0" for i in obj.values()] + ["", f"extension {kind} 1"]
    ext += [" ".join([str(i), *map(fmt, v)]) for v, i in obj.items()] + [""]
    k = lines.index("[SHAPES]")
    lines[k:k] = ext
    return _sign("\n".join(lines).encode())


def as_version(data: bytes, version: str) -> bytes:
    """A pypulseq 1.5.0 file rewritten in format ``version`` as the writers of that version lay it out:
    1.4.1 by pypulseq's own 1.4.1 writer (what pypulseq 1.4 example scripts wrote), 1.4.0 the same text
    labelled 1.4.0, 1.3.x / 1.2.x from that text by the older layouts (block column 2 a [DELAYS] id holding
    the block duration, no RF/gradient time shapes, every shape run-length compressed, 1.2.x without the
    block extension column).  Only default-raster RF and arbitrary gradients can go below 1.4."""
    import os
    import tempfile

    import pypulseq as pp

    from dtoc.seq.pulseq import quiet

    with tempfile.TemporaryDirectory() as d:
        src, dst = os.path.join(d, "a.seq"), os.path.join(d, "b.seq")
        with open(src, "wb") as f:
            f.write(data)
        seq = pp.Sequence()
        with quiet():
            seq.read(src)
            seq.write(dst, create_signature=False, v141_compat=True)
        with open(dst, "rb") as f:
            text = f.read()
    if version == "1.4.1":
        return _sign(text)
    if version == "1.4.0":
        return _sign(_set_version(text, "1.4.0"))
    return _sign(_set_version(_old_layout(text.decode(), version), version))


def _compress(w) -> list[str]:
    """Pulseq shape compression: run-length encoded derivative (repeats of a value: the value twice, then the
    count of further repeats)."""
    d = np.diff(np.concatenate([[0.0], np.asarray(w, dtype=np.float64)]))
    d = np.round(d, 9)
    out: list[str] = []
    i = 0
    while i < len(d):
        j = i
        while j + 1 < len(d) and d[j + 1] == d[i]:
            j += 1
        run = j - i + 1
        if run >= 2:
            out += [f"{d[i]:.9g}", f"{d[i]:.9g}", str(run - 2)]
        else:
            out.append(f"{d[i]:.9g}")
        i = j + 1
    return out


def _decompress(data: list[float], num: int) -> np.ndarray:
    if len(data) == num:
        return np.asarray(data)
    out: list[float] = []
    k = 0
    while k < len(data):
        if k + 2 < len(data) and data[k] == data[k + 1]:
            out += [data[k]] * (int(data[k + 2]) + 2)
            k += 3
        else:
            out.append(data[k])
            k += 1
    return np.cumsum(out)


def _old_layout(text: str, version: str) -> bytes:
    """1.4.1 text -> the 1.3.x / 1.2.x layout (see :func:`as_version`)."""
    sec = None
    out: list[str] = []
    delays: dict[int, int] = {}
    shape_lines: list[str] = []
    raster_us = 10
    for line in text.split("\n"):
        s = line.strip()
        if s.startswith("BlockDurationRaster"):
            raster_us = round(float(s.split()[1]) * 1e6)
        if s.startswith("["):
            sec = s
            if sec == "[SHAPES]":
                continue
            out.append(line)
            continue
        if sec == "[SHAPES]":
            shape_lines.append(s)
            continue
        if not s or s.startswith("#"):
            out.append(line)
            continue
        t = s.split()
        if sec == "[BLOCKS]":
            dur_us = int(t[1]) * raster_us
            did = delays.setdefault(dur_us, len(delays) + 1)
            t[1] = str(did)
            if version.startswith("1.2"):
                t = t[:7]
        elif sec == "[RF]":  # id amp mag phase time delay freq phase -> no time shape
            assert t[4] == "0", "only default-raster RF goes below 1.4"
            t = t[:4] + t[5:]
        elif sec == "[GRADIENTS]":  # id amp shape time delay -> no time shape
            assert t[3] == "0", "only default-raster arbitrary gradients go below 1.4"
            t = t[:3] + t[4:]
        out.append(" ".join(t))
    body = "\n".join(out).rstrip("\n").split("\n")
    body = [ln for ln in body if not ln.startswith(("TotalDuration", "AdcRasterTime", "BlockDurationRaster"))]
    body += ["", "[DELAYS]"] + [f"{i} {us}" for us, i in delays.items()] + ["", "[SHAPES]", ""]
    k = 0
    while k < len(shape_lines):
        if shape_lines[k].startswith("shape_id"):
            sid = shape_lines[k]
            num = int(shape_lines[k + 1].split()[1])
            k += 2
            data = []
            while k < len(shape_lines) and shape_lines[k] and not shape_lines[k].startswith("shape_id"):
                data.append(float(shape_lines[k]))
                k += 1
            body += [sid, f"num_samples {num}", *_compress(_decompress(data, num)), ""]
        else:
            k += 1
    return ("\n".join(body) + "\n").encode()


def spiral_140_ending_on_zero(n_spiral: int = 120, dwell: float = 4e-6) -> bytes:
    """A field-camera style 1.4.0 file written by hand in the 1.4.0 layout: a hard pulse, then a spiral-out
    arbitrary gradient on x and y (default raster, samples at raster centres, no first/last: 1.4.0 has none)
    whose last sample on both axes is exactly 0, an ADC over it, then an empty block. The waveform rises from
    and returns to 0 within the samples; the scanner plays no step at the spiral's end."""
    raster = 10e-6
    t = (np.arange(n_spiral) + 0.5) / n_spiral
    env = np.sin(np.pi * t) ** 2  # 0 -> 1 -> 0 envelope
    wx = env * np.cos(6 * np.pi * t)
    wy = env * np.sin(6 * np.pi * t)
    wx[-1] = wy[-1] = 0.0  # the last sample is exactly zero
    amp = 400000.0  # Hz/m (9.4 mT/m)
    sx, sy = wx / np.abs(wx).max(), wy / np.abs(wy).max()
    n_adc = int(round(n_spiral * raster / dwell))
    lines = [
        "# Pulseq sequence file", "# written by a 1.4.0-era exporter (hand-made test writer)", "",
        "[VERSION]", "major 1", "minor 4", "revision 0", "",
        "[DEFINITIONS]", "AdcRasterTime 1e-07", "BlockDurationRaster 1e-05", "GradientRasterTime 1e-05",
        "RadiofrequencyRasterTime 1e-06", "",
        "[BLOCKS]", "1 40 1 0 0 0 0 0", f"2 {n_spiral} 0 1 2 0 1 0", "3 100 0 0 0 0 0 0", "4 40 1 0 0 0 0 0",
        f"5 {n_spiral} 0 1 2 0 1 0", "6 100 0 0 0 0 0 0", "",
        "[RF]", "1 250 1 0 0 100 0 0", "",
        "[GRADIENTS]", f"1 {amp * np.abs(wx).max():.9g} 2 0 0", f"2 {amp * np.abs(wy).max():.9g} 3 0 0", "",
        "[ADC]", f"1 {n_adc} {dwell * 1e9:.0f} 0 0 0", "",
        "[SHAPES]", "",
        "shape_id 1", "num_samples 200", "1", "0", "0", "197", "",
        "shape_id 2", f"num_samples {n_spiral}", *(f"{v:.9g}" for v in sx), "",
        "shape_id 3", f"num_samples {n_spiral}", *(f"{v:.9g}" for v in sy), "",
    ]  # fmt: skip
    return _sign(("\n".join(lines) + "\n").encode())


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


def oversampled_151(n_raster: int = 40, version: str = "1.5.1") -> tuple[bytes, np.ndarray]:
    """A hand-written 1.5.1 file with an oversampled arbitrary gradient (time shape id -1: samples every half
    raster between the stated first and last) on x over an ADC, after a hard pulse. Returns (bytes, the
    played x gradient in Hz/m at every half raster of the gradient, edges included)."""
    m = np.arange(2 * n_raster + 1) / (2 * n_raster)
    played = 300000.0 * np.sin(np.pi * m) * (1 + 0.3 * np.cos(5 * np.pi * m))  # 0 at both ends
    amp = float(np.abs(played).max())
    inner = played[1:-1] / amp
    lines = [
        "[VERSION]", "major 1", "minor 5", f"revision {version.split('.')[2]}", "",
        "[DEFINITIONS]", "AdcRasterTime 1e-07", "BlockDurationRaster 1e-05", "GradientRasterTime 1e-05",
        "RadiofrequencyRasterTime 1e-06", "",
        "[BLOCKS]", "1 40 1 0 0 0 0 0", f"2 {n_raster} 0 1 0 0 1 0", "3 50 0 0 0 0 0 0", "",
        "[RF]", "1 250 1 2 0 100 100 0 0 0 0 e", "",
        "[GRADIENTS]", f"1 {amp:.12g} 0 0 3 -1 0", "",
        "[ADC]", f"1 {n_raster * 2} 5000 0 0 0 0 0 0", "",
        "[SHAPES]", "",
        "shape_id 1", "num_samples 200", "1", "0", "0", "197", "",
        "shape_id 2", "num_samples 200", "0", "0", "198", "",
        "shape_id 3", f"num_samples {len(inner)}", *(f"{v:.12g}" for v in inner), "",
    ]  # fmt: skip
    return _sign(("\n".join(lines) + "\n").encode()), played


def rotated_trapezoids_151() -> bytes:
    """A hand-written 1.5.1 file in the style of Pulseq's rotation demos: five ADC readouts on one x trapezoid,
    turned by 0, 45, 90, 45, 0 degrees about z with the rotation extension; no RF, hence no [SHAPES] section."""
    c, s = math.cos(math.pi / 8), math.sin(math.pi / 8)
    h = math.sqrt(0.5)
    lines = [
        "[VERSION]", "major 1", "minor 5", "revision 1", "",
        "[DEFINITIONS]", "AdcRasterTime 1e-07", "BlockDurationRaster 1e-05", "GradientRasterTime 1e-05",
        "RadiofrequencyRasterTime 1e-06", "RequiredExtensions ROTATIONS", "",
        "[BLOCKS]", "1 40 0 1 0 0 1 1", "2 40 0 1 0 0 1 2", "3 40 0 1 0 0 1 3", "4 40 0 1 0 0 1 2",
        "5 40 0 1 0 0 1 1", "",
        "[TRAP]", "1 100000 100 200 100 0", "",
        "[ADC]", "1 8 25000 100 0 0 0 0 0", "",
        "[EXTENSIONS]", "1 1 1 0", "2 1 2 0", "3 1 3 0", "",
        "extension ROTATIONS 1", "1 1 0 0 0", f"2 {c:.15g} 0 0 {s:.15g}", f"3 {h:.15g} 0 0 {h:.15g}", "",
    ]  # fmt: skip
    return _sign(("\n".join(lines) + "\n").encode())


def as_binary(data: bytes, sign: bool = True) -> bytes:
    """A pypulseq 1.5 text file (no extensions) in the binary format of the specification's "Binary files"
    section: header ``0x01 pulseq 0x02``, version, sections each with code ``0xFFFFFFFF_000000NN`` (int64,
    little-endian), times in ps, shapes float32, then the md5 signature section over the bytes before it."""
    import hashlib
    import struct

    sec: dict[str, list[list[str]]] = {}
    cur = None
    shapes: list[tuple[int, int, list[float]]] = []
    text = _unsigned(data).decode()
    for line in text.split("\n"):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        if s.startswith("["):
            cur = s
            sec[cur] = []
            continue
        if cur == "[SHAPES]":
            t = s.split()
            if t[0] == "shape_id":
                shapes.append((int(t[1]), 0, []))
            elif t[0] == "num_samples":
                shapes[-1] = (shapes[-1][0], int(t[1]), [])
            else:
                shapes[-1][2].append(float(s))
            continue
        sec[cur].append(s.split())
    ver = {t[0]: int(t[1]) for t in sec["[VERSION]"]}

    def code(n: int) -> bytes:
        return struct.pack("<Q", (0xFFFFFFFF << 32) | n)

    def ps(us: str) -> int:
        return round(float(us) * 1e6)

    b = bytearray(b"\x01pulseq\x02" + struct.pack("<qqq", ver["major"], ver["minor"], ver["revision"]))
    defs = sec.get("[DEFINITIONS]", [])
    b += code(1) + struct.pack("<q", len(defs))
    for key, *vals in defs:
        b += struct.pack("<i", len(key)) + key.encode()
        try:
            nums = [float(v) for v in vals]
            b += struct.pack("<i", len(nums)) + b"f" + struct.pack(f"<{len(nums)}d", *nums)
        except ValueError:
            sval = " ".join(vals)
            b += struct.pack("<i", len(sval)) + b"c" + sval.encode()
    blocks = sec["[BLOCKS]"]
    b += code(2) + struct.pack("<q", len(blocks))
    for t in blocks:
        b += struct.pack("<q6i", int(t[1]), *map(int, t[2:8]))
    rf = sec.get("[RF]", [])
    b += code(3) + struct.pack("<q", len(rf))
    for t in rf:
        b += struct.pack("<idiiiqqdddd", int(t[0]), float(t[1]), *map(int, t[2:5]), ps(t[5]), ps(t[6]),
                         *map(float, t[7:11])) + t[11].encode()  # fmt: skip
    grads = sec.get("[GRADIENTS]", [])
    if grads:
        b += code(4) + struct.pack("<q", len(grads))
        for t in grads:
            b += struct.pack("<idddiiq", int(t[0]), *map(float, t[1:4]), int(t[4]), int(t[5]), ps(t[6]))
    traps = sec.get("[TRAP]", [])
    b += code(5) + struct.pack("<q", len(traps))
    for t in traps:
        b += struct.pack("<idqqqq", int(t[0]), float(t[1]), *map(ps, t[2:6]))
    adc = sec.get("[ADC]", [])
    b += code(6) + struct.pack("<q", len(adc))
    for t in adc:
        b += struct.pack("<iqqqddddi", int(t[0]), int(t[1]), round(float(t[2]) * 1e3), ps(t[3]),
                         *map(float, t[4:8]), int(t[8]))  # fmt: skip
    b += code(8) + struct.pack("<q", len(shapes))
    for sid, num, vals in shapes:
        b += struct.pack("<iqq", sid, num, len(vals)) + struct.pack(f"<{len(vals)}f", *vals)
    if sign:
        digest = hashlib.md5(bytes(b)).digest()
        orig = len(b)
        b += code(0x00FFFFFF) + struct.pack("<i", 3) + b"md5" + struct.pack("<i", len(digest)) + digest
        b += struct.pack("<q", orig)
    return bytes(b)
