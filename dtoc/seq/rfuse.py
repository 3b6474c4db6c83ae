"""The use of each RF pulse (excitation, refocusing, ...) where the file does not state it.

Pulseq files before format 1.5.0 carry no RF ``use``.  The k-space of a spin echo depends on it (a refocusing
pulse negates k, an excitation sets it to 0), so such files are read as the reference tools read them: Pulseq
MATLAB's ``read(..., 'detectRFuse')`` and pypulseq's ``read(detect_rf_use=True)`` (its default for files before
1.5.0) decide per RF event of the file's ``[RF]`` library, from the pulse alone:

* flip angle below 90.01 deg (the integral of the B1 shape): excitation;
* otherwise a pulse longer than 6 ms, off resonance by -3.4 to -3.5 ppm (a fat saturation): saturation;
* otherwise: refocusing.

dtoc adds one refinement that cannot change k at any ADC sample: a pulse of 90.01 deg or more that is followed by
an excitation before any ADC sample (an inversion or saturation preparation, e.g. an MPRAGE inversion) is called
'inversion' (k is reset by the excitation anyway).  Every decision is stated per RF event in the notes; the user
overrides any with ``--rf-use ID=use,...`` (ID: the event's number in the file's ``[RF]`` section).  Files of format
1.5 state the use: it is kept (an explicit 'undefined' is taken as an excitation, as the reference tools' k-space
calculations do, and said so).
"""

from __future__ import annotations

import bisect
import dataclasses
import math

from dtoc.errors import InputError

#: the uses Pulseq defines (1.5 format), by their initial as the file writes them
USES = {
    "e": "excitation",
    "r": "refocusing",
    "i": "inversion",
    "s": "saturation",
    "p": "preparation",
    "o": "other",
    "u": "undefined",
}
_FLIP_EXCITATION_DEG = 90.01  # the reference tools' threshold (0.01 deg for rounding of very short pulses)
_FATSAT_MIN_DURATION_S = 6e-3
_FATSAT_PPM = (-3.5, -3.4)


def parse_rf_use_overrides(text: str | None) -> dict[int, str]:
    """``"3=refocusing,5=e"`` -> ``{3: 'refocusing', 5: 'excitation'}`` (uses by name or initial).

    Raises:
        InputError: a malformed item or an unknown use (one line).
    """
    out: dict[int, str] = {}
    if not text:
        return out
    names = set(USES.values())
    for item in text.split(","):
        item = item.strip()
        if not item:
            continue
        key, sep, val = item.partition("=")
        val = val.strip().lower()
        if not sep or not key.strip().isdigit() or not val:
            raise InputError(f"--rf-use: {item!r} is not ID=use (ID: a number of the file's [RF] section)")
        use = USES.get(val, val)
        if use not in names:
            raise InputError(f"--rf-use: unknown use {val!r} (one of {', '.join(sorted(names))})")
        out[int(key)] = use
    return out


def detect_use(flip_rad: float, duration_s: float, freq_offset_hz: float, b0_T: float, gamma_hz_per_T: float) -> str:
    """The use a pre-1.5 reader gives a pulse (Pulseq's ``detectRFuse``, pypulseq's ``detect_rf_use``): full name."""
    flip_deg = math.degrees(abs(flip_rad))
    if flip_deg < _FLIP_EXCITATION_DEG:
        return "excitation"
    ppm = 1e6 * freq_offset_hz / (b0_T * gamma_hz_per_T)
    if duration_s > _FATSAT_MIN_DURATION_S and _FATSAT_PPM[0] <= ppm <= _FATSAT_PPM[1]:
        return "saturation"
    return "refocusing"


def rf_event_ids(ir, block_rf_ids: dict[int, int] | None) -> list[int]:
    """The file's ``[RF]`` event number of each of ``ir.rf`` (from the block table ``block id -> RF id``); where
    unknown, pulses with the same flip, duration and frequency share a number (1, 2, ... in order of appearance)."""
    bids = ir.meta.get("block_ids") or []
    out: list[int] = []
    seen: dict[tuple, int] = {}
    for r in ir.rf:
        rid = None
        if block_rf_ids is not None and r.block < len(bids):
            rid = block_rf_ids.get(int(bids[r.block]))
        if rid is None:
            key = (round(r.flip_angle_rad, 6), round(r.duration_s, 9), round(r.freq_offset_hz, 3))
            rid = seen.setdefault(key, len(seen) + 1)
        out.append(int(rid))
    return out


def block_rf_ids_of_text(st) -> dict[int, int] | None:
    """``block id -> RF event id`` from a parsed file's ``[BLOCKS]`` (column 3 in every format version)."""
    try:
        out = {}
        for ln in st.sections.get("[BLOCKS]", []):
            t = ln.tokens
            if len(t) >= 3 and int(t[2]) > 0:
                out[int(t[0])] = int(t[2])
        return out
    except (ValueError, AttributeError):
        return None


def resolve_rf_use(
    ir,
    version: tuple[int, int, int],
    block_rf_ids: dict[int, int] | None = None,
    overrides: dict[int, str] | None = None,
    b0_T: float = 1.5,
    gamma_hz_per_T: float = 42.576e6,
) -> bool:
    """Give every RF pulse of ``ir`` its use (module doc): detected where the format has none (before 1.5.0), the
    user's ``overrides`` (RF event id -> use) over anything.  Records ``ir.meta['rf_use']`` (one entry per RF event
    of the file: id, use, how it was decided, flip, duration, count) and one note per RF event.  ``b0_T`` and
    ``gamma_hz_per_T`` only serve the fat-saturation test (the reference tools' defaults: 1.5 T).

    Returns:
        True when a use changed (the caller recomputes what depends on it, e.g. the free mask).
    Raises:
        InputError: an override names an RF event the file does not have.
    """
    overrides = dict(overrides or {})
    ids = rf_event_ids(ir, block_rf_ids)
    known = set(ids)
    unknown = sorted(set(overrides) - known)
    if unknown:
        have = ", ".join(str(i) for i in sorted(known)) or "none"
        raise InputError(f"--rf-use: the file has no RF event {unknown[0]} (its [RF] events: {have})")
    pre15 = tuple(version[:2]) < (1, 5)
    ir.meta.pop("rf_use_undefined", None)
    notes = ir.meta.setdefault("notes", [])
    notes[:] = [n for n in notes if not n.startswith(_UNDEFINED_NOTE_START)]
    new_rf = []
    per_id: dict[int, dict] = {}
    adc_t = sorted(a.t_start_s for a in ir.adc)
    for r, rid in zip(ir.rf, ids, strict=True):
        if rid in overrides:
            use, how = overrides[rid], "--rf-use"
        elif pre15:  # the format has no use field: whatever a reader filled in is a guess
            use = detect_use(r.flip_angle_rad, r.duration_s, r.freq_offset_hz, b0_T, gamma_hz_per_T)
            how = "detected"
        else:
            use, how = r.use, "file"
        new_rf.append(dataclasses.replace(r, use=use))
        e = per_id.setdefault(
            rid,
            {
                "id": rid,
                "use": use,
                "how": how,
                "flip_deg": round(math.degrees(abs(r.flip_angle_rad)), 3),
                "duration_us": round(1e6 * r.duration_s, 3),
                "count": 0,
            },
        )
        e["count"] += 1
    # the refinement: a detected 'refocusing' pulse followed by an excitation before any ADC sample (inversion)
    next_exc = [math.inf] * len(new_rf)  # centre of the next excitation after each pulse (one backward pass)
    t_next = math.inf
    for i in range(len(new_rf) - 1, -1, -1):
        next_exc[i] = t_next
        if new_rf[i].use == "excitation":
            t_next = new_rf[i].t_center_s
    for i, (r, rid) in enumerate(zip(new_rf, ids, strict=True)):
        e = per_id[rid]
        if e["how"] != "detected" or e["use"] != "refocusing":
            continue
        j = bisect.bisect_right(adc_t, r.t_center_s)
        first_adc = adc_t[j] if j < len(adc_t) else math.inf
        e.setdefault("_inv", []).append(next_exc[i] < first_adc)
    for e in per_id.values():
        inv = e.pop("_inv", None)
        if inv and all(inv):
            e["use"] = "inversion"
    if any(per_id[rid]["use"] != r.use for r, rid in zip(new_rf, ids, strict=True)):
        new_rf = [dataclasses.replace(r, use=per_id[rid]["use"]) for r, rid in zip(new_rf, ids, strict=True)]
    changed = any(a.use != b.use for a, b in zip(ir.rf, new_rf, strict=True))
    ir.rf = new_rf
    table = sorted(per_id.values(), key=lambda e: e["id"])
    ir.meta["rf_use"] = table
    if table and (pre15 or overrides):
        notes.append(describe_rf_use(table, version))
    n_undef = sum(r.use == "undefined" for r in new_rf)
    if n_undef:
        ir.meta["rf_use_undefined"] = n_undef
        notes.append(undefined_note(n_undef))
    _sync_source(ir)
    return changed


def _sync_source(ir) -> None:
    """Give the pypulseq Sequence the IR was read from the resolved uses (its RF library's types), so that a file
    written from it states them (format 1.5) instead of the reader's guess or nothing."""
    seq = ir.source
    lib = getattr(seq, "rf_library", None)
    bids = ir.meta.get("block_ids") or []
    if lib is None or not hasattr(lib, "type") or not hasattr(seq, "block_events"):
        return
    initial = {v: k for k, v in USES.items()}
    touched = False
    for r in ir.rf:
        if r.block >= len(bids):
            return
        ev = seq.block_events.get(int(bids[r.block]))
        if ev is None or len(ev) < 2 or not ev[1]:
            continue
        lib.type[int(ev[1])] = initial.get(r.use, "u")
        touched = True
    if touched and hasattr(seq, "block_cache"):
        seq.block_cache.clear()  # blocks read before carry the old use


_UNDEFINED_NOTE_START = "RF pulse(s) with use 'undefined'"


def undefined_note(n: int) -> str:
    """The note for pulses whose use stays 'undefined' (format 1.5 files that say so)."""
    return (
        f"{_UNDEFINED_NOTE_START}: {n}, taken as excitations (k = 0 after them, slice axis held), as pypulseq's "
        "calculate_kspace and Pulseq's calcKspace do; give --rf-use ID=use to say otherwise"
    )


def describe_rf_use(table: list[dict], version) -> str:
    """One note line: each RF event's use and how it was decided."""
    how_words = {
        "detected": "detected",
        "--rf-use": "from --rf-use",
        "file": "from the file",
    }
    parts = [
        f"RF {e['id']} ({e['flip_deg']:.4g} deg, {e['duration_us'] / 1e3:.4g} ms, x{e['count']}): {e['use']} "
        f"({how_words[e['how']]})"
        for e in table
    ]
    head = (
        f"format {'.'.join(str(v) for v in version)} states no RF use: detected from each pulse as Pulseq's "
        "read(...,'detectRFuse') and pypulseq's detect_rf_use do (flip < 90.01 deg: excitation; else fat "
        "saturation or refocusing; a refocusing-strength pulse followed by an excitation before any ADC: "
        "inversion); override with --rf-use ID=use"
        if tuple(version[:2]) < (1, 5)
        else "RF use"
    )
    return f"{head}: " + "; ".join(parts)


__all__ = [
    "USES",
    "detect_use",
    "parse_rf_use_overrides",
    "resolve_rf_use",
    "rf_event_ids",
    "block_rf_ids_of_text",
    "describe_rf_use",
    "undefined_note",
]
