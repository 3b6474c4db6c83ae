"""Write a (modified) :class:`SequenceIR` back to a Pulseq ``.seq`` file, in the format version the interpreter
reads (1.4.0-1.5.2: :func:`seq_bytes_of`, docs/contracts.md §6; default the input's), read back before it is
published.

:func:`to_pypulseq` copies ``ir.source`` (the pypulseq ``Sequence`` the IR was read or built from) and
replaces, block by block and axis by axis, only the gradients whose played waveform changed: such a
gradient is written as an **extended trapezoid with a vertex on every raster edge of its block**
(the IR's even fine samples), so the interpreter plays exactly the IR's piecewise-linear waveform;
its first/last values are the IR's boundary samples, shared with the neighbouring blocks (continuity
is exact by construction).  RF, ADC, labels, other extensions, untouched gradients and definitions
are carried over unchanged.

Precision of the file (pypulseq 1.5.0 format): amplitudes are written with 6 significant digits and
normalised shapes are quantised to 1e-7.  The writer rounds each rewritten gradient's peak vertex
(and any boundary sample it changed) to 6 significant digits first, so the amplitude is exact and
**every played vertex is within 5e-8 x |peak of its block| of the IR** (0.15 Hz/m = 3.5e-6 mT/m at
72 mT/m), except the peak vertex itself and changed boundary samples, which move by at most
5e-6 x |peak| (the 6-digit rounding).  The k-space effect is far below 0.01 dk (tests measure it).

The IR's raster-centre (odd) samples of a changed block must be the mean of their neighbours (that is
what an extended trapezoid plays); otherwise :class:`dtoc.errors.DtocError` is raised.
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from pathlib import Path

import numpy as np

from dtoc.constants import AXES, hz_per_m_from_mT_per_m
from dtoc.errors import DtocError, InputError
from dtoc.seq.ir import SequenceIR, edges_to_fine
from dtoc.seq.pieces import signature_ok, text_facts
from dtoc.seq.pulseq import quiet, representable_amplitudes, seq_file
from dtoc.seq.seqtext import sign_file
from dtoc.seq.system import SystemSpec
from dtoc.seq.versions import (
    KEPT_EXTENSIONS,
    LABELS_141,
    WRITABLE,
    WRITABLE_AS_INPUT,
    add_kept_extensions,
    check_writable,
    parse_version,
    quaternion_matrix,
    set_revision,
    set_revision_file,
    version_str,
)
from dtoc.util.interrupt import fault_point

#: a block/axis counts as changed when any fine sample moved by more than this, mT/m
CHANGE_TOL_MT_PER_M = 1e-9
#: fine samples per piece where a whole waveform is compared (temporaries of a piece, not of the sequence)
_PIECE = 1 << 19


def _round6(x: np.ndarray) -> np.ndarray:
    return np.array([float(f"{v:.6g}") for v in np.ravel(x)]).reshape(np.shape(x))


def _original_grad(ir: SequenceIR) -> np.ndarray:
    """The demanded gradient of ``ir.source`` as it was read (kept on the IR by the reader)."""
    if ir.source_grad_mT_per_m is None:
        raise DtocError("this IR has no source gradient to compare with (read it from a .seq or build it from a spec)")
    return ir.source_grad_mT_per_m


def changed_blocks(ir: SequenceIR) -> dict[int, list[int]]:
    """{block index: [axes]} whose played gradient differs from ``ir.source``."""
    orig = _original_grad(ir)
    if orig.shape != ir.grad_mT_per_m.shape:
        raise DtocError(f"IR gradient grid {ir.grad_mT_per_m.shape} does not match its source sequence {orig.shape}")
    m_edges = np.round(np.asarray(ir.block_edges_s) / ir.dt_fine_s).astype(np.int64)
    g = ir.grad_mT_per_m
    # in pieces: no whole-length float temporaries (a long sequence's 96 bytes per raster edge)
    diff = np.empty(g.shape, dtype=bool)
    for i in range(0, g.shape[1], _PIECE):
        e = slice(i, i + _PIECE)
        np.greater(np.abs(g[:, e] - orig[:, e]), CHANGE_TOL_MT_PER_M, out=diff[:, e])
    out: dict[int, list[int]] = {}
    for b in range(len(m_edges) - 1):
        if m_edges[b + 1] == m_edges[b]:  # a zero-duration block (labels only) holds no gradient
            continue
        axes = [a for a in range(3) if diff[a, m_edges[b] : m_edges[b + 1] + 1].any()]
        if axes:
            out[b] = axes
    return out


def to_pypulseq(ir: SequenceIR, adc_offsets: dict[int, tuple[float, float]] | None = None):
    """A pypulseq ``Sequence``: ``ir.source`` with every changed gradient replaced (module doc).

    ``adc_offsets``: {block index: (phase rad, frequency Hz)} added to that block's ADC phase and frequency
    offsets (the off-centre correction of :mod:`dtoc.optimize.offcentre`; the only non-gradient change)."""
    from dtoc.seq.pulseq import import_pypulseq

    pp = import_pypulseq()

    src = ir.source
    if src is None:
        raise DtocError("this IR has no source sequence to write into (read it from a .seq or build it from a spec)")
    if abs(float(src.grad_raster_time) - ir.raster_s) > 1e-15:
        raise DtocError("IR raster differs from its source sequence's gradient raster")
    changes = changed_blocks(ir)
    adc_offsets = {b: v for b, v in (adc_offsets or {}).items() if v[0] or v[1]}
    seq = _copy_without_cache(src)
    if not changes and not adc_offsets:
        return seq
    # pypulseq keeps every block it decodes (get_block) in its block cache: every rewritten block's events,
    # waveforms included, would stay until the copy dies (~100 bytes per raster step); not kept here
    seq.use_block_cache = False
    orig = _original_grad(ir)
    r = ir.raster_s
    opts = SystemSpec(
        grad_raster_s=r,
        rf_raster_s=float(src.rf_raster_time),
        adc_raster_s=float(src.adc_raster_time),
        block_raster_s=float(src.block_duration_raster),
        rf_dead_time_s=0.0,
        rf_ringdown_time_s=0.0,
    ).to_pypulseq_opts(enforce_limits=False)
    keys = list(seq.block_events.keys())
    m_edges = np.round(np.asarray(ir.block_edges_s) / ir.dt_fine_s).astype(np.int64)
    g = ir.grad_mT_per_m
    # pypulseq's set_block compares the new first/last with the neighbours' (still old) values using
    # system.max_slew * raster; blocks are rewritten one at a time, so lift that check on our copy
    # (continuity of the result is exact by construction and verified by dtoc.seq.check).
    saved_slew, saved_grad = seq.system.max_slew, seq.system.max_grad
    seq.system.max_slew, seq.system.max_grad = opts.max_slew, opts.max_grad
    # boundary samples that changed are rounded to 6 significant digits (Hz/m) on both sides at once (kept apart:
    # not a second whole-length copy of the waveform)
    rounded: dict[tuple[int, int], float] = {}
    for m in m_edges:
        for a in range(3):
            if abs(g[a, m] - orig[a, m]) > CHANGE_TOL_MT_PER_M:
                hz = _round6(np.array([hz_per_m_from_mT_per_m(g[a, m])]))[0]
                rounded[a, int(m)] = hz / hz_per_m_from_mT_per_m(1.0)
    rot = {int(b): quaternion_matrix(q) for b, q in (ir.meta.get("rotations") or {}).items()}
    for b in sorted(set(changes) | set(adc_offsets)):
        axes = changes.get(b, [])
        key = keys[b]
        with quiet():
            blk = seq.get_block(key)
        m0, m1 = int(m_edges[b]), int(m_edges[b + 1])
        dur = float(seq.block_durations[key])
        played, edges_g = g[:, m0 : m1 + 1], g[:, m0 : m1 + 1].copy()
        for a in range(3):
            for m in (m0, m1):
                if (a, m) in rounded:
                    edges_g[a, m - m0] = rounded[a, m]
        if b in rot and axes:  # a rotated block: its events are logical gradients, R^T of the played ones
            played, edges_g = rot[b].T @ played, rot[b].T @ edges_g
            axes = [0, 1, 2]
        for a in axes:
            seg = played[a]
            edges_v, mids = seg[::2], seg[1::2]
            want = 0.5 * (edges_v[1:] + edges_v[:-1])
            if np.any(np.abs(mids - want) > 1e-9 + 1e-9 * np.abs(seg).max()):
                i = int(np.argmax(np.abs(mids - want)))
                raise DtocError(
                    f"block {key} axis {AXES[a]}: raster-centre sample {m0 + 2 * i + 1} is not the mean of its raster edges "
                    "(the writer plays straight lines between raster edges; build waveforms with dtoc.seq.ir.edges_to_fine)"
                )
            hz = hz_per_m_from_mT_per_m(edges_g[a, ::2])
            ch = "g" + AXES[a]
            if np.all(np.abs(hz) < 1e-9):
                setattr(blk, ch, None)
                continue
            amps = representable_amplitudes(hz)
            times = np.arange(len(hz)) * r
            with quiet():
                ev = pp.make_extended_trapezoid(channel=AXES[a], times=times, amplitudes=amps, system=opts)
            setattr(blk, ch, ev)
        if b in adc_offsets:
            if getattr(blk, "adc", None) is None:
                raise DtocError(f"block {key}: an ADC correction for a block without ADC")
            adc = copy.copy(blk.adc)
            adc.phase_offset = float(adc.phase_offset) + adc_offsets[b][0]
            adc.freq_offset = float(adc.freq_offset) + adc_offsets[b][1]
            blk.adc = adc
        events = [getattr(blk, n) for n in ("rf", "gx", "gy", "gz", "adc") if getattr(blk, n, None) is not None]
        for extra in ("label", "trigger", "soft_delay"):
            v = getattr(blk, extra, None)
            if v is None:
                continue
            events.extend(v.values() if isinstance(v, dict) else (v if isinstance(v, (list, tuple)) else [v]))
        try:
            with quiet():
                set_block_in_place(seq, keys, b, *events, pp.make_delay(dur))
        except Exception as e:  # noqa: BLE001
            raise DtocError(f"block {key}: pypulseq refused the rewritten block: {e}") from None
        if abs(float(seq.block_durations[key]) - dur) > 1e-12:
            raise DtocError(f"block {key}: duration changed while rewriting ({dur} -> {seq.block_durations[key]})")
    seq.system.max_slew, seq.system.max_grad = saved_slew, saved_grad
    seq.use_block_cache = True
    return seq


def _copy_without_cache(src):
    """A deep copy of the pypulseq ``Sequence`` ``src`` without its block cache (decoded blocks, which pypulseq
    rebuilds on demand: the same sequence, without a second copy of every decoded block of the base)."""
    kept = src.block_cache
    src.block_cache = {}
    try:
        return copy.deepcopy(src)
    finally:
        src.block_cache = kept


def set_block_in_place(seq, keys: list, b: int, *events) -> None:
    """``seq.set_block(keys[b], *events)`` on an existing block, in time independent of the sequence's length.

    pypulseq 1.5's ``set_block`` finds an existing block's neighbours by ``list(block_events).index(key)``,
    three times a call, so rewriting every block of a long sequence is quadratic (minutes for 5 minutes of
    sequence).  Its neighbour look-up and slew checks read only the block and its two neighbours, so it is
    given a table holding just those three, in order; the rewritten entry then goes into the full table.
    The result is the same sequence (same libraries, same bytes)."""
    full = seq.block_events
    key = keys[b]
    local = type(full)((k, full[k]) for k in keys[max(b - 1, 0) : b + 2])
    seq.block_events = local
    try:
        seq.set_block(key, *events)
    finally:
        seq.block_events = full
    full[key] = local[key]


def seq_bytes_of(
    ir: SequenceIR,
    definitions: dict | None = None,
    adc_offsets=None,
    version: tuple[int, int, int] | str | None = None,
    verify: bool = True,
) -> bytes:
    """The signed Pulseq text of :func:`to_pypulseq` (ir) in format ``version`` (default :func:`output_version`),
    with ``definitions`` added to [DEFINITIONS] (names: letters and digits; values: numbers, or one word of letters and digits such as a hash).

    What the version cannot express is refused by name first (:func:`unwritable`); with ``verify`` the text is
    read back by dtoc's reader and by pypulseq and must play what ``ir`` plays (:func:`verify_written`).
    The bytes of :func:`write_seq_text` (a long sequence's export writes the file without holding its text).

    Raises:
        InputError: the version is not one dtoc writes, or cannot state something ``ir`` holds.
        DtocError: the written text does not read back to ``ir``."""
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "out.seq"
        v = write_seq_text(ir, p, definitions, adc_offsets, version)
        data = p.read_bytes()
    if verify:
        verify_written(ir, data, v, adc_offsets)
    return data


def write_seq_text(
    ir: SequenceIR,
    path: str | Path,
    definitions: dict | None = None,
    adc_offsets=None,
    version: tuple[int, int, int] | str | None = None,
) -> tuple[int, int, int]:
    """Write :func:`seq_bytes_of`'s text (unverified) to ``path``; returns the format version written.

    The text is never whole in memory (pypulseq writes it unsigned, the [VERSION] section is set on its first
    chunk, the md5 signature is computed in chunks: :func:`dtoc.seq.pulseq.seq_file`), except where 1.5.1's
    ROTATIONS / RF_SHIMS are chained into the block table (a whole-text edit).

    Raises:
        InputError, DtocError: as :func:`seq_bytes_of`."""
    v = writable_version(ir, version)
    seq = to_pypulseq(ir, adc_offsets)
    for k, val in (definitions or {}).items():
        vals = [float(x) for x in np.ravel(val)] if isinstance(val, (list, tuple, np.ndarray)) else val
        ok_val = isinstance(vals, (int, float)) or (isinstance(vals, list) and vals and all(np.isfinite(vals)))
        ok_val = ok_val or (isinstance(vals, str) and vals.isalnum())  # a hash (DtocBaseSha256)
        if not str(k).isalnum() or not ok_val:
            raise DtocError(f"definition {k!r}: names are letters/digits and values numbers (or one word)")
        seq.set_definition(str(k), vals)
    rotations, shims = ir.meta.get("rotations") or {}, ir.meta.get("rf_shims") or {}
    seq.use_block_cache = False  # pypulseq's write decodes every block (its timing check): none kept (to_pypulseq)
    p = Path(path)
    # 1.5.x from pypulseq's 1.5.0 writer, earlier versions from its 1.4.1 writer (without pypulseq's timing check,
    # which only warns, silenced: the same text); a version other than the writer's own has its [VERSION] set and
    # ends, as the text of a signed one stripped of its signature, with a newline
    seq_file(seq, p, v141=v < (1, 5, 0), in_place=True, check_timing=False, signed=False)
    del seq
    if rotations or shims:
        p.write_bytes(add_kept_extensions(set_revision(p.read_bytes() + b"\n", v), rotations, shims))
    elif v != (1, 5, 0):
        set_revision_file(p, v, newline=True)
    sign_file(p)
    return v


def output_version(ir: SequenceIR, version: tuple[int, int, int] | str | None = None) -> tuple[int, int, int]:
    """The format version to write: ``version`` if given; else the input file's (``ir.meta['format_version']``),
    1.4.1 for a 1.2.x/1.3.x input (dtoc writes no older format), 1.5.0 for a sequence built from a spec."""
    if version is not None:
        return parse_version(version) if isinstance(version, str) else tuple(int(x) for x in version)  # type: ignore[return-value]
    src = ir.meta.get("format_version")
    if not src:
        return (1, 5, 0)
    v = parse_version(src)
    return v if v in WRITABLE + WRITABLE_AS_INPUT else ((1, 4, 1) if v < (1, 5, 0) else WRITABLE[-1])


def writable_version(ir: SequenceIR, version: tuple[int, int, int] | str | None = None) -> tuple[int, int, int]:
    """The output version (:func:`output_version`) once dtoc writes it and ``ir`` holds nothing it cannot
    state (:func:`unwritable`).

    Raises:
        InputError: one line naming the first thing the version cannot state (and how many more)."""
    v = output_version(ir, version)
    check_writable(v)
    reasons = unwritable(ir, v)
    if reasons:
        more = f" (and {len(reasons) - 1} more)" if len(reasons) > 1 else ""
        raise InputError(f"cannot write Pulseq format {version_str(v)}: {reasons[0]}{more}")
    return v


def unwritable(ir: SequenceIR, version: tuple[int, int, int]) -> list[str]:
    """What ``ir`` holds that format ``version`` cannot state, one phrase each (empty: writable)."""
    v = tuple(version)
    out: list[str] = []
    n_rot, n_shim = len(ir.meta.get("rotations") or {}), len(ir.meta.get("rf_shims") or {})
    if v < (1, 5, 1) and n_rot:
        out.append(f"the rotation extension ({n_rot} rotated blocks) needs format 1.5.1 or later")
    if v < (1, 5, 1) and n_shim:
        out.append(f"the RF shimming extension ({n_shim} blocks) needs format 1.5.1 or later")
    src = ir.source
    if v >= (1, 5, 0) or src is None:
        return out
    if ir.meta.get("soft_delay_blocks"):
        out.append(
            f"soft delays (extension DELAYS, {len(ir.meta['soft_delay_blocks'])} blocks) need format 1.5.0 or later"
        )
    from dtoc.seq.pulseq import import_pypulseq

    pp = import_pypulseq()
    src_v = parse_version(ir.meta.get("format_version") or "1.5.0")  # what the input itself stated
    stated_use = src_v >= (1, 5, 0)  # before 1.5 a use is detected, not stated
    from dtoc.seq.rfuse import USES

    for k, lib in src.rf_library.data.items():
        use = src.rf_library.type.get(k, "u")
        if lib[6] or lib[7]:
            out.append(f"RF event {k} has a frequency/phase offset in ppm (format 1.5.0 on)")
        with quiet():
            rf = src.rf_from_lib_data(lib, use)
            stated = float(rf.center)
            del rf.center
            peak = float(pp.calc_rf_center(rf)[0])
        if abs(stated - peak) > 1.01 * float(src.rf_raster_time):
            out.append(
                f"RF event {k} rotates at {stated * 1e6:.6g} us, more than one RF raster from its peak "
                f"({peak * 1e6:.6g} us), and format 1.4 states no centre"
            )
        detected = _detected_use(src, rf)
        if stated_use and use != "u" and use in USES and use != detected:
            out.append(
                f"RF event {k} is stated as {USES[use]}, which format 1.4 cannot say (1.4 readers would take it as "
                f"{USES[detected]})"
            )
    for k, lib in src.adc_library.data.items():
        if lib[3] or lib[4]:
            out.append(f"ADC event {k} has a frequency/phase offset in ppm (format 1.5.0 on)")
        if len(lib) > 7 and lib[7]:
            out.append(f"ADC event {k} has a phase modulation shape (format 1.5.0 on)")
    if v < (1, 4, 1) <= src_v:  # (a 1.4.0 input using them keeps them: its interpreter read them)
        from pypulseq.supported_labels_rf_use import get_supported_labels

        labels = get_supported_labels()
        used = {
            labels[int(d[1]) - 1] for lib in (src.label_set_library, src.label_inc_library) for d in lib.data.values()
        }
        new = sorted(used & set(LABELS_141))
        if new:
            out.append(f"label(s) {', '.join(new)} were added in format 1.4.1")
    return out


def _detected_use(seq, rf) -> str:
    """The RF use (initial) a 1.4 reader detects (pypulseq's and Pulseq MATLAB's ``detectRFuse``: one rule,
    :func:`dtoc.seq.rfuse.detect_use`)."""
    from dtoc.seq.rfuse import USES, detect_use

    flip_rad = 2 * np.pi * float(np.abs(np.sum(rf.signal[:-1] * (rf.t[1:] - rf.t[:-1]))))
    use = detect_use(flip_rad, rf.shape_dur, rf.freq_offset, seq.system.B0, seq.system.gamma)
    return next(k for k, v in USES.items() if v == use)


#: raster steps per piece of a long written text read back (:mod:`dtoc.seq.pieces`): the read-back holds a piece's
#: reading (~600 bytes per raster step), not the sequence's; a text of one piece is read whole
VERIFY_PIECE_RASTER = 1 << 17


def verify_written(ir: SequenceIR, data: bytes, version, adc_offsets=None) -> None:
    """Read ``data`` back with dtoc's reader and with pypulseq (which reads no 1.5.1 extension: a text holding
    ROTATIONS or RF_SHIMS is read by dtoc's reader only): it must be format ``version`` and play ``ir``'s
    gradients (within the writer's precision, module doc), RF centres and ADC samples.  dtoc's read-back is
    compared and released before pypulseq reads the text (a long sequence's two readings are not held together).

    A text longer than :data:`VERIFY_PIECE_RASTER` raster steps is read in pieces (:mod:`dtoc.seq.pieces`:
    consecutive blocks with the library lines they use, each line of the text in some piece), each piece with
    the blocks either side of it as context (so a boundary sample, and a pre-1.5 edge a reader infers from the
    neighbouring block, read as in the whole text); every gradient sample, RF centre and ADC event is compared,
    and the whole text's signature checked once.

    Raises:
        DtocError: one line naming the first difference."""
    spans = verify_spans(ir)
    index = None
    in_order = all(
        a.block <= b.block for ev in (ir.rf, ir.adc) for a, b in zip(ev, ev[1:])
    )  # (as read: pieces' events)
    if len(spans) > 1 and in_order:
        from dtoc.seq.pieces import PieceError, TextIndex

        try:
            index = TextIndex(data)
        except PieceError:
            index = None  # a layout not cut in pieces: read whole
    if index is None:
        _verify_text(ir, data, version, None)
        return
    from dtoc.seq.pieces import share

    v = version_str(tuple(version))
    if not signature_ok(data):
        raise DtocError(f"the written format {v} text's signature does not match its content")
    if index.n_blocks != len(ir.block_edges_s) - 1:
        raise DtocError(f"the written format {v} text holds {index.n_blocks} blocks, not {len(ir.block_edges_s) - 1}")
    try:
        extras = share(index.unused(), len(spans))
    except PieceError as e:
        raise DtocError(f"the written format {v} text does not read back: {e}") from None
    gmax = _grad_peak(ir)
    for span, extra in zip(spans, extras, strict=True):
        try:
            piece = index.piece(span[0], span[3], extra)
        except PieceError as e:
            raise DtocError(f"the written format {v} text does not read back: {e}") from None
        _verify_text(ir, piece, version, (*span, gmax))


def verify_spans(ir: SequenceIR) -> list[tuple[int, int, int, int]]:
    """The pieces of :func:`verify_written`: (c0, b0, b1, c1) per piece -- blocks ``b0`` .. ``b1 - 1`` compared,
    ``c0`` .. ``c1 - 1`` read (the compared ones and, either side, the next block of non-zero duration and the
    zero-duration blocks between)."""
    e = np.round(np.asarray(ir.block_edges_s) / ir.raster_s).astype(np.int64)
    nb = len(e) - 1
    out, b0 = [], 0
    while b0 < nb:
        b1 = int(np.searchsorted(e, e[b0] + VERIFY_PIECE_RASTER, side="left"))
        b1 = min(max(b1, b0 + 1), nb)
        if nb - b1 > 0 and e[nb] - e[b1] < VERIFY_PIECE_RASTER // 4:  # no short last piece
            b1 = nb
        c0 = max(b0 - 1, 0)
        while c0 > 0 and e[c0 + 1] == e[c0]:
            c0 -= 1
        c1 = min(b1 + 1, nb)
        while c1 < nb and e[c1] == e[c1 - 1]:
            c1 += 1
        out.append((c0, b0, b1, c1))
        b0 = b1
    return out


def _grad_peak(ir: SequenceIR) -> float:
    g, piece = ir.grad_mT_per_m, 1 << 16  # (a piece's temporaries: 1.6 MB)
    return max([float(np.abs(g[:, i : i + piece]).max()) for i in range(0, g.shape[1], piece)] + [1e-9])


def _verify_text(ir: SequenceIR, data: bytes, version, span) -> None:
    """Read back ``data`` (the whole text, ``span`` None, or the piece ``span`` = (c0, b0, b1, c1, gmax)) with
    dtoc's reader and compare it, then with pypulseq (:func:`verify_written`)."""
    import os
    import tempfile

    from dtoc.seq.read import read_seq

    v = version_str(tuple(version))
    where = "" if span is None else f" (the piece of blocks {_block_id(ir, span[1])}-{_block_id(ir, span[2] - 1)})"
    fd, tmp = tempfile.mkstemp(suffix=".seq")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        try:
            back = read_seq(tmp)
        except DtocError as e:
            raise DtocError(
                f"the written format {v} text does not read back{where}: {str(e).replace(tmp, 'output')}"
            ) from None
        _compare_read_back(ir, back, v, version, span)
        del back
        if not _has_kept_extensions(data):
            _pypulseq_reads(tmp, version, where)
    finally:
        os.unlink(tmp)


#: the lines that open a 1.5.1 extension pypulseq 1.5.0 does not read (ROTATIONS, RF_SHIMS)
_KEPT_MARKERS = tuple(f"\nextension {k} ".encode() for k in KEPT_EXTENSIONS)


def _has_kept_extensions(data: bytes) -> bool:
    """The text holds a 1.5.1 extension pypulseq 1.5.0 does not read (ROTATIONS, RF_SHIMS)."""
    return any(m in data for m in _KEPT_MARKERS)


def _pypulseq_reads(path, version, where: str) -> None:
    """pypulseq itself reads the written text at ``path`` (as written: not dtoc's rendering of it for pypulseq).

    Raises:
        DtocError: one line naming pypulseq's error (``where``: the piece)."""
    from dtoc.seq.pulseq import import_pypulseq

    try:
        with quiet():  # (its 1.4 port leaves unused gradients' edges None, which its de-duplication rounds)
            import_pypulseq().Sequence().read(str(path), remove_duplicates=tuple(version) >= (1, 5, 0))
    except Exception as e:  # noqa: BLE001 - pypulseq raises anything
        v = version_str(tuple(version))
        raise DtocError(f"pypulseq cannot read the written format {v} text{where}: {type(e).__name__}: {e}") from None


class _Mismatch(Exception):
    """A piece's reading that :func:`verify_written` decides (a difference, or a reading it makes otherwise)."""


class _SharedReadBack:
    """:func:`verify_written`'s comparison on the check's reading of each piece (:data:`dtoc.seq.check.ReadBack`):
    the piece parsed once by dtoc and read once by dtoc's reader for both.  Anything but a clean comparison raises
    :class:`_Mismatch` (the caller then runs :func:`verify_written` itself, whose one line names the difference)."""

    def __init__(self, ir: SequenceIR, path: Path, version, spans: list):
        self.ir, self.version, self.spans = ir, tuple(version), spans
        self.v = version_str(self.version)
        facts = text_facts(path, _KEPT_MARKERS)  # (read in chunks: the text is not held)
        self.pypulseq_too = not facts.markers
        # the whole text's own checks (verify_written's, before any piece; the reader's of a text read whole): not
        # met here, verify_written decides
        self.whole_ok = not facts.has_cr and facts.signature_ok and facts.signature_types in ((), (b"md5",))
        self.gmax = _grad_peak(ir) if len(spans) > 1 else None
        self.done: set = set()

    def __call__(self, k: int | None, path: Path, version: tuple, seq, back: SequenceIR) -> None:
        fault_point("verify")
        if not self.whole_ok or (k is None) != (len(self.spans) <= 1):
            raise _Mismatch
        back.meta["format_version"] = version_str(tuple(version))
        span = None if k is None else (*self.spans[k], self.gmax)
        try:
            _compare_read_back(self.ir, back, self.v, self.version, span)
            if self.pypulseq_too:
                _pypulseq_reads(path, self.version, "")
        except DtocError:
            raise _Mismatch from None
        self.done.add(k)

    def complete(self) -> bool:
        return self.done == ({None} if len(self.spans) <= 1 else set(range(len(self.spans))))


def verify_and_check(
    ir: SequenceIR,
    path: Path,
    version,
    system,
    safety=None,
    check_pieces: Callable | None = None,
    judge: Callable | None = None,
):
    """:func:`verify_written` of the text written at ``path`` and the check of that file
    (:func:`dtoc.seq.check.check_file_pieces` in the read-back's pieces, :func:`verify_spans`; no vendor
    conventions), on one reading of each piece: the check hands each reading to the read-back's comparison (and
    pypulseq reads the piece as written).  Where the check reads the text otherwise (whole after a piece, a text
    rule, a reading that fails) or a comparison fails, the check is finished without it and :func:`verify_written`
    reads the text itself, so its refusal is the one line it gives alone.

    ``check_pieces``: the check (default :func:`dtoc.seq.check.check_file_pieces`, or one with its signature);
    ``judge(result)``: the caller's verdict on the check's result (it raises to refuse), given before a read-back
    the shared readings did not settle is made: a refusal by the check's rules comes first.

    Returns:
        the check's :class:`dtoc.seq.check.CheckResult`.
    Raises:
        DtocError: the read-back's refusal (one line)."""
    if check_pieces is None:
        from dtoc.seq.check import check_file_pieces as check_pieces

    spans = verify_spans(ir)
    in_order = all(a.block <= b.block for ev in (ir.rf, ir.adc) for a, b in zip(ev, ev[1:]))
    # (the text is not held while it is checked: the check reads it, and verify_written where it must)
    rb = _SharedReadBack(ir, Path(path), version, spans) if in_order or len(spans) <= 1 else None

    def check(read_back):
        return check_pieces(path, spans, system, safety, conventions=None, read_back=read_back)

    try:
        res = check(rb)
    except _Mismatch:
        res = check(None)
    except InputError:  # a text the check cannot parse at all: the read-back's refusal
        verify_written(ir, Path(path).read_bytes(), version)
        raise
    if judge is not None:
        judge(res)
    if rb is None or not rb.complete():
        verify_written(ir, Path(path).read_bytes(), version)
    return res


def _in_blocks(events: list, b0: int, b1: int) -> list:
    """The events (in block order, as the reader lists them) of blocks ``b0`` .. ``b1 - 1``: a piece's, found in
    time logarithmic in the sequence's events."""
    from bisect import bisect_left

    return events[bisect_left(events, b0, key=lambda e: e.block) : bisect_left(events, b1, key=lambda e: e.block)]


def _block_id(ir: SequenceIR, b: int) -> int:
    ids = ir.meta.get("block_ids", [])
    return int(ids[b]) if b < len(ids) else b + 1


def _compare_read_back(ir: SequenceIR, back: SequenceIR, v: str, version, span=None) -> None:
    """:func:`verify_written`'s comparison of dtoc's read-back ``back`` (format ``v``) with ``ir``; ``span``
    (c0, b0, b1, c1, gmax): ``back`` is the piece of blocks ``c0`` .. ``c1 - 1``, compared on ``b0`` .. ``b1 - 1``
    (the last piece also on the final sample) with the whole waveform's peak ``gmax``."""
    if back.meta.get("format_version") != v:
        raise DtocError(f"written text says format {back.meta.get('format_version')}, not {v}")
    nb = len(ir.block_edges_s) - 1
    c0, b0, b1, c1 = (0, 0, nb, nb) if span is None else span[:4]
    m_e = np.round(np.asarray(ir.block_edges_s) / ir.dt_fine_s).astype(np.int64)
    m_c, m0, m1 = int(m_e[c0]), int(m_e[b0]), int(m_e[b1]) + (1 if b1 == nb else 0)
    g, gb = ir.grad_mT_per_m, back.grad_mT_per_m
    if gb.shape != (3, int(m_e[c1]) - m_c + 1):
        raise DtocError(f"format {v} text reads back with {gb.shape[1]} gradient samples, not {int(m_e[c1]) - m_c + 1}")
    piece = _PIECE  # the comparison's temporaries are a piece's, not the sequence's
    tol = 2e-5 * (_grad_peak(ir) if span is None else span[4])
    lo = m0 - m_c
    if any(
        float(np.abs(gb[:, lo + i - m0 : lo + min(i + piece, m1) - m0] - g[:, i : min(i + piece, m1)]).max()) > tol
        for i in range(m0, m1, piece)
    ):
        d = np.abs(gb[:, lo : lo + m1 - m0] - g[:, m0:m1])  # the first largest difference, named (a failure only)
        a, m = np.unravel_index(int(np.argmax(d)), d.shape)
        m = int(m) + m0
        b = int(np.searchsorted(ir.block_edges_s, m * ir.dt_fine_s, side="right")) - 1
        raise DtocError(
            f"format {v} text plays another gradient: block {_block_id(ir, b)} "
            f"axis {AXES[a]} at {m * ir.dt_fine_s * 1e3:.4f} ms: {gb[a, m - m_c]:.6g} instead of {g[a, m]:.6g} mT/m"
        )
    rf0, adc0 = _in_blocks(ir.rf, b0, b1), _in_blocks(ir.adc, b0, b1)
    rf1 = [r for r in back.rf if b0 <= c0 + r.block < b1]
    adc1 = [a for a in back.adc if b0 <= c0 + a.block < b1]
    if len(rf1) != len(rf0) or len(adc1) != len(adc0):
        what = "" if span is None else f" in blocks {_block_id(ir, b0)}-{_block_id(ir, b1 - 1)}"
        raise DtocError(
            f"format {v} text reads back with {len(rf1)} RF / {len(adc1)} ADC events{what}, not {len(rf0)} / {len(adc0)}"
        )
    t_c = float(ir.block_edges_s[c0])
    rf_raster = float(ir.source.rf_raster_time) if ir.source is not None and tuple(version) < (1, 5, 0) else 1e-7
    for r0, r1 in zip(rf0, rf1, strict=True):
        if abs(r0.t_center_s - (r1.t_center_s + t_c)) > 1.01 * rf_raster:  # 1.4 states no centre: the peak's sample
            raise DtocError(
                f"format {v} text moves the RF centre of block {r0.block + 1}: {(r1.t_center_s + t_c) * 1e3:.6f} ms "
                f"instead of {r0.t_center_s * 1e3:.6f} ms"
            )
    for a0, a1 in zip(adc0, adc1, strict=True):
        if abs(a0.t_start_s - (a1.t_start_s + t_c)) > 1e-9 or a0.num_samples != a1.num_samples:
            raise DtocError(f"format {v} text moves the ADC of block {a0.block + 1}")


def preflight_write(ir: SequenceIR, version: tuple[int, int, int] | str | None = None) -> tuple[int, int, int]:
    """Before any work: the format version an output of ``ir`` will be written in (:func:`output_version`), after
    what the version cannot state was refused by name (:func:`unwritable`, on the whole file) and the base was
    written in it and read back with the free gradient samples of one block of each kind
    (:func:`_representative_free_edges`) moved by 0.1 % of the peak (rewritten as the export does; the others
    written as the base's).

    What is written and read back is the base's sub-sequence of those blocks, each with the neighbours it is
    written against, extended to block boundaries where no gradient plays (:func:`preflight_blocks`): the same
    libraries (every RF, gradient, ADC, label and extension event of the file), definitions and extensions,
    so its cost is that of the distinct blocks, not of the protocol's length (a 51 s field-camera EPI:
    seconds).  Where no such boundaries make the sub-sequence much shorter, the whole base is written; so it
    is when the sub-sequence fails, and a refusal (its message, its block numbers) is always the whole base's.

    Raises:
        InputError: one line naming what the version cannot state, or why the base does not read back."""
    v = writable_version(ir, version)
    rep = _representative_free_edges(ir)
    blocks = preflight_blocks(ir, rep)
    if blocks is not None:
        try:
            sub, sub_rep = _sub_ir(ir, blocks, rep)
            _write_moved(ir, sub, sub_rep, v)
            return v
        except Exception:  # noqa: BLE001 - decided on the whole base below (no refusal for the cut alone)
            pass
    try:
        _write_moved(ir, ir, rep, v)
    except InputError:
        raise
    except DtocError as err:
        raise InputError(f"the base cannot be written as Pulseq format {version_str(v)}: {err}") from None
    except Exception as err:  # noqa: BLE001 - pypulseq's writer raises anything
        raise InputError(
            f"the base cannot be written as Pulseq format {version_str(v)}: {type(err).__name__}: {err}"
        ) from None
    return v


def _write_moved(ir: SequenceIR, target: SequenceIR, rep: np.ndarray, v: tuple[int, int, int]) -> None:
    """``target`` (the base or its sub-sequence) with its edges ``rep`` moved by 0.1 % of the base's peak,
    written in format ``v`` and read back (:func:`seq_bytes_of`)."""
    e = target.edge_grad_mT_per_m.copy()
    e[rep] += 1e-3 * max(float(np.abs(ir.edge_grad_mT_per_m).max()), 1e-3)
    seq_bytes_of(target.with_grad(edges_to_fine(e)), version=v)


#: the pre-flight writes the whole base unless its sub-sequence is at most this fraction of it
PREFLIGHT_SUB_MAX_FRACTION = 0.5


def preflight_blocks(ir: SequenceIR, rep: np.ndarray) -> list[int] | None:
    """The blocks (0-based, in order) of the pre-flight's sub-sequence: every block with a representative free
    edge (``rep``, (3, N+1)) and its two neighbours, each run of them extended to block boundaries where every
    axis is at 0 or neither block has an arbitrary gradient without a time shape (so that the runs, put end to
    end, play what they play in the base: no edge value a pre-1.5 reader infers from the neighbour changes),
    or None when that is not much shorter than the base (then
    the whole base is written) or when the base has no source sequence."""
    src = ir.source
    nb = len(ir.block_edges_s) - 1
    if src is None or len(src.block_events) != nb or nb < 8:
        return None
    edges = np.round(np.asarray(ir.block_edges_s) / ir.raster_s).astype(np.int64)
    eg = ir.edge_grad_mT_per_m
    # a boundary where the runs may meet: every axis at 0 there, or no arbitrary gradient without a time shape on
    # either side (the only event whose edge value a pre-1.5 text leaves to the reader to take from the neighbour)
    lib, types = src.grad_library.data, src.grad_library.type
    untimed = {k for k, d in lib.items() if types.get(k) == "g" and len(d) > 4 and int(d[4]) == 0}
    inferred = np.array([any(int(x) in untimed for x in ev[2:5]) for ev in src.block_events.values()], dtype=bool)
    quiet_edge = ~np.any(eg[:, edges] != 0, axis=0)  # (nb + 1,): boundary b (start of block b)
    quiet_edge[1:-1] |= ~(inferred[:-1] | inferred[1:])
    anyrep = np.any(rep, axis=0)  # (N + 1,)
    has = np.logical_or.reduceat(anyrep, np.minimum(edges[:-1], len(anyrep) - 1))
    has &= edges[1:] > edges[:-1]  # (reduceat of an empty block -- a last one too -- reads the next element)
    keep = np.zeros(nb, dtype=bool)
    for b in np.flatnonzero(has):
        lo, hi = max(int(b) - 1, 0), min(int(b) + 1, nb - 1)
        while lo > 0 and not quiet_edge[lo]:
            lo -= 1
        while hi < nb - 1 and not quiet_edge[hi + 1]:
            hi += 1
        keep[lo : hi + 1] = True
    sel = np.flatnonzero(keep)
    if sel.size == 0:
        return None
    span = float(np.sum(edges[sel + 1] - edges[sel]))
    if span > PREFLIGHT_SUB_MAX_FRACTION * max(float(edges[-1]), 1.0):
        return None
    return [int(b) for b in sel]


def _sub_ir(ir: SequenceIR, blocks: list[int], rep: np.ndarray) -> tuple[SequenceIR, np.ndarray]:
    """The IR of the base's blocks ``blocks`` put end to end (same libraries, definitions, extensions, read as
    :func:`dtoc.seq.read.read_seq` reads the base), and ``rep`` (3, N+1) mapped onto its raster edges."""
    from collections import OrderedDict

    from dtoc.seq.read import from_pypulseq

    src = ir.source
    keys = list(src.block_events.keys())
    sub = copy.copy(src)  # the libraries are shared (read only here: the writer works on a deep copy)
    sub.block_events = OrderedDict((i + 1, src.block_events[keys[b]]) for i, b in enumerate(blocks))
    sub.block_durations = {i + 1: src.block_durations[keys[b]] for i, b in enumerate(blocks)}
    sub.block_cache, sub.block_trace = {}, OrderedDict()
    sub.next_free_block_ID = len(blocks) + 1
    src_rot = getattr(src, "dtoc_rotations", None) or {}
    sub.dtoc_rotations = {i: src_rot[b] for i, b in enumerate(blocks) if b in src_rot}
    out = from_pypulseq(sub, free_unused_axes=True, rotations=sub.dtoc_rotations)
    for k in ("format_version", "unsigned"):
        if k in ir.meta:
            out.meta[k] = ir.meta[k]
    for k in ("rotations", "rf_shims"):
        own = ir.meta.get(k) or {}
        mapped = {i: own[b] for i, b in enumerate(blocks) if b in own}
        if mapped:
            out.meta[k] = mapped
    edges = np.round(np.asarray(ir.block_edges_s) / ir.raster_s).astype(np.int64)
    sub_edges = np.round(np.asarray(out.block_edges_s) / out.raster_s).astype(np.int64)
    sub_rep = np.zeros((3, int(sub_edges[-1]) + 1), dtype=bool)
    for i, b in enumerate(blocks):
        sub_rep[:, sub_edges[i] : sub_edges[i + 1] + 1] |= rep[:, edges[b] : edges[b + 1] + 1]
    if out.grad_mT_per_m.shape[1] != 2 * int(sub_edges[-1]) + 1:
        raise DtocError("the pre-flight's sub-sequence does not line up with the base's blocks")
    return out, sub_rep


def _representative_free_edges(ir: SequenceIR) -> np.ndarray:
    """(3, N+1) bool: the free raster edges of one block of each kind -- the same duration and events up to
    their amplitudes and phases (:func:`_block_kind`) between neighbours of the same kinds: what the writer's
    result depends on -- so that the pre-flight rewrites a few blocks of a long protocol, not thousands of
    readouts that differ only in their phase-encoding amplitude or RF-spoiling phase."""
    free = ir.free_mask[:, ::2]
    src = ir.source
    edges = np.round(np.asarray(ir.block_edges_s) / ir.raster_s).astype(np.int64)
    if src is None or len(src.block_events) != len(edges) - 1:
        return free
    rot = {int(b): tuple(float(x) for x in q) for b, q in (ir.meta.get("rotations") or {}).items()}
    memo: dict = {}
    kinds = [
        (round(float(src.block_durations[k]) / ir.raster_s), _block_kind(src, src.block_events[k], memo), rot.get(b))
        for b, k in enumerate(src.block_events)
    ]
    out = np.zeros_like(free)
    seen: set = set()
    for b, kind in enumerate(kinds):
        ctx = (kinds[b - 1] if b else None, kind, kinds[b + 1] if b + 1 < len(kinds) else None)
        if ctx not in seen:
            seen.add(ctx)
            out[:, edges[b] : edges[b + 1] + 1] = free[:, edges[b] : edges[b + 1] + 1]
    return out


def _block_kind(src, ev, memo: dict) -> tuple:
    """A block's events up to amplitudes and phases: RF shapes and delay; per axis a trapezoid (delayed or not:
    it starts and ends at 0, its ramps are written as any vertex list), or an arbitrary gradient's shapes, delay
    and whether it starts/ends at 0; ADC samples, dwell and delay; the extension list's types (a label's value
    is not the writer's business; a trigger is kept as it is)."""

    def lib_kind(name: str, i: int):
        if not i:
            return 0
        key = (name, i)
        if key not in memo:
            lib = getattr(src, name)
            d = tuple(float(x) for x in lib.data[i])
            if name == "rf_library":
                memo[key] = ("rf", d[1:4], d[5], lib.type.get(i))
            elif name == "adc_library":
                memo[key] = ("adc", d[:3])
            elif lib.type.get(i) == "t":  # (starts and ends at 0: its timing is rewritten as any vertex list)
                memo[key] = ("t", d[4] > 0.0)
            else:  # (amp, first, last, shape, time, delay)
                memo[key] = ("g", d[3:6], d[1] == 0.0, d[2] == 0.0)
        return memo[key]

    e = [int(x) for x in ev]
    return (
        lib_kind("rf_library", e[1]),
        *(lib_kind("grad_library", i) for i in e[2:5]),
        lib_kind("adc_library", e[5]),
        *(_extension_kinds(src, i, memo) for i in e[6:]),
    )


def _extension_kinds(src, ext_id: int, memo: dict) -> tuple:
    """The types of a block's extension list (labels: their type, not their values; other extensions: the
    event itself)."""
    if not ext_id:
        return ()
    key = ("ext", ext_id)
    if key not in memo:
        lib = src.extensions_library.data
        names = dict(zip(getattr(src, "extension_numeric_idx", []), getattr(src, "extension_string_idx", [])))
        out, seen, i = [], set(), ext_id
        while i and i in lib and i not in seen:
            seen.add(i)
            t, ref, nxt = (int(x) for x in lib[i][:3])
            out.append(names.get(t, t) if names.get(t) in ("LABELSET", "LABELINC") else (names.get(t, t), ref))
            i = nxt
        memo[key] = tuple(out)
    return memo[key]


def write_seq(ir: SequenceIR, path: str | Path, force: bool = False, version=None) -> Path:
    """Write ``ir`` as a signed Pulseq ``.seq`` (format ``version``, default :func:`output_version`) atomically
    (no overwrite without ``force``), after it read back (:func:`seq_bytes_of`)."""
    from dtoc.util.atomic import atomic_write_bytes, check_output_path

    check_output_path(path, force)
    return atomic_write_bytes(path, seq_bytes_of(ir, version=version), force=force)
