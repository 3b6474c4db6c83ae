"""Write a (modified) :class:`SequenceIR` back to a Pulseq 1.5 ``.seq`` file.

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
from pathlib import Path

import numpy as np

from dtoc.constants import AXES, hz_per_m_from_mT_per_m
from dtoc.errors import DtocError
from dtoc.seq.ir import SequenceIR
from dtoc.seq.pulseq import quiet, representable_amplitudes, seq_bytes
from dtoc.seq.system import SystemSpec

#: a block/axis counts as changed when any fine sample moved by more than this, mT/m
CHANGE_TOL_MT_PER_M = 1e-9


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
    diff = np.abs(ir.grad_mT_per_m - orig) > CHANGE_TOL_MT_PER_M
    out: dict[int, list[int]] = {}
    for b in range(len(m_edges) - 1):
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
    seq = copy.deepcopy(src)
    if not changes and not adc_offsets:
        return seq
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
    g = ir.grad_mT_per_m.copy()
    # pypulseq's set_block compares the new first/last with the neighbours' (still old) values using
    # system.max_slew * raster; blocks are rewritten one at a time, so lift that check on our copy
    # (continuity of the result is exact by construction and verified by dtoc.seq.check).
    saved_slew, saved_grad = seq.system.max_slew, seq.system.max_grad
    seq.system.max_slew, seq.system.max_grad = opts.max_slew, opts.max_grad
    # boundary samples that changed are rounded to 6 significant digits (Hz/m) on both sides at once
    for m in m_edges:
        for a in range(3):
            if abs(g[a, m] - orig[a, m]) > CHANGE_TOL_MT_PER_M:
                g[a, m] = _round6(np.array([hz_per_m_from_mT_per_m(g[a, m])]))[0] / hz_per_m_from_mT_per_m(1.0)
    for b in sorted(set(changes) | set(adc_offsets)):
        axes = changes.get(b, [])
        key = keys[b]
        with quiet():
            blk = seq.get_block(key)
        m0, m1 = int(m_edges[b]), int(m_edges[b + 1])
        dur = float(seq.block_durations[key])
        for a in axes:
            seg = ir.grad_mT_per_m[a, m0 : m1 + 1]
            edges_v, mids = seg[::2], seg[1::2]
            want = 0.5 * (edges_v[1:] + edges_v[:-1])
            if np.any(np.abs(mids - want) > 1e-9 + 1e-9 * np.abs(seg).max()):
                i = int(np.argmax(np.abs(mids - want)))
                raise DtocError(
                    f"block {key} axis {AXES[a]}: raster-centre sample {m0 + 2 * i + 1} is not the mean of its raster edges "
                    "(the writer plays straight lines between raster edges; build waveforms with dtoc.seq.ir.edges_to_fine)"
                )
            hz = hz_per_m_from_mT_per_m(g[a, m0 : m1 + 1 : 2])
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
    return seq


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


def seq_bytes_of(ir: SequenceIR, definitions: dict | None = None, adc_offsets=None) -> bytes:
    """The signed Pulseq 1.5 text of :func:`to_pypulseq` (ir), with ``definitions`` added to [DEFINITIONS]
    (names: letters and digits; values: numbers, or one word of letters and digits such as a hash)."""
    seq = to_pypulseq(ir, adc_offsets)
    for k, v in (definitions or {}).items():
        vals = [float(x) for x in np.ravel(v)] if isinstance(v, (list, tuple, np.ndarray)) else v
        ok_val = isinstance(vals, (int, float)) or (isinstance(vals, list) and vals and all(np.isfinite(vals)))
        ok_val = ok_val or (isinstance(vals, str) and vals.isalnum())  # a hash (DtocBaseSha256)
        if not str(k).isalnum() or not ok_val:
            raise DtocError(f"definition {k!r}: names are letters/digits and values numbers (or one word)")
        seq.set_definition(str(k), vals)
    return seq_bytes(seq)


def write_seq(ir: SequenceIR, path: str | Path, force: bool = False) -> Path:
    """Write ``ir`` as a signed Pulseq 1.5 ``.seq`` atomically (no overwrite without ``force``)."""
    from dtoc.util.atomic import atomic_write_bytes, check_output_path

    check_output_path(path, force)
    return atomic_write_bytes(path, seq_bytes_of(ir), force=force)
