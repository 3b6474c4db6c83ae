"""Pulseq format versions: every released text layout in (1.2.0-1.5.2), the version the interpreter reads out.

Reading (:func:`reader_text`): pypulseq 1.5.0's reader handles the older layouts only partly (its 1.4 port
leaves the RF use table empty, so writing such a sequence fails with ``KeyError``; it extrapolates edge
values of arbitrary gradients that the file never states; it cannot read a 1.4 gradient that no block uses
on one axis, nor 1.5.1 oversampled gradients or the 1.5.1 extensions).  dtoc therefore rewrites every file
into the 1.5.0 text layout itself, from its own parse (:mod:`dtoc.seq.seqtext`), and pypulseq reads that:

* 1.2.x / 1.3.x: the block's second column is a [DELAYS] id (1.2.x has no extension column); the block
  duration is the longest of its events and its delay, on the block raster; RF and arbitrary gradients
  have no time shape; missing raster definitions take the reference readers' defaults (10 us gradient and
  block raster, 1 us RF raster, 100 ns ADC raster); shapes are always run-length compressed.
* 1.2.x-1.4.x: RF pulses get their centre (time of the peak magnitude, as Pulseq's ``calcRfCenter``) and
  use ``u`` (undefined: the format had no field for it); ADC events get zero ppm offsets and no phase shape.
* Arbitrary gradients of 1.2.x-1.4.x state no edge values (``first``/``last``: samples sit at raster
  centres).  The edge a gradient shares with its neighbour takes the value the neighbour states there
  (a trapezoid's 0, an extended trapezoid's vertex); between two such gradients the mean of the two
  centre samples next to it (the straight line the samples describe); an edge with nothing played beyond it
  is 0.  No centre sample is extrapolated to an edge (pypulseq and Pulseq MATLAB extrapolate half a raster,
  which reports steps the scanner never plays: issue "what dtoc says must be true").  One gradient used
  with different edges is split into one event per edge pair.
* 1.5.1: ``time_id`` -1 (oversampled arbitrary gradients, samples every half raster) becomes an explicit
  time shape; the ROTATIONS and RF_SHIMS extensions are taken out of the text and kept per block
  (:class:`Layout`), the rotations applied to the gradients by :func:`dtoc.seq.read.from_pypulseq` and both
  written back by :func:`dtoc.seq.write.seq_bytes_of`.  Extensions named in ``RequiredExtensions`` that dtoc
  does not know are refused by name.
* The binary format of the specification's "Binary files" section: its text (:func:`binary_to_text`).

Writing (:func:`format_text`): 1.5.0 text from pypulseq, set to the target revision (1.5.1 / 1.5.2 add the
extensions kept on read); 1.4.x through pypulseq's 1.4.1 writer, after :func:`unwritable` found nothing the
target cannot express (RF use other than what 1.4 readers detect, ppm offsets, ADC phase shapes, soft delays,
1.4.1 labels in 1.4.0, rotations and RF shimming before 1.5.1).
"""

from __future__ import annotations

import math
import os
import re
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dtoc.errors import InputError

#: Released format versions (the specification's revision table; Pulseq 1.4.2 software writes format 1.4.1).
RELEASED = (
    (1, 2, 0),
    (1, 2, 1),
    (1, 3, 0),
    (1, 3, 1),
    (1, 4, 0),
    (1, 4, 1),
    (1, 5, 0),
    (1, 5, 1),
    (1, 5, 2),
)
#: Versions dtoc writes.
WRITABLE = ((1, 4, 0), (1, 4, 1), (1, 5, 0), (1, 5, 1), (1, 5, 2))
#: Also written when the input says so: the label pypulseq 1.4.2 and MRzero put on the 1.4.1 layout.
WRITABLE_AS_INPUT = ((1, 4, 2),)
#: Extensions dtoc reads (pypulseq's four, and the two 1.5.1 ones kept per block).
KNOWN_EXTENSIONS = ("TRIGGERS", "LABELSET", "LABELINC", "DELAYS", "ROTATIONS", "RF_SHIMS")
KEPT_EXTENSIONS = ("ROTATIONS", "RF_SHIMS")
#: Labels that 1.4.1 added (not expressible in 1.4.0).
LABELS_141 = ("PMC", "NOROT", "NOPOS", "NOSLC", "ONCE")
#: The binary file header of the specification's "Binary files" section.
BINARY_MAGIC = b"\x01pulseq\x02"
#: Defaults of the reference readers for pre-1.4 files without raster definitions, s.
OLD_RASTER_DEFAULTS = {
    "GradientRasterTime": 10e-6,
    "RadiofrequencyRasterTime": 1e-6,
    "AdcRasterTime": 100e-9,
    "BlockDurationRaster": 10e-6,
}


def version_str(v) -> str:
    return ".".join(str(int(x)) for x in v)


def parse_version(s: str) -> tuple[int, int, int]:
    """'1.4' / '1.4.1' -> (1, 4, 1) (a missing revision is the newest released of that minor)."""
    m = re.fullmatch(r"\s*(\d+)\.(\d+)(?:\.(\d+))?\s*", str(s))
    if not m:
        raise InputError(f"format version {s!r}: expected MAJOR.MINOR[.REVISION], e.g. 1.4.1 or 1.5.0")
    if m.group(3) is None:
        same = [v for v in WRITABLE if v[:2] == (int(m.group(1)), int(m.group(2)))]
        if not same:
            raise InputError(f"format version {s}: dtoc writes {', '.join(map(version_str, WRITABLE))}")
        return same[-1]
    return int(m.group(1)), int(m.group(2)), int(m.group(3))


def check_writable(v: tuple[int, int, int]) -> None:
    if tuple(v) not in WRITABLE + WRITABLE_AS_INPUT:
        raise InputError(
            f"format version {version_str(v)}: dtoc writes {', '.join(map(version_str, WRITABLE))} "
            "(1.2.x and 1.3.x are read, not written: their interpreters are a decade old)"
        )


def check_known(v: tuple[int, int, int], path) -> None:
    """Refuse a version outside the released ones by name."""
    if tuple(v) not in RELEASED and not ((1, 2) <= tuple(v[:2]) <= (1, 4)):  # 1.2-1.4 layouts are final
        raise InputError(
            f"{path}: Pulseq format version {version_str(v)} is not supported "
            f"(dtoc reads the released versions {version_str(RELEASED[0])} to {version_str(RELEASED[-1])})"
        )


@dataclass
class Layout:
    """What a file's version and extensions mean beyond what pypulseq reads.

    Attributes:
        version: the file's format version.
        rotations: {block index: (q0, qx, qy, qz)} of the ROTATIONS extension (1.5.1).
        shims: {block index: (num_chan, mag1, phase1, ...)} of the RF_SHIMS extension (1.5.1).
        notes: what the reader inferred (one line each).
    """

    version: tuple[int, int, int] = (1, 5, 0)
    rotations: dict[int, tuple[float, ...]] = field(default_factory=dict)
    shims: dict[int, tuple[float, ...]] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)

    def rotation_matrices(self) -> dict[int, np.ndarray]:
        return {b: quaternion_matrix(q) for b, q in self.rotations.items()}


def quaternion_matrix(q) -> np.ndarray:
    """The rotation matrix of a unit quaternion (q0, qx, qy, qz) (Pulseq ``mr.aux.quat.toRotMat``): applied to
    a column vector of logical (x, y, z) gradients it gives the played ones."""
    w, x, y, z = (float(v) for v in q)
    n = math.sqrt(w * w + x * x + y * y + z * z)
    if not (0.99 < n < 1.01):
        raise InputError(f"rotation quaternion {tuple(q)} is not normalised (|q| = {n:.4g})")
    w, x, y, z = w / n, x / n, y / n, z / n
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def decompress(data: list[float], num: int, always_compressed: bool = False) -> np.ndarray:
    """Pulseq shape samples: run-length compressed derivative, or stored as is when ``len(data) == num``
    (1.4.0 on; before, every shape was compressed)."""
    if len(data) == num and not always_compressed:
        return np.asarray(data, dtype=np.float64)
    vals: list[float] = []
    reps: list[int] = []
    k = 0
    while k < len(data):
        if k + 2 < len(data) and data[k] == data[k + 1]:
            vals.append(data[k])
            reps.append(int(round(data[k + 2])) + 2)
            k += 3
        else:
            vals.append(data[k])
            reps.append(1)
            k += 1
    w = np.cumsum(np.repeat(np.asarray(vals, dtype=np.float64), reps))
    return w[:num]


def _g(v: float) -> str:
    """A number as the shortest text that reads back to the same float."""
    f = float(v)
    if f.is_integer() and abs(f) < 1e15:
        return "-0" if f == 0 and math.copysign(1.0, f) < 0 else str(int(f))
    return repr(f)


# ------------------------------------------------------------------------------------------------ reading
def reader_text(st) -> tuple[bytes, Layout]:
    """The 1.5.0 text of a parsed file (:class:`dtoc.seq.seqtext.SeqText`) for pypulseq, and its :class:`Layout`."""
    v = st.version
    lay = Layout(version=tuple(v))
    old = v[:2] < (1, 4)
    defs = [ln.text for ln in st.sections.get("[DEFINITIONS]", [])]
    names = {d.split()[0] for d in defs if d.split()}
    if old:
        for k, val in OLD_RASTER_DEFAULTS.items():
            if k not in names:
                defs.append(f"{k} {val:g}")
                lay.notes.append(f"format {version_str(v)} without {k}: {val:g} s (the reference readers' default)")
    _check_required_extensions(st)
    dmap = _defs(defs)
    grad_raster = dmap["GradientRasterTime"]
    rf_raster = dmap["RadiofrequencyRasterTime"]
    block_raster = dmap["BlockDurationRaster"]
    shapes = {sid: decompress(data, num, always_compressed=old) for sid, (num, data, _) in st.shapes.items()}
    # shapes go to pypulseq as the file states them (compressed or not); only a pre-1.4 compressed shape not
    # shorter than its sample count (read as uncompressed, or invalid, from 1.4 on) is written expanded
    out_shapes: dict[int, list[float] | np.ndarray] = {
        sid: (shapes[sid] if old and len(data) >= num else data) for sid, (num, data, _) in st.shapes.items()
    }
    nums = {sid: num for sid, (num, _, _) in st.shapes.items()}
    next_shape = max(shapes, default=0) + 1

    def new_shape(values) -> int:
        nonlocal next_shape
        out_shapes[next_shape] = np.asarray(values, dtype=np.float64)
        nums[next_shape] = len(values)
        next_shape += 1
        return next_shape - 1

    rows = lambda sec: [[float(x) if _isnum(x) else x for x in ln.tokens] for ln in st.sections.get(sec, [])]  # noqa: E731
    # ---- events, in 1.5 columns
    rf: dict[int, list] = {}
    centres: dict[tuple[int, int], float] = {}
    for t in rows("[RF]"):
        i = int(t[0])
        if v[:2] >= (1, 5):
            rf[i] = t[1:]
            continue
        if old:  # id amp mag phase delay freq phase
            amp, mag, ph, delay, freq, phase = t[1:7]
            tid = 0
        else:  # id amp mag phase time delay freq phase
            amp, mag, ph, tid, delay, freq, phase = t[1:8]
        key = (int(mag), int(tid))
        if key not in centres:  # the peak (plateau centre) of the magnitude, as Pulseq's calcRfCenter
            m = shapes[key[0]]
            a = np.abs(m)
            pk = np.flatnonzero(a >= a.max() * 0.99999) if a.size else np.array([0])
            t_pk = shapes[key[1]][[pk[0], pk[-1]]] if tid else pk[[0, -1]] + 0.5
            centres[key] = 1e6 * rf_raster * 0.5 * float(t_pk[0] + t_pk[1]) if a.size else 0.0
        rf[i] = [amp, mag, ph, tid, centres[key], delay, 0.0, 0.0, freq, phase, "u"]
    for r in rf.values():  # phase shape 0: no phase modulation (pypulseq needs a shape)
        if int(r[2]) == 0 and int(r[1]) in shapes:
            r[2] = new_shape(np.zeros(len(shapes[int(r[1])])))
    traps = {int(t[0]): t[1:6] for t in rows("[TRAP]")}
    adc: dict[int, list] = {}
    for t in rows("[ADC]"):
        adc[int(t[0])] = t[1:] if v[:2] >= (1, 5) else [t[1], t[2], t[3], 0.0, 0.0, t[4], t[5], 0]
    grads: dict[int, list] = {}  # id -> [amp, first|None, last|None, shape, time, delay]
    for t in rows("[GRADIENTS]"):
        i = int(t[0])
        if v[:2] >= (1, 5):
            amp, first, last, sid, tid, delay = t[1:7]
        elif old:
            amp, sid, delay = t[1:4]
            first = last = None
            tid = 0
        else:
            amp, sid, tid, delay = t[1:5]
            first = last = None
        if int(tid) == -1:  # 1.5.1 oversampling: samples every half raster -> explicit time shape with the edges
            w = shapes[int(sid)]
            n = len(w)
            vals = np.concatenate([[first / amp if amp else 0.0], w, [last / amp if amp else 0.0]])
            sid = new_shape(vals)
            tid = new_shape(np.arange(n + 2) * 0.5)
        grads[i] = [amp, first, last, int(sid), int(tid), delay]
    # ---- blocks: (duration in block rasters, rf, gx, gy, gz, adc, ext)
    delays = {int(t[0]): t[1] * 1e-6 for t in rows("[DELAYS]")}
    blocks: list[list[int]] = []
    for ln in st.sections["[BLOCKS]"]:
        t = [int(float(x)) for x in ln.tokens]
        if old:
            ev = t[2:7] + ([t[7]] if len(t) > 7 else [0])
            dur = _old_block_duration(t[1], ev, delays, rf, grads, traps, adc, shapes, grad_raster, rf_raster)
            blocks.append([int(math.ceil(dur / block_raster - 1e-6)), *ev])
        else:
            blocks.append(t[1:8])
    if old:
        lay.notes.append(f"format {version_str(v)}: block durations from their events and [DELAYS]")
    if v[:2] < (1, 5):
        _infer_edges(blocks, grads, traps, shapes, grad_raster, block_raster, lay)
    ext_lines, ext_sections = _extensions(st, blocks, lay)
    # ---- emit 1.5.0
    out = ["[VERSION]", "major 1", "minor 5", "revision 0", ""]
    if defs:
        out += ["[DEFINITIONS]", *defs, ""]
    out += ["[BLOCKS]"] + [" ".join(str(x) for x in [i + 1, *b]) for i, b in enumerate(blocks)] + [""]
    if rf:
        out += ["[RF]"]
        for i, r in rf.items():
            out.append(" ".join([str(i), *(_g(x) if not isinstance(x, str) else x for x in r)]))
        out.append("")
    if grads:
        out += ["[GRADIENTS]"]
        for i, g in grads.items():
            amp, first, last, sid, tid, delay = g
            out.append(f"{i} {_g(amp)} {_g(first or 0.0)} {_g(last or 0.0)} {sid} {tid} {_g(delay)}")
        out.append("")
    if traps:
        out += ["[TRAP]"] + [" ".join([str(i), *map(_g, t)]) for i, t in traps.items()] + [""]
    if adc:
        out += ["[ADC]"] + [" ".join([str(i), *map(_g, a)]) for i, a in adc.items()] + [""]
    if ext_lines:
        out += ["[EXTENSIONS]", *ext_lines, ""]
        for head, lines in ext_sections:
            out += [head, *lines, ""]
    if out_shapes:
        out += ["[SHAPES]", ""]
        for sid, w in out_shapes.items():
            out += [f"shape_id {sid}", f"num_samples {nums[sid]}", *(_g(x) for x in w), ""]
    return ("\n".join(out) + "\n\n").encode(), lay


def _isnum(x: str) -> bool:
    try:
        float(x)
        return True
    except ValueError:
        return False


def _defs(lines: list[str]) -> dict[str, float]:
    out = dict(OLD_RASTER_DEFAULTS)
    for d in lines:
        p = d.split()
        if len(p) == 2 and p[0] in out:
            out[p[0]] = float(p[1])
    return out


def _check_required_extensions(st) -> None:
    req = st.definitions().get("RequiredExtensions", "").split()
    unknown = [e for e in req if e not in KNOWN_EXTENSIONS]
    if unknown:
        raise InputError(
            f"{st.path}: the file requires extension {', '.join(unknown)} (RequiredExtensions), which dtoc does not "
            f"know (it reads {', '.join(KNOWN_EXTENSIONS)})"
        )


def _grad_span(gid, grads, traps, shapes, raster):
    """(start s, end s) of a gradient event in its block."""
    if gid in traps:
        _, r, f, fa, d = traps[gid]
        return d * 1e-6, (d + r + f + fa) * 1e-6
    amp, _, _, sid, tid, delay = grads[gid]
    n = len(shapes[sid])
    dur = shapes[tid][-1] * raster if tid else n * raster
    return delay * 1e-6, delay * 1e-6 + dur


def _old_block_duration(delay_id, ev, delays, rf, grads, traps, adc, shapes, raster, rf_raster) -> float:
    ends = [delays.get(delay_id, 0.0)]
    if ev[0]:
        r = rf[ev[0]]
        ends.append(r[5] * 1e-6 + len(shapes[int(r[1])]) * rf_raster)
    for g in ev[1:4]:
        if g:
            ends.append(_grad_span(g, grads, traps, shapes, raster)[1])
    if ev[4]:
        a = adc[ev[4]]
        ends.append(a[2] * 1e-6 + a[0] * a[1] * 1e-9)
    return max(ends)


def _infer_edges(blocks, grads, traps, shapes, raster, block_raster, lay: Layout) -> None:
    """Edge values (first/last) of pre-1.5 gradients without stated ones (module doc); splits events used with
    different edges; rewrites ``blocks`` and ``grads`` in place."""
    tol = 1e-9

    def stated(gid, end: bool):
        """The value a gradient states at its start/end edge, or None when it states none."""
        if gid in traps:
            return 0.0
        amp, _, _, sid, tid, _ = grads[gid]
        if tid == 0:
            return None
        tt = shapes[tid]
        w = amp * shapes[sid]
        if end:
            return float(w[-1])
        return float(w[0]) if abs(tt[0]) < 1e-9 else None

    def centre(gid, end: bool) -> float:
        amp, _, _, sid, _, _ = grads[gid]
        w = shapes[sid]
        return float(amp * (w[-1] if end else w[0]))

    n = len(blocks)
    firsts: list[list] = [[None] * 3 for _ in range(n)]
    lasts: list[list] = [[None] * 3 for _ in range(n)]
    for a in range(3):
        for b in range(n):
            gid = blocks[b][2 + a]
            if not gid or gid in traps or stated(gid, False) is not None and stated(gid, True) is not None:
                continue
            dur = blocks[b][0] * block_raster
            t0, t1 = _grad_span(gid, grads, traps, shapes, raster)
            # start edge
            first = 0.0
            if t0 < tol and b > 0:
                p = blocks[b - 1][2 + a]
                if p:
                    pdur = blocks[b - 1][0] * block_raster
                    if abs(_grad_span(p, grads, traps, shapes, raster)[1] - pdur) < tol:
                        s = stated(p, True)
                        first = s if s is not None else 0.5 * (centre(p, True) + centre(gid, False))
            last = 0.0
            if abs(t1 - dur) < tol and b + 1 < n:
                q = blocks[b + 1][2 + a]
                if q and _grad_span(q, grads, traps, shapes, raster)[0] < tol:
                    s = stated(q, False)
                    last = s if s is not None else 0.5 * (centre(gid, True) + centre(q, False))
            firsts[b][a] = stated(gid, False) if stated(gid, False) is not None else first
            lasts[b][a] = stated(gid, True) if stated(gid, True) is not None else last
    # one event per (id, first, last)
    new_id = max([*grads, *traps, 0]) + 1
    seen: dict[tuple, int] = {}
    orig = {k: list(g) for k, g in grads.items()}
    used_ids: set[int] = set()
    for b in range(n):
        for a in range(3):
            gid = blocks[b][2 + a]
            if not gid or firsts[b][a] is None:
                continue
            key = (gid, round(firsts[b][a], 9), round(lasts[b][a], 9))
            if key not in seen:
                if gid not in used_ids:
                    seen[key] = gid
                    used_ids.add(gid)
                else:
                    seen[key] = new_id
                    new_id += 1
                g = list(orig[gid])
                g[1], g[2] = firsts[b][a], lasts[b][a]
                grads[seen[key]] = g
            blocks[b][2 + a] = seen[key]
    for g in grads.values():  # events no block uses: no edges to infer
        if g[1] is None:
            g[1] = g[2] = 0.0


def _extensions(st, blocks, lay: Layout) -> tuple[list[str], list[tuple[str, list[str]]]]:
    """The [EXTENSIONS] list and extension sections without the kept ones (ROTATIONS, RF_SHIMS), whose
    objects go to ``lay`` per block; block extension columns rewritten in place."""
    entries = {}
    for ln in st.sections.get("[EXTENSIONS]", []):
        t = [int(x) for x in ln.tokens]
        entries[t[0]] = (t[1], t[2], t[3])
    types: dict[int, str] = {}
    sections: list[tuple[str, list[str]]] = []
    kept: dict[str, dict[int, tuple[float, ...]]] = {k: {} for k in KEPT_EXTENSIONS}
    for name in st.section_order:
        if not name.startswith("extension "):
            continue
        p = name.split()
        kind, tid = p[1], int(p[2])
        types[tid] = kind
        lines = [ln.text for ln in st.sections[name]]
        if kind in KEPT_EXTENSIONS:
            for x in lines:
                f = x.split()
                kept[kind][int(f[0])] = tuple(float(y) for y in f[1:])
        else:
            sections.append((name, lines))
    if not any(kept.values()):
        return [f"{i} {a} {b} {c}" for i, (a, b, c) in entries.items()], sections
    new_entries: dict[tuple, int] = {}
    lines_out: list[str] = []
    for bi, blk in enumerate(blocks):
        head = blk[6]
        chain = []
        seen = set()
        while head and head not in seen:
            seen.add(head)
            typ, ref, nxt = entries[head]
            kind = types.get(typ)
            if kind == "ROTATIONS":
                lay.rotations[bi] = kept[kind][ref]
            elif kind == "RF_SHIMS":
                lay.shims[bi] = kept[kind][ref]
            else:
                chain.append((typ, ref))
            head = nxt
        nxt = 0
        for typ, ref in reversed(chain):
            key = (typ, ref, nxt)
            if key not in new_entries:
                new_entries[key] = len(new_entries) + 1
                lines_out.append(f"{new_entries[key]} {typ} {ref} {nxt}")
            nxt = new_entries[key]
        blk[6] = nxt
    if lay.rotations:
        lay.notes.append(f"rotation extension: {len(lay.rotations)} block(s) rotated (played as rotated)")
    if lay.shims:
        lay.notes.append(f"RF shimming extension on {len(lay.shims)} block(s): kept unchanged on output")
    return lines_out, sections


# ------------------------------------------------------------------------------------------------ writing
def set_revision(text: bytes, version: tuple[int, int, int]) -> bytes:
    """``text`` with its [VERSION] section saying ``version`` (the writers emit 1.5.0 / 1.4.1)."""
    i = text.find(b"[VERSION]")
    j = text.find(b"\n\n", i)
    if i < 0 or j < 0:
        raise InputError("written text has no [VERSION] section")
    head = f"[VERSION]\nmajor {version[0]}\nminor {version[1]}\nrevision {version[2]}".encode()
    return text[:i] + head + text[j:]


def set_revision_file(path, version: tuple[int, int, int], newline: bool = False) -> None:
    """:func:`set_revision` on the text at ``path`` (its [VERSION] section is at the top: only the first chunk
    is read whole; the rest is copied in chunks), ``newline``: with a newline appended (the text
    :func:`strip_signature` leaves of a signed one)."""
    p = Path(path)
    tmp = p.with_name(p.name + ".rev")
    try:
        with open(p, "rb") as f, open(tmp, "wb") as g:
            head = f.read(1 << 16)
            g.write(set_revision(head, version))
            shutil.copyfileobj(f, g, 1 << 22)
            if newline:
                g.write(b"\n")
        os.replace(tmp, p)
    finally:
        if tmp.exists():
            tmp.unlink()


def strip_signature(text: bytes) -> bytes:
    i = text.find(b"\n[SIGNATURE]")
    return text if i < 0 else text[: i + 1]


def add_kept_extensions(text: bytes, rotations: dict, shims: dict) -> bytes:
    """``text`` (unsigned 1.5 text) with the ROTATIONS / RF_SHIMS objects of ``rotations`` / ``shims`` ({block
    index: values}) chained into each block's extension list (new list entries, new extension type ids)."""
    if not rotations and not shims:
        return text
    lines = text.decode().split("\n")

    def section(name: str) -> tuple[int, int]:
        try:
            i = lines.index(name)
        except ValueError:
            return -1, -1
        j = i + 1
        while j < len(lines) and lines[j].strip():
            j += 1
        return i, j

    b0, b1 = section("[BLOCKS]")
    e0, e1 = section("[EXTENSIONS]")
    entries = [ln.split() for ln in lines[e0 + 1 : e1] if ln.strip() and not ln.startswith("#")] if e0 >= 0 else []
    next_entry = max((int(t[0]) for t in entries), default=0) + 1
    types = [int(ln.split()[-1]) for ln in lines if ln.startswith("extension ")]
    t_rot = max(types, default=0) + 1
    t_shim = t_rot + 1
    objs: dict[str, dict[tuple, int]] = {"ROTATIONS": {}, "RF_SHIMS": {}}
    new_entries: dict[tuple, int] = {}
    rows = [ln for ln in lines[b0 + 1 : b1] if ln.strip() and not ln.startswith("#")]
    out_rows = []
    for bi, row in enumerate(rows):
        t = row.split()
        head = int(t[7])
        for kind, typ, table in (("RF_SHIMS", t_shim, shims), ("ROTATIONS", t_rot, rotations)):
            if bi not in table:
                continue
            vals = tuple(float(x) for x in table[bi])
            ref = objs[kind].setdefault(vals, len(objs[kind]) + 1)
            key = (typ, ref, head)
            if key not in new_entries:
                new_entries[key] = next_entry
                next_entry += 1
            head = new_entries[key]
        t[7] = str(head)
        out_rows.append(" ".join(t))
    lines[b0 + 1 : b1] = out_rows
    ext_rows = [f"{i} {typ} {ref} {nxt}" for (typ, ref, nxt), i in new_entries.items()]
    spec: list[str] = []
    if objs["ROTATIONS"]:
        spec += ["# Extension specification for rotations:", "# id RotQuat0 RotQuatX RotQuatY RotQuatZ"]
        spec += [f"extension ROTATIONS {t_rot}"] + [
            " ".join([str(i), *map(_g, q)]) for q, i in objs["ROTATIONS"].items()
        ]
        spec += [""]
    if objs["RF_SHIMS"]:
        spec += ["# Extension specification for RF shimming:", "# id num_chan magn_c1 phase_c1 magn_c2 phase_c2 ..."]
        spec += [f"extension RF_SHIMS {t_shim}"]
        spec += [" ".join([str(i), str(int(q[0])), *map(_g, q[1:])]) for q, i in objs["RF_SHIMS"].items()]
        spec += [""]
    e0, e1 = section("[EXTENSIONS]")
    if e0 >= 0:
        # after the list and the extension specifications that follow it (up to the next [SECTION] or comment block)
        k = e1
        while k < len(lines) and not lines[k].startswith("[") and not lines[k].startswith("# Sequence Shapes"):
            k += 1
        lines[e1:e1] = ext_rows
        k += len(ext_rows)
        lines[k:k] = spec
    else:
        k = next((i for i, ln in enumerate(lines) if ln in ("[SHAPES]", "# Sequence Shapes")), len(lines))
        lines[k:k] = ["[EXTENSIONS]", *ext_rows, "", *spec]
    return "\n".join(lines).encode()


# ------------------------------------------------------------------------------------------------ binary files
#: Label names by their index in binary files (Pulseq's ``mr.getSupportedLabels``, 1-based).
BINARY_LABELS = (
    "SLC", "SEG", "REP", "AVG", "SET", "ECO", "PHS", "LIN", "PAR", "ACQ", "TRID", "NAV", "REV", "SMS", "REF",
    "IMA", "OFF", "NOISE", "PMC", "NOROT", "NOPOS", "NOSCL", "ONCE",
)  # fmt: skip


def binary_to_text(raw: bytes, path) -> tuple[bytes, str | None]:
    """The text of a binary Pulseq file (the specification's "Binary files" section: little-endian, times in
    ps, shapes float32) and its md5 signature (None: unsigned), checked over the binary bytes before it.

    Raises:
        InputError: truncated or malformed binary data, an unknown section code, a signature mismatch."""
    import hashlib
    import struct

    pos = 8

    def take(fmt: str):
        nonlocal pos
        size = struct.calcsize("<" + fmt)
        if pos + size > len(raw):
            raise InputError(f"{path}: binary Pulseq file truncated at byte {pos}")
        vals = struct.unpack_from("<" + fmt, raw, pos)
        pos += size
        return vals if len(vals) > 1 else vals[0]

    def chars(n: int) -> str:
        nonlocal pos
        if n < 0 or pos + n > len(raw):
            raise InputError(f"{path}: binary Pulseq file truncated at byte {pos}")
        s = raw[pos : pos + n].decode("ascii", errors="replace")
        pos += n
        return s

    def us(ps: int) -> str:
        return _g(ps / 1e6)

    major, minor, rev = take("qqq")
    out = ["[VERSION]", f"major {major}", f"minor {minor}", f"revision {rev}", ""]
    sections: list[str] = []
    ext_sections: list[str] = []
    signed_until = None
    signature = None
    while pos < len(raw):
        code = take("q") & 0xFFFFFFFF
        if code == 0x00FFFFFF:  # signature
            signed_until = pos - 8
            sig_type = chars(take("i"))
            n_hash = take("i")
            digest = raw[pos : pos + n_hash]
            pos += n_hash
            take("q")
            signature = (sig_type.strip().lower(), digest.hex())
            continue
        if code == 1:
            lines = ["[DEFINITIONS]"]
            for _ in range(take("q")):
                key = chars(take("i"))
                count = take("i")
                typ = chars(1)
                if typ == "c":
                    vals = [chars(count)]
                elif typ == "i":
                    vals = [str(take("i")) for _ in range(count)]
                elif typ == "f":
                    vals = [_g(take("d")) for _ in range(count)]
                else:
                    raise InputError(f"{path}: binary definition {key!r} has an unknown value type {typ!r}")
                lines.append(" ".join([key, *vals]))
            sections += [*lines, ""]
        elif code == 2:
            sections.append("[BLOCKS]")
            for i in range(take("q")):
                dur, *ev = take("qiiiiii")
                sections.append(" ".join(map(str, [i + 1, dur, *ev])))
            sections.append("")
        elif code == 3:
            sections.append("[RF]")
            for _ in range(take("q")):
                i, amp, mag, ph, tid, centre, delay, fppm, pppm, freq, phase = take("idiiiqqdddd")
                use = chars(1)
                sections.append(
                    f"{i} {_g(amp)} {mag} {ph} {tid} {us(centre)} {us(delay)} {_g(fppm)} {_g(pppm)} {_g(freq)} "
                    f"{_g(phase)} {use}"
                )
            sections.append("")
        elif code == 4:
            sections.append("[GRADIENTS]")
            for _ in range(take("q")):
                i, amp, first, last, sid, tid, delay = take("idddiiq")
                sections.append(f"{i} {_g(amp)} {_g(first)} {_g(last)} {sid} {tid} {us(delay)}")
            sections.append("")
        elif code == 5:
            sections.append("[TRAP]")
            for _ in range(take("q")):
                i, amp, *t = take("idqqqq")
                sections.append(" ".join([str(i), _g(amp), *map(us, t)]))
            sections.append("")
        elif code == 6:
            sections.append("[ADC]")
            for _ in range(take("q")):
                i, num, dwell, delay, fppm, pppm, freq, phase, pid = take("iqqqddddi")
                sections.append(
                    f"{i} {num} {_g(dwell / 1e3)} {us(delay)} {_g(fppm)} {_g(pppm)} {_g(freq)} {_g(phase)} {pid}"
                )
            sections.append("")
        elif code == 7:  # legacy delays: ignored by current readers
            for _ in range(take("q")):
                take("iq")
        elif code == 8:
            shp = ["[SHAPES]", ""]
            for _ in range(take("q")):
                sid, num, ncomp = take("iqq")
                if ncomp < 0 or pos + 4 * ncomp > len(raw):
                    raise InputError(f"{path}: binary Pulseq file truncated at byte {pos}")
                vals = np.frombuffer(raw, dtype="<f4", count=ncomp, offset=pos).astype(np.float64)
                pos += 4 * ncomp
                shp += [f"shape_id {sid}", f"num_samples {num}", *(_g(v) for v in vals), ""]
            ext_sections.append("\n".join(shp))
        elif code == 9:
            sections.append("[EXTENSIONS]")
            for _ in range(take("q")):
                sections.append(" ".join(map(str, take("iiii"))))
            sections.append("")
        elif 10 <= code <= 15:
            kind = {10: "TRIGGERS", 11: "LABELSET", 12: "LABELINC", 13: "DELAYS", 14: "RF_SHIMS", 15: "ROTATIONS"}[code]
            lines = [f"extension {kind} {take('i')}"]
            for _ in range(take("q")):
                if kind == "TRIGGERS":
                    i, typ, ch, delay, dur = take("iiiqq")
                    lines.append(f"{i} {typ} {ch} {us(delay)} {us(dur)}")
                elif kind in ("LABELSET", "LABELINC"):
                    i, value, idx = take("iii")
                    if not 1 <= idx <= len(BINARY_LABELS):
                        raise InputError(f"{path}: binary label index {idx} is not a Pulseq label")
                    lines.append(f"{i} {value} {BINARY_LABELS[idx - 1]}")
                elif kind == "DELAYS":
                    i, num, offset, factor = take("iiqd")
                    lines.append(f"{i} {num} {us(offset)} {_g(factor)} {chars(take('i'))}")
                elif kind == "RF_SHIMS":
                    i, n = take("ii")
                    vals = take("d" * (2 * n)) if n else ()
                    lines.append(" ".join([str(i), str(n), *map(_g, vals)]))
                else:
                    i, *q = take("idddd")
                    lines.append(" ".join([str(i), *map(_g, q)]))
            sections += [*lines, ""]
        else:
            raise InputError(f"{path}: binary Pulseq file: unknown section code {code:#x} at byte {pos - 8}")
    if signature is not None:
        typ, digest = signature
        if typ != "md5":
            raise InputError(f"{path}: unsupported signature type {typ!r} (expected md5)")
        got = hashlib.md5(raw[:signed_until]).hexdigest()
        if got != digest:
            raise InputError(
                f"{path}: signature mismatch: md5 of content is {got}, file says {digest} (modified after writing?)"
            )
    return ("\n".join(out + sections + ext_sections) + "\n\n").encode(), (signature[1] if signature else None)
