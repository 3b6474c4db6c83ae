"""dtoc's pre-upload validator: everything a careful engineer checks before a ``.seq`` goes to a scanner.

Two layers:

* :func:`check_ir_limits` (IR only; the optimizer calls it before writing): per-axis and vector
  gradient amplitude and slew rate on the played piecewise-linear waveform, i.e. on every fine-grid
  segment including the half-raster edge segments to an arbitrary gradient's ``first``/``last``.
* :func:`check_file` (file text + pypulseq events + IR): the limits above, plus continuity between
  blocks (``system.continuity_tol_hz_per_m``, 1 Hz/m by default), gradients that end inside a block
  or at the end of the sequence must end at zero, block durations on the block raster, events
  inside their block, RF dead time / ring-down / raster, ADC dead time / raster / sample-count rules,
  gradient timing on the gradient raster, the md5 signature, LF line endings, integer fields without
  scientific notation or decimals, rasters equal to the system's, and required definitions.

Each problem is a :class:`Violation` (rule, block, axis, value, limit, unit, message) of one of three kinds
(:data:`RULE_KINDS`, docs/foreign.md "What dtoc check checks"), each with where its value came from:

* ``format``: what the file's format version requires (structure, signature when present, integer fields, required
  definitions, events on the file's own rasters and inside their blocks, continuous gradients that end at zero);
* ``limits``: the user's limits or scanner profile (gradient amplitude and slew per axis and vector, PNS, acoustics);
* ``convention``: a vendor's conventions (RF dead time and ring-down, ADC dead time, ADC sample count and
  segmenting, the file's rasters against the scanner's), checked only when a scanner profile or a system file
  names them (``conventions``); otherwise listed in ``CheckResult.not_checked``, never assumed.

Limits are aggregated per (rule, block, axis): one row with the worst value.
"""

from __future__ import annotations

import copy
import re
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import ValidationError

from dtoc.constants import AXES, GAMMA_HZ_PER_T
from dtoc.errors import InputError, ValidationFailed
from dtoc.seq.ir import SequenceIR
from dtoc.seq.pulseq import quiet
from dtoc.seq.read import from_pypulseq, grad_vertices, read_pypulseq
from dtoc.seq.seqtext import INTEGER_COLUMNS, forget_shared_parse, parse_seq_text, shared_parse
from dtoc.seq.system import SystemSpec, format_validation_error

_RTOL = 1e-6  # relative tolerance on limits (file precision: 6 significant digits)
_TTOL = 1e-9  # s, timing tolerance


FORMAT, LIMITS, CONVENTION = "format", "limits", "convention"
#: the kind of each rule (module doc)
RULE_KINDS = {
    **dict.fromkeys(
        (
            "line_endings",
            "signature",
            "integer_format",
            "definitions",
            "block_raster",
            "grad_raster",
            "rf_raster",
            "adc_raster",
            "adc_dwell",
            "block_duration",
            "continuity",
            "grad_start_nonzero",
            "grad_end_nonzero",
        ),
        FORMAT,
    ),
    **dict.fromkeys(("grad_amplitude", "slew_rate", "grad_vector", "slew_vector", "pns", "acoustic"), LIMITS),
    **dict.fromkeys(("rf_dead_time", "rf_ringdown", "adc_dead_time", "adc_samples", "raster"), CONVENTION),
}
_AUTO = "auto"


@dataclass
class Violation:
    rule: str
    block: int | None = None  # Pulseq block number (1-based) when known
    axis: str | None = None
    value: float | None = None
    limit: float | None = None
    unit: str = ""
    message: str = ""
    kind: str = ""  # format / limits / convention (RULE_KINDS)
    source: str = ""  # where the limit or rule came from (e.g. "format 1.4.1", "--gmax 32", "--scanner terra")

    def __post_init__(self):
        self.block = None if self.block is None else int(self.block)
        self.value = None if self.value is None else float(self.value)
        self.limit = None if self.limit is None else float(self.limit)

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class CheckResult:
    path: str
    system: SystemSpec
    limits_source: str
    violations: list[Violation] = field(default_factory=list)
    #: facts that do not fail the check but a user must see (e.g. an interrupted optimize's best-so-far)
    warnings: list[str] = field(default_factory=list)
    #: what was checked beyond the limits, with its figure (e.g. "PNS (SAFE): max 63.2 % of the limit")
    checks: list[str] = field(default_factory=list)
    #: the file's [DEFINITIONS] as text (name -> value string), for checks made on top (e.g. orientation)
    definitions: dict[str, str] = field(default_factory=dict)
    #: rules not checked and why (e.g. vendor conventions that no scanner profile names)
    not_checked: list[str] = field(default_factory=list)
    #: where each kind of rule came from (kind -> source; a kind absent: not checked)
    sources: dict[str, str] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return not self.violations

    def rules(self) -> set[str]:
        return {v.rule for v in self.violations}

    def to_dict(self) -> dict:
        return {
            "path": self.path,
            "ok": self.ok,
            "limits_source": self.limits_source,
            "system": self.system.model_dump(mode="json"),
            "n_violations": len(self.violations),
            "violations": [v.to_dict() for v in self.violations],
            "warnings": list(self.warnings),
            "checks": list(self.checks),
            "not_checked": list(self.not_checked),
            "rule_sources": dict(self.sources),
        }

    def failed_kinds(self) -> dict[str, list[Violation]]:
        """Violations by kind (format, limits, convention), in that order, kinds without any left out."""
        out: dict[str, list[Violation]] = {}
        for k in (FORMAT, LIMITS, CONVENTION):
            vs = [v for v in self.violations if v.kind == k]
            if vs:
                out[k] = vs
        return out

    def summary(self) -> str:
        """One line per failed kind: its source and each rule with its worst value (no internal names alone)."""
        parts = []
        for kind, vs in self.failed_kinds().items():
            worst: dict[str, Violation] = {}
            for v in vs:
                w = worst.setdefault(v.rule, v)
                if v.value is not None and v.limit and w.value is not None and w.limit:
                    if abs(v.value / v.limit) > abs(w.value / w.limit):
                        worst[v.rule] = v
            rules = "; ".join(_worst_text(r, w, sum(x.rule == r for x in vs)) for r, w in sorted(worst.items()))
            parts.append(f"{kind} ({vs[0].source}): {rules}")
        return " | ".join(parts)


def _q(x: float, unit: str) -> str:
    return f"{x:.5g} {unit}".strip()


def _worst_text(rule: str, w: Violation, n: int) -> str:
    many = f"{n} x " if n > 1 else ""
    if w.value is not None and w.limit is not None:
        return f"{many}{rule} (worst {_q(w.value, w.unit)} vs {_q(w.limit, w.unit)})"
    if w.value is not None:
        return f"{many}{rule} ({_q(w.value, w.unit)}: {w.message})"
    return f"{many}{rule} ({w.message})"


# ------------------------------------------------------------------------------------------ limits
def _block_numbers(ir: SequenceIR) -> list[int]:
    ids = ir.meta.get("block_ids")
    nb = len(ir.block_edges_s) - 1
    return list(ids) if ids and len(ids) == nb else list(range(1, nb + 1))


def check_ir_limits(ir: SequenceIR, system: SystemSpec, grad_mT_per_m=None, m0: int = 0) -> list[Violation]:
    """Amplitude and slew violations of the played demanded gradient (per axis and vector norm).

    Args:
        ir: the sequence (its fine grid and blocks).
        system: limits.
        grad_mT_per_m: optional (3, 2N+1) waveform to check instead of ``ir.grad_mT_per_m``.
        m0: the fine-grid index of ``ir``'s first sample in a longer sequence it is a piece of (the times the
            messages name are the longer sequence's).
    Returns:
        violations, one per (rule, block, axis) with the worst value.
    """
    g = np.asarray(ir.grad_mT_per_m if grad_mT_per_m is None else grad_mT_per_m, dtype=np.float64)
    dtf = ir.dt_fine_s
    nums = _block_numbers(ir)
    m_edges = np.round(np.asarray(ir.block_edges_s) / dtf).astype(np.int64)
    out: list[Violation] = []

    # Memory: one (2N+1,) temporary at a time, and the block of a sample or segment looked up only for the
    # offending indices (a long sequence's checker must not hold per-sample block tables).
    def worst(rule, vals, segment, limit, unit, axis=None, what=""):
        bad = np.flatnonzero(np.abs(vals) > limit * (1 + _RTOL))
        if bad.size == 0:
            return
        blocks = np.searchsorted(m_edges, bad, side="right") - 1  # a segment belongs to the block holding its start
        if not segment:
            blocks = np.clip(blocks, 0, len(nums) - 1)
        for b in np.unique(blocks):
            sel = bad[blocks == b]
            i = sel[np.argmax(np.abs(vals[sel]))]
            v = float(abs(vals[i]))
            out.append(
                Violation(
                    rule,
                    nums[int(b)],
                    axis,
                    v,
                    limit,
                    unit,
                    f"{what} {v:.4g} {unit} > {limit:.4g} at t = {(i + m0) * dtf * 1e3:.3f} ms",
                )
            )

    def slew(a):  # T/m/s
        return np.diff(g[a]) / dtf * 1e-3

    for a in range(3):
        worst("grad_amplitude", g[a], False, system.max_grad_mT_per_m, "mT/m", AXES[a], f"|g{AXES[a]}|")
        worst("slew_rate", slew(a), True, system.max_slew_T_per_m_per_s, "T/m/s", AXES[a], f"|dg{AXES[a]}/dt|")
    g2 = g[0] * g[0]
    g2 += g[1] * g[1]
    g2 += g[2] * g[2]
    worst("grad_vector", np.sqrt(g2, out=g2), False, system.vector_grad_limit_mT_per_m, "mT/m", None, "|g|")
    del g2
    s2 = slew(0) ** 2
    s2 += slew(1) ** 2
    s2 += slew(2) ** 2
    worst("slew_vector", np.sqrt(s2, out=s2), True, system.vector_slew_limit_T_per_m_per_s, "T/m/s", None, "|dg/dt|")
    return out


# ------------------------------------------------------------------------------------------- file
def system_from_definitions(defs: dict) -> SystemSpec | None:
    """The design limits a dtoc-built file records (MaxGrad_mT_per_m, MaxSlew_T_per_m_per_s, rasters)."""
    try:
        g = float(defs["MaxGrad_mT_per_m"])
        s = float(defs["MaxSlew_T_per_m_per_s"])
    except (KeyError, TypeError, ValueError):
        return None
    kw = {"name": "file definitions", "max_grad_mT_per_m": g, "max_slew_T_per_m_per_s": s}
    for key, f in (
        ("GradientRasterTime", "grad_raster_s"),
        ("RadiofrequencyRasterTime", "rf_raster_s"),
        ("AdcRasterTime", "adc_raster_s"),
        ("BlockDurationRaster", "block_raster_s"),
    ):
        try:
            kw[f] = float(defs[key])
        except (KeyError, TypeError, ValueError):
            pass
    try:
        return SystemSpec(**kw)
    except ValidationError as e:
        raise InputError(
            f"the limits recorded in the file's definitions are invalid ({format_validation_error(e)}); "
            "give them with --gmax/--smax or --system"
        ) from None


def _all_on_raster(times, r: float) -> bool:
    """True when every time (s) is a multiple of the raster ``r`` to 1e-6 of it (an arbitrary gradient has one
    time per sample: tested at once)."""
    q = np.asarray(times, dtype=np.float64) / r
    return bool(np.all(np.abs(q - np.round(q)) < 1e-6))


def _on_raster(t: float, r: float) -> bool:
    return _all_on_raster((t,), r)


def _text_rules(st, out: list[Violation]) -> None:
    """The format's rules on the text (line endings, signature when present, integer fields, required
    definitions)."""
    raw = st.raw
    if b"\r" in raw:
        n = raw.count(b"\r\n") or raw.count(b"\r")
        out.append(Violation("line_endings", message=f"{n} CR characters: the file must use LF line endings"))
    if st.signature_hash is None:
        pass  # optional in the specification: a warning (check_file), not a violation
    elif st.signature_type not in (None, "md5"):
        out.append(
            Violation("signature", message=f"signature type {st.signature_type!r}: Pulseq interpreters verify md5")
        )
    else:
        got = st.content_md5()
        if got != st.signature_hash:
            out.append(Violation("signature", message=f"md5 of content {got} != signature {st.signature_hash}"))
    cols = INTEGER_COLUMNS.get(st.major_minor, {})
    for sec, idx in cols.items():
        for ln in st.sections.get(sec, []):
            t = ln.tokens
            for c in idx:
                if c < len(t) and not re.fullmatch(r"[+-]?\d+", t[c]):
                    out.append(
                        Violation(
                            "integer_format",
                            message=f"line {ln.lineno} {sec} field {c + 1}: {t[c]!r} is not a plain integer",
                        )
                    )
    for ln in st.sections.get("[SHAPES]", []):
        t = ln.tokens
        if len(t) == 2 and t[0] in ("shape_id", "num_samples") and not re.fullmatch(r"\d+", t[1]):
            out.append(
                Violation(
                    "integer_format", message=f"line {ln.lineno} [SHAPES] {t[0]}: {t[1]!r} is not a plain integer"
                )
            )
    defs = st.definitions()
    if st.major_minor >= (1, 4):  # format 1.4.0 made the four rasters required definitions
        for key in _RASTER_DEFINITIONS:
            if key not in defs:
                out.append(
                    Violation(
                        "definitions",
                        message=f"required definition {key} is missing (format {st.major_minor[0]}.{st.major_minor[1]})",
                    )
                )
    for key in _RASTER_DEFINITIONS:
        if key in defs:
            try:
                float(defs[key].split()[0])
            except (ValueError, IndexError):
                out.append(Violation("definitions", message=f"definition {key} {defs[key]!r} is not a number"))


_RASTER_DEFINITIONS = ("GradientRasterTime", "RadiofrequencyRasterTime", "AdcRasterTime", "BlockDurationRaster")


def file_rasters(seq) -> dict[str, float]:
    """The rasters the file declares (pypulseq's defaults where it declares none), s."""
    return {
        "grad": float(seq.grad_raster_time),
        "rf": float(seq.rf_raster_time),
        "adc": float(seq.adc_raster_time),
        "block": float(seq.block_duration_raster),
    }


def _raster_convention(rasters: dict[str, float], system: SystemSpec, out: list[Violation]) -> None:
    """The file's rasters against the scanner's: the gradient raster must be the scanner's (the interpreter plays
    gradient samples on it); the RF, ADC and block rasters a whole multiple of the scanner's (every time on the
    file's raster is then on the scanner's: a declared 10 us RF raster is legal on a 1 us scanner)."""
    for key, name, want in (
        ("grad", "GradientRasterTime", system.grad_raster_s),
        ("rf", "RadiofrequencyRasterTime", system.rf_raster_s),
        ("adc", "AdcRasterTime", system.adc_raster_s),
        ("block", "BlockDurationRaster", system.block_raster_s),
    ):
        v = rasters[key]
        ok = abs(v - want) <= 1e-12 if key == "grad" else _on_raster(v, want)
        if not ok:
            how = "differs from" if key == "grad" else "is not a whole multiple of"
            out.append(
                Violation(
                    "raster",
                    value=v * 1e6,
                    limit=want * 1e6,
                    unit="us",
                    message=f"{name} {v * 1e6:g} us {how} the scanner's {want * 1e6:g} us",
                )
            )


def _event_rules(
    seq,
    ir: SequenceIR | None,
    system: SystemSpec,
    out: list[Violation],
    conventions: bool,
    adc_segment: int | None,
    names: dict | None = None,
) -> None:
    """Events on the file's own rasters and inside their blocks, continuity (format); with ``conventions`` the
    scanner's dead times, ring-down and ADC sample rules (``adc_segment``: the file's MaxAdcSegmentLength, the
    interpreter splits a longer ADC into segments of that many samples).  ``names``: the number each block of
    ``seq`` is reported by (a piece's blocks: the whole text's), default its own."""
    rasters = file_rasters(seq)
    r = rasters["grad"]
    keys = list(seq.block_events.keys())
    tol = system.continuity_tol_hz_per_m
    prev_last = np.zeros(3)  # value each axis has at the end of the previous block of non-zero duration, Hz/m
    prev_key = None  # that block (None: the sequence starts)
    for src_key in keys:
        key = src_key if names is None else names[src_key]
        with quiet():
            blk = seq.get_block(src_key)
        dur = float(seq.block_durations[src_key])
        if not _on_raster(dur, rasters["block"]):
            out.append(
                Violation(
                    "block_raster",
                    key,
                    None,
                    dur * 1e6,
                    rasters["block"] * 1e6,
                    "us",
                    f"duration {dur * 1e6:.3f} us is not a multiple of the block raster",
                )
            )
        first = np.zeros(3)
        last = np.zeros(3)
        for a, ch in enumerate(("gx", "gy", "gz")):
            gr = getattr(blk, ch, None)
            if gr is None:
                continue
            tv, vv = grad_vertices(gr, r)
            if not _on_raster(gr.delay, r):
                out.append(
                    Violation(
                        "grad_raster",
                        key,
                        AXES[a],
                        gr.delay * 1e6,
                        r * 1e6,
                        "us",
                        "gradient delay not on the gradient raster",
                    )
                )
            if gr.type == "trap":
                for nm in ("rise_time", "flat_time", "fall_time"):
                    if not _on_raster(getattr(gr, nm), r):
                        out.append(
                            Violation(
                                "grad_raster",
                                key,
                                AXES[a],
                                getattr(gr, nm) * 1e6,
                                r * 1e6,
                                "us",
                                f"trapezoid {nm} not on the gradient raster",
                            )
                        )
            elif gr.time_id not in (0, -1) and not _all_on_raster(gr.tt, r / 2):
                # shaped gradients sample at raster edges (extended trapezoids), raster centres (arbitrary
                # gradients with an explicit time shape, e.g. 0.5 1.5 ...) or every half raster (1.5.1
                # oversampling): every time a multiple of half the gradient raster is the format's
                q = np.asarray(gr.tt, dtype=np.float64) / (r / 2)
                off = float(np.asarray(gr.tt)[np.argmax(np.abs(q - np.round(q)) >= 1e-6)])
                out.append(
                    Violation(
                        "grad_raster",
                        key,
                        AXES[a],
                        off * 1e6,
                        r / 2 * 1e6,
                        "us",
                        f"shaped-gradient time {off * 1e6:.4g} us not on the half gradient raster",
                    )
                )
            if tv[-1] > dur + _TTOL:
                out.append(
                    Violation(
                        "block_duration", key, AXES[a], tv[-1] * 1e6, dur * 1e6, "us", "gradient ends after its block"
                    )
                )
            if tv[0] <= _TTOL:
                first[a] = vv[0]
            elif abs(vv[0]) > tol:
                out.append(
                    Violation(
                        "grad_start_nonzero",
                        key,
                        AXES[a],
                        abs(vv[0]),
                        tol,
                        "Hz/m",
                        "gradient starting after the block start does not start at zero",
                    )
                )
            if tv[-1] >= dur - _TTOL:
                last[a] = vv[-1]
            elif abs(vv[-1]) > tol:
                out.append(
                    Violation(
                        "grad_end_nonzero",
                        key,
                        AXES[a],
                        abs(vv[-1]),
                        tol,
                        "Hz/m",
                        f"gradient ends at {vv[-1]:.6g} Hz/m before the block end ({tv[-1] * 1e6:.1f} of {dur * 1e6:.1f} us)",
                    )
                )
        # a zero-duration block (labels, other extensions) plays no time: the gradient runs on from the previous
        # block of non-zero duration into the next one, as Pulseq's own setBlock and checkTiming compare them
        # (docs/foreign.md "What dtoc check checks")
        if dur > _TTOL:
            for a in range(3):
                jump = abs(first[a] - prev_last[a])
                if jump > tol:
                    what = "sequence starts" if prev_key is None else f"jump from block {prev_key}"
                    out.append(
                        Violation(
                            "continuity",
                            key,
                            AXES[a],
                            jump,
                            tol,
                            "Hz/m",
                            f"{what}: {prev_last[a]:.6g} -> {first[a]:.6g} Hz/m",
                        )
                    )
            prev_last, prev_key = last, key
        rf = getattr(blk, "rf", None)
        if rf is not None and conventions:
            if rf.delay < system.rf_dead_time_s - _TTOL:
                out.append(
                    Violation(
                        "rf_dead_time",
                        key,
                        None,
                        rf.delay * 1e6,
                        system.rf_dead_time_s * 1e6,
                        "us",
                        "RF delay shorter than the RF dead time",
                    )
                )
            tail = dur - (rf.delay + rf.shape_dur)
            if tail < system.rf_ringdown_time_s - _TTOL:
                out.append(
                    Violation(
                        "rf_ringdown",
                        key,
                        None,
                        tail * 1e6,
                        system.rf_ringdown_time_s * 1e6,
                        "us",
                        "time from RF end to block end shorter than the ring-down time",
                    )
                )
        if rf is not None and not _on_raster(rf.delay, rasters["rf"]):
            out.append(
                Violation(
                    "rf_raster",
                    key,
                    None,
                    rf.delay * 1e6,
                    rasters["rf"] * 1e6,
                    "us",
                    "RF delay not on the file's RF raster",
                )
            )
        adc = getattr(blk, "adc", None)
        if adc is not None:
            end = adc.delay + adc.num_samples * adc.dwell
            if conventions and adc.delay < system.adc_dead_time_s - _TTOL:
                out.append(
                    Violation(
                        "adc_dead_time",
                        key,
                        None,
                        adc.delay * 1e6,
                        system.adc_dead_time_s * 1e6,
                        "us",
                        "ADC delay shorter than the ADC dead time",
                    )
                )
            if conventions and dur - end < system.adc_dead_time_s - _TTOL:
                out.append(
                    Violation(
                        "adc_dead_time",
                        key,
                        None,
                        (dur - end) * 1e6,
                        system.adc_dead_time_s * 1e6,
                        "us",
                        "time from ADC end to block end shorter than the ADC dead time",
                    )
                )
            if end > dur + _TTOL:
                out.append(
                    Violation("block_duration", key, None, end * 1e6, dur * 1e6, "us", "ADC ends after its block")
                )
            if not adc.dwell > 0:  # every sample at one instant: no readout (on the raster, but not playable)
                out.append(
                    Violation("adc_dwell", key, None, adc.dwell * 1e9, rasters["adc"] * 1e9, "ns", "ADC dwell is 0")
                )
            elif not _on_raster(adc.dwell, rasters["adc"]):
                out.append(
                    Violation(
                        "adc_raster",
                        key,
                        None,
                        adc.dwell * 1e9,
                        rasters["adc"] * 1e9,
                        "ns",
                        "ADC dwell not on the file's ADC raster",
                    )
                )
            if not _on_raster(adc.delay, rasters["rf"]):
                out.append(
                    Violation(
                        "adc_raster",
                        key,
                        None,
                        adc.delay * 1e6,
                        rasters["rf"] * 1e6,
                        "us",
                        "ADC delay not on the file's RF raster",
                    )
                )
            if conventions:
                _adc_sample_rules(key, int(adc.num_samples), float(adc.dwell), r, system, adc_segment, out)
    for a in range(3):
        if abs(prev_last[a]) > tol:
            out.append(
                Violation(
                    "grad_end_nonzero",
                    prev_key,
                    AXES[a],
                    abs(prev_last[a]),
                    tol,
                    "Hz/m",
                    "sequence ends with a non-zero gradient",
                )
            )


def _adc_sample_rules(
    key, n: int, dwell: float, grad_raster: float, system: SystemSpec, segment: int | None, out: list[Violation]
) -> None:
    """The scanner's ADC sample rules: at most ``adc_max_samples`` per ADC and a multiple of ``adc_samples_divisor``;
    where the file declares MaxAdcSegmentLength L and the ADC is longer, the interpreter plays it as n / L segments:
    then L (not n) obeys them, n is a whole number of segments, and each segment ends on the gradient raster
    (Pulseq's ``mr.calcAdcSeg``)."""

    def bad(value, limit, msg):
        out.append(Violation("adc_samples", key, None, value, limit, "", msg))

    if segment is not None and n > segment:
        if n % segment:
            bad(n, segment, f"{n} samples is not a whole number of the declared {segment}-sample ADC segments")
        if segment % system.adc_samples_divisor:
            bad(segment, system.adc_samples_divisor, f"ADC segment of {segment} samples is not a multiple of "
                f"{system.adc_samples_divisor}")  # fmt: skip
        if segment > system.adc_max_samples:
            bad(segment, system.adc_max_samples, f"ADC segment of {segment} samples exceeds {system.adc_max_samples}")
        if not _on_raster(segment * dwell, grad_raster):
            bad(segment, None, f"ADC segment of {segment} samples ({segment * dwell * 1e6:.6g} us) does not end on the "
                "gradient raster")  # fmt: skip
        return
    if n % system.adc_samples_divisor:
        bad(n, system.adc_samples_divisor, f"{n} samples is not a multiple of {system.adc_samples_divisor}")
    if n > system.adc_max_samples:
        bad(n, system.adc_max_samples, f"{n} samples exceeds {system.adc_max_samples} per ADC (and the file declares "
            "no MaxAdcSegmentLength for the interpreter to split it)")  # fmt: skip


#: format rules on the timing of events dtoc never changes (block durations, RF and ADC events): an output inherits
#: a base's violation of them unchanged, so the optimize pre-flight refuses such a base (:func:`base_timing_violations`)
INHERITED_RULES = ("block_raster", "block_duration", "rf_raster", "adc_raster", "adc_dwell")
#: the definition that states each inherited rule's raster (None: no raster)
_RULE_RASTER = {"block_raster": "BlockDurationRaster", "rf_raster": "RadiofrequencyRasterTime"}


def base_timing_violations(seq) -> list[tuple[Violation, int]]:
    """A base's violations of :data:`INHERITED_RULES` (the same rules :func:`check_file` applies to an output, on the
    file's own rasters), each with the number of blocks that fail it the same way.  Those rules depend on a block's
    duration, its RF event's delay and its ADC event only, so one block of each is checked: a second for a protocol
    of thousands of blocks, RF pulses of many phases included."""
    rf_delay = {i: float(d[5]) for i, d in seq.rf_library.data.items()}  # (amp, mag, phase, time, center, delay, ..)
    groups: dict = {}
    for k, ev in seq.block_events.items():
        groups.setdefault((float(seq.block_durations[k]), rf_delay.get(int(ev[1])), int(ev[5])), []).append(k)
    sub = copy.copy(seq)  # libraries shared (read only); a block of each kind
    sub.block_events = OrderedDict((ks[0], seq.block_events[ks[0]]) for ks in groups.values())
    sub.block_durations = {ks[0]: seq.block_durations[ks[0]] for ks in groups.values()}
    sub.block_cache, sub.block_trace = {}, OrderedDict()
    count = {ks[0]: len(ks) for ks in groups.values()}
    out: list[Violation] = []
    no_limits = SystemSpec(max_grad_mT_per_m=1.0, max_slew_T_per_m_per_s=1.0)  # (the timing rules use none)
    _event_rules(sub, None, no_limits, out, False, None)
    return [(v, count.get(v.block, 1)) for v in out if v.rule in INHERITED_RULES]


def base_timing_refusal(seq, version: str, path: str | Path | None = None) -> str | None:
    """One line naming the base's first violation of :data:`INHERITED_RULES` (the rule, how many blocks, the
    figures, the raster and whether the file declares it or a reader's default is assumed: ``path``, the file whose
    [DEFINITIONS] say it; without one, what ``seq`` holds), or None."""
    found = base_timing_violations(seq)
    if not found:
        return None
    v, _ = found[0]
    n = sum({w.block: c for w, c in found if w.rule == v.rule}.values())  # blocks (one may fail it twice)
    name = _RULE_RASTER.get(v.rule)
    if v.rule == "adc_raster":
        name = "AdcRasterTime" if "dwell" in v.message else "RadiofrequencyRasterTime"
    declared = {str(k) for k in (getattr(seq, "definitions", None) or {})}
    # a pre-1.4 reader fills the rasters it assumes into the definitions: what the file says (its opening section)
    if path is not None and name is not None and Path(path).is_file():
        with open(path, "rb") as f:
            head = f.read(1 << 16).decode("latin-1")
        declared = {name} if re.search(rf"^\s*{name}\s", head, re.M) else set()
    where = ""
    if name is not None and v.limit is not None:
        how = "declared by the file" if name in declared else "not declared by the file: the readers' default, assumed"
        where = f", {name} {v.limit:g} {v.unit} {how}"
    figure = "" if v.value is None else f" ({v.value:g} {v.unit})"
    return (
        f"the base itself fails dtoc check's rule {v.rule} (Pulseq format {version}{where}): {n} block(s), first "
        f"block {v.block}: {v.message}{figure}; dtoc keeps every block duration and RF/ADC timing, so its output "
        "would fail the same rule, and an interpreter on that raster cannot play the timing the twin optimizes for: "
        "correct the base and run again"
    )


#: the format's gradient rules no hardware limit names: a step between blocks (``continuity``) and a gradient that starts
#: or ends inside its block at a non-zero value (a step there).  dtoc's writer rewrites only the blocks it changes, so
#: an output keeps a base's step where it changes neither block: inherited, told apart from one dtoc introduces
#: (:func:`split_inherited`)
GRADIENT_RULES = ("continuity", "grad_start_nonzero", "grad_end_nonzero")


def gradient_rule_violations(seq, system: SystemSpec) -> list[Violation]:
    """The violations of :data:`GRADIENT_RULES` of a pypulseq ``Sequence`` (a base as read), as :func:`check_file`
    finds them in a file (same blocks, axes and figures, Hz/m)."""
    out: list[Violation] = []
    _event_rules(seq, None, system, out, False, None)
    return [v for v in out if v.rule in GRADIENT_RULES]


def step_limit_hz_per_m(system: SystemSpec) -> float:
    """The largest step, Hz/m, a gradient may take from one raster point to the next within the slew limit: smax x
    the gradient raster (Pulseq's own continuity tolerance, ``maxSlew * gradRasterTime`` in setBlock and pypulseq's
    add_block).  A larger step is played faster than the slew limit allows: a limit, never a format matter."""
    return system.max_slew_T_per_m_per_s * system.grad_raster_s * GAMMA_HZ_PER_T


def split_inherited(
    violations: list[Violation], base: list[Violation], system: SystemSpec
) -> tuple[list[Violation], list[tuple[Violation, Violation]]]:
    """(introduced, inherited) of an output's ``violations`` against its base's (:func:`gradient_rule_violations`).

    A violation is inherited when its rule is one of :data:`GRADIENT_RULES`, the base fails the same rule at the same
    block and axis, the output's figure is not worse than the base's (by more than the rule's own tolerance, 1 Hz/m
    by default) and the step is within the slew limit (:func:`step_limit_hz_per_m`): a base's step beyond it is a
    limit question, and dtoc never writes beyond the limits.  Every other violation is introduced.  ``inherited``
    pairs each output violation with the base's."""
    at = {(v.rule, v.block, v.axis): v for v in base if v.rule in GRADIENT_RULES}
    step = step_limit_hz_per_m(system)
    introduced: list[Violation] = []
    inherited: list[tuple[Violation, Violation]] = []
    for v in violations:
        b = at.get((v.rule, v.block, v.axis))
        if b is not None and _not_worse(v, b) and v.value is not None and v.value <= step:
            inherited.append((v, b))
        else:
            introduced.append(v)
    return introduced, inherited


def _not_worse(v: Violation, b: Violation) -> bool:
    """An output's violation ``v`` is not worse than the base's ``b`` at the same place: by at most the rule's own
    tolerance (``v.limit``, 1 Hz/m for continuity by default)."""
    return v.value is not None and b.value is not None and v.value <= b.value + (v.limit or 0.0) + 1e-9 * abs(b.value)


def settle_inherited(res: CheckResult, base_seq, system: SystemSpec) -> list[dict]:
    """The final check of a written output against its base (``base_seq``, the pypulseq ``Sequence`` it was written
    from): its :data:`GRADIENT_RULES` violations the base has too (:func:`split_inherited`) leave ``res.violations``
    and come back as records (rule, block, axis, value, the base's value, unit, message); one it introduced, or a
    base's step beyond the slew limit, raises :class:`ValidationFailed` (one line: nothing is written)."""
    mine = [v for v in res.violations if v.rule in GRADIENT_RULES]
    if not mine:
        return []
    base = [] if base_seq is None else gradient_rule_violations(base_seq, system)
    introduced, inherited = split_inherited(mine, base, system)
    if introduced:
        v = introduced[0]
        b = next((w for w in base if (w.rule, w.block, w.axis) == (v.rule, v.block, v.axis)), None)
        step = step_limit_hz_per_m(system)
        if b is None:
            why = "the base has none there: introduced by the optimization"
        elif not _not_worse(v, b):
            why = f"worse than the base's {_q(b.value or 0.0, b.unit)} there: introduced by the optimization"
        else:  # not worse, so beyond the slew limit's step: the base's own
            why = (
                f"the base itself steps {_q(b.value or 0.0, b.unit)} there, more than the {_q(step, 'Hz/m')} the slew "
                f"limit allows in one gradient raster ({system.max_slew_T_per_m_per_s:g} T/m/s x "
                f"{system.grad_raster_s * 1e6:g} us): a limit, never accepted as inherited"
            )
        more = f" (and {len(introduced) - 1} more)" if len(introduced) > 1 else ""
        raise ValidationFailed(
            f"written file fails dtoc check: {v.rule} at block {v.block}, axis {v.axis}: {v.message} "
            f"({_q(v.value or 0.0, v.unit)}){more}; {why}; nothing written"
        )
    drop = {id(v) for v, _ in inherited}
    res.violations = [v for v in res.violations if id(v) not in drop]
    return [
        {
            "rule": v.rule,
            "block": v.block,
            "axis": v.axis,
            "value": v.value,
            "base_value": b.value,
            "unit": v.unit,
            "message": v.message,
        }
        for v, b in inherited
    ]


def inherited_text(records: list[dict]) -> str:
    """One line of an output's inherited violations (:func:`settle_inherited`): how many of each rule, the worst."""
    parts = []
    for rule in GRADIENT_RULES:
        rs = [r for r in records if r["rule"] == rule]
        if rs:
            w = max(rs, key=lambda r: r["value"] or 0.0)
            parts.append(
                f"{len(rs)} x {rule} (worst {_q(w['value'] or 0.0, w['unit'])} at block {w['block']}, axis {w['axis']}; "
                f"the base's {_q(w['base_value'] or 0.0, w['unit'])})"
            )
    return "; ".join(parts)


@dataclass(frozen=True)
class SafetyChecks:
    """Checks beyond limits and timing, made on the physical axes (docs/scanner.md).

    Attributes:
        pns: SAFE parameters (:class:`dtoc.seq.pns.SafeModel`), or None: PNS not checked.
        acoustic_bands_hz: forbidden bands ``[[lo, hi], ...]``, Hz (empty: not checked).
        acoustic_max_power_fraction: the largest fraction of an axis' switching power allowed in a band.
        rotation: (3, 3) logical -> physical R the file is played at (None: its axes are the physical ones).
    """

    pns: Any = None
    acoustic_bands_hz: tuple = ()
    acoustic_max_power_fraction: float = 0.1
    rotation: Any = None


def _head(path, st, system: SystemSpec | None, limits_source, conventions, signed: bool) -> CheckResult:
    """:func:`check_file`'s result before any rule: the limits (given, or the file's definitions), the rules'
    sources, what is not checked and the warnings the parse ``st`` of the text (or of a piece of it: the same
    [VERSION] and [DEFINITIONS]) gives; ``signed``: the text has a [SIGNATURE]."""
    source = "given"
    if conventions == _AUTO:
        conventions = f"system {system.name}" if system is not None else None
    if system is None:
        defs = {}
        for k, v in st.definitions().items():
            defs[k] = v.split()[0] if v.split() else v
        try:
            system = system_from_definitions(defs)
        except InputError as e:
            raise InputError(f"{path}: {e}") from None
        if system is None:
            raise InputError(
                f"{path}: the file records no gradient limits (MaxGrad_mT_per_m / MaxSlew_T_per_m_per_s): give "
                "--gmax and --smax or --system (limits are never assumed)"
            )
        source = "file definitions"
    res = CheckResult(
        path=str(path), system=system, limits_source=limits_source or source, definitions=dict(st.definitions())
    )
    version = ".".join(str(x) for x in st.version)
    res.sources = {FORMAT: f"Pulseq format {version}", LIMITS: res.limits_source}
    if conventions:
        res.sources[CONVENTION] = conventions
    else:
        res.not_checked.append(
            "vendor conventions (RF dead time and ring-down, ADC dead time, ADC sample count and segmenting, the "
            "file's rasters against the scanner's): not checked, no scanner profile or --system names them"
        )
    if res.definitions.get("DtocInterrupted", "").split()[:1] == ["1"]:
        res.warnings.append(
            "written by an interrupted dtoc optimize (DtocInterrupted 1): a best-so-far, not a finished result"
        )
    if not signed:
        res.warnings.append(
            "unsigned (no [SIGNATURE]): the format allows it, but the interpreter cannot detect a modified file"
        )
    return res


def check_file(
    path: str | Path,
    system: SystemSpec | None = None,
    safety: SafetyChecks | None = None,
    *,
    limits_source: str | None = None,
    conventions: str | None = _AUTO,
    read_back: ReadBack | None = None,
) -> CheckResult:
    """Validate a ``.seq`` file.  ``system=None``: the limits the file records (dtoc-built files); a file that
    records none is refused (limits are never assumed: give a :class:`SystemSpec`).  ``safety``: PNS and
    acoustic checks (:class:`SafetyChecks`).

    Args:
        limits_source: where the limits came from, as the user gave them (e.g. "--gmax 32 --smax 130").
        conventions: where the vendor conventions of ``system`` (dead times, ring-down, ADC samples, rasters) come
            from, e.g. "--scanner terra"; None: not checked (listed in ``not_checked``).  Default: checked when
            ``system`` is given (its name is the source), not when the limits come from the file.
        read_back: called with the text's reading, ``read_back(None, path, version, seq, ir)`` (:data:`ReadBack`),
            once it is read (so that a writer's read-back shares the check's reading of its text).
    Raises:
        InputError: only when the file cannot be opened or parsed at all (missing, binary, truncated
            structure); every other problem is a :class:`Violation`.
    """
    with shared_parse():  # one parse of the text for its rules here and for the reader (and the writer's, in an export)
        st = parse_seq_text(path)
        res = _head(path, st, system, limits_source, conventions, st.signature_hash is not None)
        system, conventions = res.system, res.sources.get(CONVENTION)
        seg = _adc_segment(res.definitions.get("MaxAdcSegmentLength"))
        _text_rules(st, res.violations)
        seq = read_pypulseq(path, require_signature=False)[0]
        forget_shared_parse()  # the text's last reader: its parse (~20 bytes per file byte) is not kept
    if conventions:
        _raster_convention(file_rasters(seq), system, res.violations)
    try:
        ir = from_pypulseq(seq, free_mask=False)  # (no rule reads what an optimizer may change)
    except InputError as e:
        res.violations.append(Violation("block_raster", message=str(e)))
        return _tag(res)
    if read_back is not None:
        read_back(None, Path(path), st.version, seq, ir)
    _event_rules(seq, ir, system, res.violations, bool(conventions), seg)
    res.violations.extend(check_ir_limits(ir, system))
    if safety is not None and safety.pns is not None:
        _pns_rule(ir, safety.pns, safety.rotation, res)
    if safety is not None and safety.acoustic_bands_hz:
        _acoustic_rule(ir, safety.acoustic_bands_hz, safety.acoustic_max_power_fraction, safety.rotation, res)
    return _tag(res)


#: the rules :func:`check_ir_limits` finds, in the order it lists them (per rule and axis, each in block order)
_LIMIT_ORDER = {
    k: i
    for i, k in enumerate(
        [(r, a) for a in AXES for r in ("grad_amplitude", "slew_rate")] + [("grad_vector", None), ("slew_vector", None)]
    )
}


#: ``read_back(piece index or None, path of the text read, its format version, pypulseq Sequence, IR)``: what
#: :func:`check_file` and :func:`check_file_pieces` hand a caller of each reading they make (the IR as
#: :func:`dtoc.seq.read.from_pypulseq` gives it, without a free mask); it may raise to stop the check
ReadBack = Callable[[int | None, Path, tuple, Any, SequenceIR], None]


class _Played:
    """The gradient a text plays, stitched from its pieces' readings: what :func:`_pns_rule` and
    :func:`_acoustic_rule` read of a :class:`SequenceIR` (waveform, fine step, block edges and ids)."""

    def __init__(self, grad_mT_per_m, dt_fine_s, block_edges_s, ids):
        self.grad_mT_per_m, self.dt_fine_s, self.block_edges_s = grad_mT_per_m, dt_fine_s, block_edges_s
        self.meta = {"block_ids": ids}


def check_file_pieces(
    path: str | Path,
    spans: list[tuple[int, int, int, int]],
    system: SystemSpec | None = None,
    safety: SafetyChecks | None = None,
    *,
    limits_source: str | None = None,
    conventions: str | None = _AUTO,
    read_back: ReadBack | None = None,
) -> CheckResult:
    """:func:`check_file` of a long text, in the pieces ``spans`` (``(c0, b0, b1, c1)`` per piece, as the written
    text's read-back cuts it, :func:`dtoc.seq.write.verify_spans`): the same :class:`CheckResult`, holding one
    piece's parse and reading at a time instead of the text's (~570 bytes per raster step).

    Each piece (:mod:`dtoc.seq.pieces`: blocks ``c0`` .. ``c1 - 1`` with the library lines they use, each line
    copied byte for byte, so block ids are the text's) is parsed, read and checked as a file: the per-block rules
    (events, rasters, continuity, gradients ending at zero) and the limits (per sample and per raster segment) are
    kept for its own blocks ``b0`` .. ``b1 - 1`` only -- the context blocks either side give a boundary block its
    neighbour, as in the whole text, and their own rows are another piece's -- and the limits' times are the
    whole text's (``m0``).  The rules of the whole file: line endings and the md5 signature on the text's bytes;
    the definitions (and the rasters' convention, the warnings) from the first piece (every piece carries the
    [DEFINITIONS] verbatim); the integer fields per piece (each line is in some piece); PNS and acoustics, which
    integrate over time, on the stitched waveform of the pieces' own blocks (held only when ``safety`` asks for
    them: 48 bytes per raster step).  Whenever a piece finds a rule whose figures would name the piece rather than
    the text (a text rule's line number, a reading that fails, a malformed signature), and for one piece or a text
    :mod:`dtoc.seq.pieces` does not cut, the text is checked whole by :func:`check_file` instead: the result is
    always the whole check's.

    ``read_back`` (:data:`ReadBack`) is called with each piece's reading, ``read_back(k, piece path, version, seq,
    ir)`` for piece ``k`` of ``spans``, or with the whole text's (``k`` None) when ``spans`` is one piece; a
    check that goes whole after the first piece does not call it again (the caller sees which pieces it got)."""

    def whole(rb: ReadBack | None = None) -> CheckResult:
        return check_file(path, system, safety, limits_source=limits_source, conventions=conventions, read_back=rb)

    from dtoc.seq.pieces import mapped_text, text_facts

    if len(spans) <= 1:
        return whole(read_back)
    facts = text_facts(path)  # (the text is read in chunks, then mapped: never held whole)
    if facts.has_cr or not facts.signature_ok:
        return whole()
    with mapped_text(path) as (data, drop):
        return _check_in_pieces(
            path, spans, system, safety, limits_source, conventions, read_back, whole, data, drop, facts.signed
        )


def _check_in_pieces(
    path, spans, system, safety, limits_source, conventions, read_back, whole, data, drop, signed: bool
) -> CheckResult:
    """:func:`check_file_pieces` on the text ``data`` (a mapped text whose pages ``drop`` releases, after the
    index and after each piece); ``whole()``: the whole check, where the pieces cannot give its result."""
    from dtoc.seq.pieces import PieceError, TextIndex, share

    try:
        index = TextIndex(data, drop)
        extras = share(index.unused(), len(spans))
    except PieceError:
        return whole()
    drop()
    if index.n_blocks != spans[-1][3]:
        return whole()
    ids = [int(x) for x in index.rows["[BLOCKS]"].ids]
    need_played = safety is not None and (safety.pns is not None or bool(safety.acoustic_bands_hz))
    res: CheckResult | None = None
    events: list[Violation] = []
    limits: list[Violation] = []
    played: list[np.ndarray] = []
    edges: list[np.ndarray] = []
    m_b0 = 0  # the whole text's fine-grid index of the piece's first own block
    dtf = 0.0
    seg: int | None = None
    by_id = True  # every piece's reader numbered its blocks by their ids (else by position, as the whole's does)
    import os
    import tempfile

    for k, (span, extra) in enumerate(zip(spans, extras, strict=True)):
        c0, b0, b1, c1 = span
        try:
            piece = index.piece(c0, c1, extra)
        except PieceError:
            return whole()
        drop()
        fd, tmp = tempfile.mkstemp(suffix=".seq")
        try:
            with os.fdopen(fd, "wb") as f:
                f.write(piece)
            del piece
            try:
                with shared_parse():
                    st = parse_seq_text(tmp)
                    text: list[Violation] = []
                    _text_rules(st, text)
                    seq = read_pypulseq(tmp, require_signature=False)[0]
                    forget_shared_parse()
            except InputError:
                return whole()
            if text:
                return whole()
            if res is None:  # the first piece: what the whole file's [DEFINITIONS] and version say
                res = _head(path, st, system, limits_source, conventions, signed)
                system = res.system
                conventions = res.sources.get(CONVENTION)
                seg = _adc_segment(res.definitions.get("MaxAdcSegmentLength"))
                if conventions:
                    _raster_convention(file_rasters(seq), system, res.violations)
            version = st.version
            del st
            try:
                ir = from_pypulseq(seq, free_mask=False)  # (no rule reads what an optimizer may change)
            except InputError:
                return whole()
            if read_back is not None:  # (while the piece's file exists: the caller may read it too)
                read_back(k, Path(tmp), version, seq, ir)
        finally:
            os.unlink(tmp)
        keys = [int(x) for x in seq.block_events]
        if len(keys) != c1 - c0:
            return whole()
        if keys == ids[c0:c1]:  # the reader numbers blocks by their ids: the pieces' are the text's
            names = dict(zip(keys, keys, strict=True))
        else:  # by their position: the whole text's position
            names = {k: c0 + i + 1 for i, k in enumerate(keys)}
            by_id = False
        own = {names[k] for k in keys[b0 - c0 : b1 - c0]}
        found: list[Violation] = []
        _event_rules(seq, ir, system, found, bool(conventions), seg, names)
        last = k == len(spans) - 1
        events += [v for v in found if v.block in own or (v.block is None and last)]
        del seq
        m_e = np.round(np.asarray(ir.block_edges_s) / ir.dt_fine_s).astype(np.int64)
        lo, hi = int(m_e[b0 - c0]), int(m_e[b1 - c0])
        off = m_b0 - lo
        for v in check_ir_limits(ir, system, m0=off):
            v.block = names[v.block] if v.block is not None else None
            if v.block in own:
                limits.append(v)
        dtf = ir.dt_fine_s
        if need_played:
            played.append(np.array(ir.grad_mT_per_m[:, lo : hi + (1 if last else 0)]))
            edges.append(m_e[b0 - c0 : b1 - c0 + (1 if last else 0)] + off)
        m_b0 = off + hi
        del ir
    assert res is not None
    res.violations += events
    limits.sort(key=lambda v: _LIMIT_ORDER[(v.rule, v.axis)])  # stable: each rule and axis in block order
    res.violations += limits
    if need_played:
        assert safety is not None
        g = np.concatenate(played, axis=1)
        del played
        whole_ir: Any = _Played(g, dtf, np.concatenate(edges) * dtf, ids if by_id else list(range(1, len(ids) + 1)))
        if safety.pns is not None:
            _pns_rule(whole_ir, safety.pns, safety.rotation, res)
        if safety.acoustic_bands_hz:
            _acoustic_rule(whole_ir, safety.acoustic_bands_hz, safety.acoustic_max_power_fraction, safety.rotation, res)
    return _tag(res)


def _adc_segment(v: str | None) -> int | None:
    """The file's MaxAdcSegmentLength (samples), None when absent or not a positive whole number."""
    try:
        x = float((v or "").split()[0])
    except (ValueError, IndexError):
        return None
    return int(x) if x >= 1 and x == int(x) else None


def _tag(res: CheckResult) -> CheckResult:
    """Every violation gets its kind and the source of its rule."""
    for v in res.violations:
        v.kind = RULE_KINDS.get(v.rule, FORMAT)
        v.source = res.sources.get(v.kind, "")
    return res


def _acoustic_rule(ir: SequenceIR, bands, max_fraction: float, rotation, res: CheckResult) -> None:
    """Switching power inside a forbidden acoustic band (:mod:`dtoc.seq.acoustics`)."""
    from dtoc.seq.acoustics import band_power_fractions

    rows = band_power_fractions(ir.grad_mT_per_m, ir.dt_fine_s, bands, rotation)
    worst = max(rows, key=lambda r: r.power_fraction, default=None)
    if worst is None:
        res.checks.append("acoustic bands: no switching gradient")
        return
    lo, hi = worst.band_hz
    res.checks.append(
        f"acoustic bands: at most {100 * worst.power_fraction:.1f} % of an axis' switching power in a forbidden band "
        f"({AXES[worst.axis]}, {lo:g}-{hi:g} Hz; allowed {100 * max_fraction:g} %)"
    )
    for r in rows:
        if r.power_fraction > max_fraction:
            res.violations.append(
                Violation(
                    "acoustic",
                    None,
                    AXES[r.axis],
                    100 * r.power_fraction,
                    100 * max_fraction,
                    "%",
                    f"{100 * r.power_fraction:.1f} % of the {AXES[r.axis]} switching power in the forbidden band "
                    f"{r.band_hz[0]:g}-{r.band_hz[1]:g} Hz (peak at {r.peak_hz:.0f} Hz)",
                )
            )


def _pns_rule(ir: SequenceIR, model, rotation, res: CheckResult) -> None:
    """SAFE PNS on the physical axes (:mod:`dtoc.seq.pns`): a violation above the model's limit."""
    from dtoc.seq.pns import safe_pns

    r = safe_pns(ir.grad_mT_per_m, ir.dt_fine_s, model, rotation)
    where = f"at t = {1e3 * r.t_max_s:.3f} ms"
    res.checks.append(
        f"PNS (SAFE): max {r.max_percent:.1f} % of the stimulation limit {where} (allowed {model.limit_percent:g} %)"
    )
    if r.max_percent > model.limit_percent:
        b = int(np.searchsorted(np.asarray(ir.block_edges_s), r.t_max_s, side="right")) - 1
        ids = _block_numbers(ir)
        res.violations.append(
            Violation(
                "pns",
                ids[min(max(b, 0), len(ids) - 1)],
                None,
                r.max_percent,
                model.limit_percent,
                "%",
                f"SAFE PNS {r.max_percent:.1f} % of the stimulation limit {where}",
            )
        )


__all__ = [
    "RULE_KINDS",
    "INHERITED_RULES",
    "base_timing_refusal",
    "base_timing_violations",
    "file_rasters",
    "Violation",
    "CheckResult",
    "SafetyChecks",
    "check_ir_limits",
    "check_file",
    "check_file_pieces",
    "system_from_definitions",
]
