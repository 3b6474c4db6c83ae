"""The candidate kinds `dtoc identify` screens, and the one way an effect is named in its reports.

No imports: the CLI reads :data:`CANDIDATE_KINDS` for its ``--kinds`` help without loading numpy.
"""

from __future__ import annotations

#: The candidate library (docs/identify.md, step 3), in the order the CLI lists it.
CANDIDATE_KINDS = (
    "delay",
    "delay_bandlimited",
    "gain",
    "offset",
    "exp_eddy",
    "cross_eddy",
    "b0_eddy",
    "resonance",
    "time_base",
    "lti",
    "slew_limit",
)


def effect_name(e) -> str:
    """``kind[axis]<-input_axis`` of anything with ``kind``, ``axis`` and ``input_axis`` (an effect or a
    screened proposal), e.g. ``cross_eddy[y]<-x``, ``delay`` (all axes), ``b0_eddy<-z``."""
    s = e.kind
    if e.axis is not None:
        s += f"[{e.axis}]"
    if e.input_axis is not None:
        s += f"<-{e.input_axis}"
    return s
