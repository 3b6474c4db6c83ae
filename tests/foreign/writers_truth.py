"""Files of our own that reproduce what other people's writers produce and dtoc must report truthfully:
a Pulseq 1.4.1 spin-echo EPI (no RF ``use`` in the format: both pulses must be recognised, k centred), a file
declaring ``MaxAdcSegmentLength`` with a 12,000-sample ADC, a 20 us RF ring-down (Pulseq's MATLAB demos),
a 10 us RF raster, and a protocol whose only RF pulse has a ~0 flip (field-camera exports: no signal).

Every function returns the signed ``.seq`` bytes.  The 1.4 files are pypulseq 1.5 files rewritten in the 1.4.1
column layout (:func:`to_v141`): RF without centre and use, gradients without first/last, ADC without the ppm
offsets and phase shape, as Pulseq 1.4 writers (MATLAB, KomaMRI, pypulseq 1.4) emit them.
"""

from __future__ import annotations

import math

from foreign.writers import _bytes, se_epi


def to_v141(seq_bytes: bytes) -> bytes:
    """A pypulseq 1.5.x file rewritten in the 1.4.1 layout (trapezoid / extended-trapezoid gradients and RF
    only: arbitrary gradients would need the 1.4 edge convention, not covered here), re-signed."""
    from dtoc.seq.seqtext import sign_text

    out: list[str] = []
    sec = ""
    for line in seq_bytes.decode().split("\n"):
        s = line.strip()
        if s.startswith("[SIGNATURE]"):
            break
        if s.startswith("["):
            sec = s
            out.append(line)
            continue
        if sec == "[VERSION]" and s.startswith("minor"):
            line = "minor 4"
        elif sec == "[VERSION]" and s.startswith("revision"):
            line = "revision 1"
        elif s.startswith("#"):
            if sec in ("[RF]", "[GRADIENTS]", "[ADC]"):
                continue  # the 1.5 column comments would be wrong
        elif not s:
            pass
        elif sec == "[RF]":
            t = s.split()  # id amp mag phase time center delay freqppm phaseppm freq phase use
            line = " ".join([t[0], t[1], t[2], t[3], t[4], t[6], t[9], t[10]])
        elif sec == "[GRADIENTS]":
            t = s.split()  # id amp first last shape time delay
            line = " ".join([t[0], t[1], t[4], t[5], t[6]])
        elif sec == "[ADC]":
            t = s.split()  # id num dwell delay freqppm phaseppm freq phase phase_id
            line = " ".join([t[0], t[1], t[2], t[3], t[6], t[7]])
        out.append(line)
    body = "\n".join(out).rstrip("\n") + "\n"
    return sign_text(body)


def se_epi_v14(n: int = 32, fov: float = 0.22, te: float = 60e-3) -> bytes:
    """:func:`foreign.writers.se_epi` (90 - crushed 180 - blipped readout, flat-top sampling) in format 1.4.1, where
    the file carries no RF use: only the pulses tell excitation from refocusing.  The readout pre-phaser is
    positive before the 180 (which negates it), so k is centred only when the 180 is taken as a refocusing pulse."""
    return to_v141(se_epi(n, fov, te))


def gre_variant(
    n: int = 16,
    fov: float = 0.22,
    flip_deg: float = 10.0,
    rf_ringdown_s: float = 30e-6,
    rf_raster_s: float = 1e-6,
    adc_samples: int | None = None,
    adc_dwell_s: float = 10e-6,
    max_adc_segment: int | None = None,
    sync_kz_per_m: float = 0.0,
    definitions: dict | None = None,
) -> bytes:
    """A small 2D spoiled GRE (n x n) as other writers make it, with what they set differently from dtoc's default
    system: the RF ring-down (Pulseq MATLAB's ``mr.opts`` default is 20 us), the RF raster (a legal 10 us), the
    readout's samples (``adc_samples`` over the ``n``-step readout area: e.g. 12,000 oversampled samples that a
    Siemens interpreter plays in ``max_adc_segment``-sample segments, declared as ``MaxAdcSegmentLength``), the flip
    angle (field-camera exports carry RF of ~1e-100 deg: nothing excited); ``sync_kz_per_m``: a z gradient of
    ``sync_kz_per_m * (line + 1)^1.5`` (1/m) before each readout that nothing rewinds (sync blocks whose kz
    accumulates: the readouts sit at kz off any grid); ``definitions``: extra [DEFINITIONS] (e.g. FOV, Matrix)."""
    import pypulseq as pp

    sys = pp.Opts(
        max_grad=32, grad_unit="mT/m", max_slew=130, slew_unit="T/m/s", rf_ringdown_time=rf_ringdown_s,
        rf_dead_time=100e-6, adc_dead_time=10e-6, rf_raster_time=rf_raster_s,
    )  # fmt: skip
    seq = pp.Sequence(sys)
    rf = pp.make_block_pulse(flip_angle=math.radians(flip_deg), duration=0.5e-3, system=sys, delay=sys.rf_dead_time)
    dk = 1 / fov
    ns = adc_samples or n
    ro_time = math.ceil(ns * adc_dwell_s / 10e-6) * 10e-6
    gx = pp.make_trapezoid("x", flat_area=n * dk * ro_time / (ns * adc_dwell_s), flat_time=ro_time, system=sys)
    adc = pp.make_adc(ns, dwell=adc_dwell_s, delay=gx.rise_time, system=sys)
    gxpre = pp.make_trapezoid("x", area=-gx.area / 2, duration=1e-3, system=sys)
    spoil = pp.make_trapezoid("x", area=2 * n * dk, system=sys)
    for i in range(n):
        gy = pp.make_trapezoid("y", area=(i - n / 2) * dk, duration=1e-3, system=sys)
        seq.add_block(rf)
        if sync_kz_per_m:
            seq.add_block(pp.make_trapezoid("z", area=sync_kz_per_m * (i + 1) ** 1.5, duration=1e-3, system=sys))
        seq.add_block(gxpre, gy)
        seq.add_block(gx, adc)
        seq.add_block(spoil, pp.scale_grad(gy, -1))
    if max_adc_segment is not None:
        seq.set_definition("MaxAdcSegmentLength", max_adc_segment)
    for k, v in (definitions or {}).items():
        seq.set_definition(k, v)
    return _bytes(seq)
