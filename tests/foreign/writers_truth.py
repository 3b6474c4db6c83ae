"""Files of our own that reproduce what other people's writers produce and dtoc must report truthfully:
a Pulseq 1.4.1 spin-echo EPI (no RF ``use`` in the format: both pulses must be recognised, k centred), a file
declaring ``MaxAdcSegmentLength`` with a 12,000-sample ADC, a 20 us RF ring-down (Pulseq's MATLAB demos),
a 10 us RF raster, and a protocol whose only RF pulse has a ~0 flip (field-camera exports: no signal).

Every function returns the signed ``.seq`` bytes.  The 1.4 files are pypulseq 1.5 files rewritten in the 1.4.1
column layout (:func:`to_v141`): RF without centre and use, gradients without first/last, ADC without the ppm
offsets and phase shape, as Pulseq 1.4 writers (MATLAB, KomaMRI, pypulseq 1.4) emit them.
"""

from __future__ import annotations

from foreign.writers import se_epi


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
