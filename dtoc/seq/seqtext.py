"""Text-level view of a Pulseq ``.seq`` file: sections, signature and structural pre-validation.

pypulseq's reader trusts its input (it loops forever on an unsigned file that ends inside the
[SHAPES] section without a trailing blank line, and turns most defects into tracebacks).  dtoc
therefore parses the text itself first: every defect becomes a one-line :class:`InputError`
naming the file, the line and the problem.  The same parse feeds the validator (:mod:`dtoc.seq.check`).

Signature: Pulseq's md5 covers the bytes before the newline that precedes ``[SIGNATURE]``.
"""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
import hashlib
import math
import os
import re
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from dtoc.errors import InputError
from dtoc.seq.versions import BINARY_MAGIC, KNOWN_EXTENSIONS, binary_to_text, check_known
from dtoc.util.cost import load_bytes

#: Number of fields (including the id) per line in each event section, by (major, minor).
_FIELDS = {
    (1, 5): {"[BLOCKS]": 8, "[RF]": 12, "[GRADIENTS]": 7, "[TRAP]": 6, "[ADC]": 9},
    (1, 4): {"[BLOCKS]": 8, "[RF]": 8, "[GRADIENTS]": 5, "[TRAP]": 6, "[ADC]": 6},
    # before 1.4: the block's 2nd column is a [DELAYS] id; RF and arbitrary gradients have no time shape
    (1, 3): {"[BLOCKS]": 8, "[RF]": 7, "[GRADIENTS]": 4, "[TRAP]": 6, "[ADC]": 6, "[DELAYS]": 2},
    (1, 2): {"[BLOCKS]": 7, "[RF]": 7, "[GRADIENTS]": 4, "[TRAP]": 6, "[ADC]": 6, "[DELAYS]": 2},
}
#: Columns (0-based, id = 0) that the format defines as integers, per section and version.
INTEGER_COLUMNS = {
    (1, 5): {
        "[BLOCKS]": tuple(range(8)),
        "[RF]": (0, 2, 3, 4, 6),  # id, mag_id, phase_id, time_shape_id, delay [us]
        "[GRADIENTS]": (0, 4, 5, 6),  # id, amp_shape_id, time_shape_id, delay [us]
        "[TRAP]": (0, 2, 3, 4, 5),  # id, rise, flat, fall, delay [us]
        "[ADC]": (0, 1, 2, 3, 8),  # id, num, dwell [ns], delay [us], phase_id
    },
    (1, 4): {
        "[BLOCKS]": tuple(range(8)),
        "[RF]": (0, 2, 3, 4, 5),
        "[GRADIENTS]": (0, 2, 3, 4),
        "[TRAP]": (0, 2, 3, 4, 5),
        "[ADC]": (0, 1, 2, 3),
    },
}
for _mm in ((1, 3), (1, 2)):
    INTEGER_COLUMNS[_mm] = {
        "[BLOCKS]": tuple(range(_FIELDS[_mm]["[BLOCKS]"])),
        "[RF]": (0, 2, 3, 4),  # id, mag_id, phase_id, delay [us]
        "[GRADIENTS]": (0, 2, 3),  # id, shape_id, delay [us]
        "[TRAP]": (0, 2, 3, 4, 5),
        "[ADC]": (0, 1, 2, 3),
        "[DELAYS]": (0, 1),
    }
_NUM = re.compile(r"^[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?$|^[+-]?(nan|inf)$", re.IGNORECASE)


@dataclass(slots=True)
class SeqLine:
    lineno: int  # 1-based line number in the file
    text: str  # stripped line

    @property
    def tokens(self) -> list[str]:
        return self.text.split()


@dataclass
class SeqText:
    """A parsed ``.seq`` text: raw bytes, version, sections (name -> data lines), signature."""

    path: str
    raw: bytes
    version: tuple[int, int, int] = (0, 0, 0)
    sections: dict[str, list[SeqLine]] = field(default_factory=dict)
    section_order: list[str] = field(default_factory=list)
    signature_hash: str | None = None
    signature_type: str | None = None
    shapes: dict[int, tuple[int, list[float], int]] = field(default_factory=dict)  # id -> (num_samples, data, line)
    layout: Any = None  # dtoc.seq.versions.Layout, set by the reader
    binary: bool = False  # read from the binary format (``raw`` is its text)

    @property
    def major_minor(self) -> tuple[int, int]:
        return self.version[:2]

    def content_md5(self) -> str | None:
        """md5 of the bytes before the newline preceding ``[SIGNATURE]`` (None if unsigned).  Files of older
        writers (JEMRIS, Pulseq before 1.4) hash that newline too: when that hash is the stated one, it is
        returned."""
        if self.binary:  # checked over the binary bytes when the text was made
            return self.signature_hash
        i = self.raw.find(b"\n[SIGNATURE]")
        if i < 0:
            return None
        md5 = hashlib.md5(self.raw[:i]).hexdigest()
        if md5 != self.signature_hash and hashlib.md5(self.raw[: i + 1]).hexdigest() == self.signature_hash:
            return self.signature_hash
        return md5

    def definitions(self) -> dict[str, str]:
        out = {}
        for ln in self.sections.get("[DEFINITIONS]", []):
            parts = ln.text.split(None, 1)
            out[parts[0]] = parts[1].strip() if len(parts) > 1 else ""
        return out


def _err(path, msg):
    return InputError(f"{path}: {msg}")


#: The parse :func:`shared_parse` keeps: [(the bytes parsed, their SeqText)] or [None]; None outside the scope.
_SHARED: contextvars.ContextVar[list | None] = contextvars.ContextVar("dtoc_shared_parse", default=None)


@contextlib.contextmanager
def shared_parse() -> Iterator[None]:
    """Inside this scope a text is parsed once: :func:`parse_seq_text` of the same bytes again (a written file
    read back by the writer's check, by the ``dtoc check`` rules and by the reader, each from its own path) gives
    the first parse, with its own path, instead of parsing again.  Only the latest parse is kept, and only for the
    scope (a parse holds ~20 bytes per byte of text).  Checks and messages are those of a parse: what is reused
    is a text that parsed without error, byte for byte the same.  Nested scopes share the outer one."""
    token = _SHARED.set([None]) if _SHARED.get() is None else None
    try:
        yield
    finally:
        if token is not None:
            _SHARED.reset(token)


def forget_shared_parse() -> None:
    """Inside :func:`shared_parse`: drop the parse kept (its text's last reader is done with it)."""
    shared = _SHARED.get()
    if shared is not None:
        shared[0] = None


def parse_seq_text(path: str | Path, raw: bytes | None = None) -> SeqText:
    """Split a ``.seq`` file into sections and check its structure (inside :func:`shared_parse`: once per text).

    Raises:
        InputError: missing, empty, binary, no/unsupported [VERSION], malformed or truncated content,
            references to undefined events or shapes.  (The signature is checked by
            :func:`verify_signature`.)
    """
    p = Path(path)
    if raw is None:
        if not p.exists():
            raise _err(p, "no such file")
        if p.is_dir():
            raise _err(p, "is a directory, expected a .seq file")
        if not p.is_file():
            raise _err(p, "not a regular file (a device or pipe): give a .seq file")
        size = p.stat().st_size
        if size > max_file_bytes():
            raise _err(
                p,
                f"{size / 1e6:.0f} MB: larger than this machine can parse ({max_file_bytes() / 1e6:.0f} MB at most, "
                "about 1/40 of its memory)",
            )
        try:
            raw = p.read_bytes()
        except OSError as e:
            raise _err(p, f"cannot read ({e.strerror})") from None
    shared = _SHARED.get()
    if shared is not None and shared[0] is not None and shared[0][0] == raw:
        return dataclasses.replace(shared[0][1], path=str(p), layout=None)
    st = _parse(p, raw)
    if shared is not None:
        shared[0] = (raw, st)
    return st


def _parse(p: Path, raw: bytes) -> SeqText:
    if not raw.strip():
        raise _err(p, "empty file")
    binary = raw.startswith(BINARY_MAGIC)
    binary_md5 = None
    if binary:  # the specification's "Binary files" format: its text (signature checked on the binary bytes)
        raw, binary_md5 = binary_to_text(raw, p)
    if b"\x00" in raw:
        raise _err(p, "not a Pulseq text file (binary data)")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        raise _err(p, "not a Pulseq text file (not UTF-8/ASCII: corrupt?)") from None
    st = SeqText(path=str(p), raw=raw, binary=binary)
    if binary_md5 is not None:
        st.signature_hash, st.signature_type = binary_md5, "md5"
    body = _shapes_body(text)
    shapes = None if body is None else _read_shapes(text[body[0] : body[1]], body[2])
    if body is not None and shapes is not None:  # [SHAPES] read at once, its header lines kept as lines
        _scan_lines(st, p, text[: body[0]], 1, None)
        st.sections["[SHAPES]"], st.shapes = shapes
        _scan_lines(st, p, text[body[1] :], body[3], "[SHAPES]")
    else:
        _scan_lines(st, p, text, 1, None)
    if "[VERSION]" not in st.sections:
        raise _err(p, "not a Pulseq file (no [VERSION] section)")
    ver = {}
    for ln in st.sections["[VERSION]"]:
        t = ln.tokens
        if len(t) != 2 or t[0] not in ("major", "minor", "revision"):
            raise _err(p, f"line {ln.lineno}: malformed [VERSION] entry {ln.text[:40]!r}")
        m = re.match(r"^(\d+)", t[1])
        if not m:
            raise _err(p, f"line {ln.lineno}: malformed version number {t[1]!r}")
        ver[t[0]] = int(m.group(1))
    if "major" not in ver or "minor" not in ver:
        raise _err(p, "[VERSION] lacks major/minor")
    st.version = (ver["major"], ver["minor"], ver.get("revision", 0))
    check_known(st.version, p)
    if "[SIGNATURE]" in st.sections:
        for ln in st.sections["[SIGNATURE]"]:
            t = ln.tokens
            if len(t) == 2 and t[0] == "Hash":
                st.signature_hash = t[1].lower()
            elif len(t) == 2 and t[0] == "Type":
                st.signature_type = t[1].lower()
    _check_definitions(st, p)
    _check_extensions(st, p)
    _check_structure(st, p)
    return st


def _scan_lines(st: SeqText, p: Path, text: str, first: int, current: str | None) -> None:
    """The lines of ``text`` (the file's from line ``first`` on, inside section ``current``) into ``st.sections``."""
    for i, line in enumerate(text.split("\n"), start=first):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        if s.startswith("["):
            if not s.endswith("]"):
                raise _err(p, f"line {i}: malformed section header {s[:40]!r}")
            current = s
            if current in st.sections:
                raise _err(p, f"line {i}: section {current} appears twice")
            st.sections[current] = []
            st.section_order.append(current)
            continue
        if s.startswith("extension "):
            current = s
            st.sections.setdefault(current, [])
            st.section_order.append(current)
            continue
        if current is None:
            if p.suffix.lower() in (".yaml", ".yml") or re.match(r"^[A-Za-z_]\w*:(\s|$)", s):
                raise _err(
                    p, "a spec YAML, not a Pulseq .seq file: build it first with 'dtoc build SPEC.yaml -o base.seq'"
                )
            raise _err(p, f"line {i}: content before the first section: {s[:40]!r}")
        st.sections[current].append(SeqLine(i, s))


#: a shape's two header lines (:func:`_read_shapes`)
_SHAPE_HEAD = re.compile(r"^[ \t]*shape_id[ \t]+(\S+)[ \t]*\n[ \t]*num_samples[ \t]+(\S+)[ \t]*$", re.M)
_TWO_TOKENS = re.compile(r"\S[ \t]+\S")
_SECTION_START = re.compile(r"^[ \t]*(\[|extension )", re.M)


def _shapes_body(text: str) -> tuple[int, int, int, int] | None:
    """(start, end, first line number, line number at end) of the [SHAPES] section's lines in ``text``, or None
    (no such section, or one named twice: the line by line reading names what is wrong)."""
    heads = list(re.finditer(r"^[ \t]*\[SHAPES\][ \t]*$", text, re.M))
    if len(heads) != 1:
        return None
    a = text.find("\n", heads[0].end())
    if a < 0:
        return None
    a += 1
    m = _SECTION_START.search(text, a)
    b = len(text) if m is None else m.start()
    first = text.count("\n", 0, a) + 1
    return a, b, first, first + text.count("\n", a, b)


def _read_shapes(body: str, first: int) -> tuple[list[SeqLine], dict[int, tuple[int, list[float], int]]] | None:
    """The [SHAPES] lines ``body`` (from line ``first``) read at once: (their header lines, id -> (num_samples,
    samples, line)).  A long text's shapes are most of its lines, and a Python object per sample line was most
    of its parse.  The same result as the line by line reading (:func:`_scan_lines`, then
    :func:`_check_structure`'s reading of the shapes); None wherever the text is anything but plain shapes (a
    comment, a line of two tokens, headers out of their order, a value that is not a finite plain number, a
    character that is not ASCII): the line by line reading then names what is wrong."""
    if not body.isascii() or "#" in body or "\r" in body or "[" in body:
        return None
    heads = list(_SHAPE_HEAD.finditer(body))
    n = len(heads)
    if not n or body.count("shape_id") != n or body.count("num_samples") != n or body.count("_") != 2 * n:
        return None
    if body[: heads[0].start()].strip():
        return None
    lines: list[SeqLine] = []
    shapes: dict[int, tuple[int, list[float], int]] = {}
    ln, pos = first, 0
    for k, m in enumerate(heads):
        ln += body.count("\n", pos, m.start())
        pos = m.start()
        sid_s, num_s = m.group(1), m.group(2)
        if not sid_s.isdigit() or not num_s.isdigit():
            return None
        # (every token is one line's: no line holds two; float() takes what the line pattern takes, and "nan",
        # "inf", "infinity", which the sum finds)
        end = heads[k + 1].start() if k + 1 < n else len(body)
        if _TWO_TOKENS.search(body, m.end(), end) is not None:
            return None
        try:
            data = [float(t) for t in body[m.end() : end].split()]
        except ValueError:
            return None
        if not data or not math.isfinite(sum(data)):
            return None
        if int(sid_s) in shapes:  # (a repeated id: each occurrence is checked line by line)
            return None
        h1, h2 = m.group(0).split("\n")
        lines += [SeqLine(ln, h1.strip()), SeqLine(ln + 1, h2.strip())]
        shapes[int(sid_s)] = (int(num_s), data, ln)
    return lines, shapes


#: Extensions dtoc reads (:mod:`dtoc.seq.versions`); any other is refused by name.
SUPPORTED_EXTENSIONS = KNOWN_EXTENSIONS


def _check_extensions(st: SeqText, p: Path) -> None:
    for name in st.section_order:
        if not name.startswith("extension "):
            continue
        parts = name.split()
        kind = parts[1] if len(parts) > 1 else "?"
        if kind not in SUPPORTED_EXTENSIONS:
            raise _err(
                p,
                f"'extension {kind}' is not supported (an extension dtoc does not know); dtoc reads "
                f"{', '.join(SUPPORTED_EXTENSIONS)}",
            )


#: Definitions that must be a positive time in s when present (pypulseq divides by them).
RASTER_DEFINITIONS = ("GradientRasterTime", "RadiofrequencyRasterTime", "AdcRasterTime", "BlockDurationRaster")


def _check_definitions(st: SeqText, p: Path) -> None:
    for ln in st.sections.get("[DEFINITIONS]", []):
        parts = ln.text.split()
        if parts and parts[0] in RASTER_DEFINITIONS:
            try:
                v = float(parts[1]) if len(parts) == 2 else float("nan")
            except ValueError:
                v = float("nan")
            if not (0 < v < 1):
                raise _err(
                    p,
                    f"line {ln.lineno}: definition {parts[0]} must be one positive time in s (below 1 s), "
                    f"got {' '.join(parts[1:])[:30]!r}",
                )


def _check_shape(st: SeqText, p: Path, sid: int, num: int, data: list[float], line: int, hint: str) -> None:
    """A shape's samples against its ``num_samples`` (compressed or not, by the format's version)."""
    if not data:
        raise _err(p, f"shape {sid} (line {line}) has no samples{hint}")
    if st.major_minor < (1, 4):  # always compressed before 1.4 (then possibly longer than num_samples)
        if not _compressed_length_ok(data, num):
            raise _err(p, f"shape {sid} (line {line}): compressed data do not expand to {num} samples")
    elif len(data) > num:
        raise _err(p, f"shape {sid} (line {line}): {len(data)} values for num_samples {num}")
    elif len(data) < num and not _compressed_length_ok(data, num):
        raise _err(p, f"shape {sid} (line {line}): compressed data do not expand to {num} samples{hint}")


def _check_structure(st: SeqText, p: Path) -> None:
    fields = _FIELDS[st.major_minor]
    signed = "[SIGNATURE]" in st.sections
    hint = "" if signed else " (file truncated?)"
    if "[BLOCKS]" not in st.sections or not st.sections["[BLOCKS]"]:
        raise _err(p, f"no [BLOCKS] section{hint}")
    ids: dict[str, set[int]] = {}
    for sec, n in fields.items():
        ids[sec] = set()
        for ln in st.sections.get(sec, []):
            t = ln.tokens
            is_rf15 = sec == "[RF]" and st.major_minor == (1, 5)
            numeric = t[:-1] if is_rf15 else t
            if len(t) != n:
                raise _err(p, f"line {ln.lineno} in {sec}: expected {n} fields, got {len(t)}{hint}")
            bad = [x for x in numeric if not _NUM.match(x)]
            if bad:
                raise _err(p, f"line {ln.lineno} in {sec}: not a number: {bad[0][:20]!r}")
            _check_values(st, sec, ln, numeric, p)
            if is_rf15 and t[-1] not in ("e", "r", "i", "s", "p", "o", "u"):
                raise _err(p, f"line {ln.lineno} in [RF]: unknown RF use {t[-1]!r}")
            try:
                ids[sec].add(int(float(t[0])))
            except (ValueError, OverflowError):
                raise _err(p, f"line {ln.lineno} in {sec}: bad id {t[0]!r}") from None
    # shapes (read at once by _read_shapes, or here from their lines)
    for sid, (num, data, line) in st.shapes.items():
        _check_shape(st, p, sid, num, data, line, hint)
    shp = [] if st.shapes else st.sections.get("[SHAPES]", [])
    i = 0
    while i < len(shp):
        t = shp[i].tokens
        if len(t) != 2 or t[0] != "shape_id":
            raise _err(p, f"line {shp[i].lineno} in [SHAPES]: expected 'shape_id N', got {shp[i].text[:30]!r}")
        sid = int(t[1]) if t[1].isdigit() else None
        if sid is None:
            raise _err(p, f"line {shp[i].lineno} in [SHAPES]: bad shape id {t[1]!r}")
        if i + 1 >= len(shp) or shp[i + 1].tokens[:1] != ["num_samples"] or len(shp[i + 1].tokens) != 2:
            raise _err(p, f"shape {sid} (line {shp[i].lineno}): missing 'num_samples'{hint}")
        try:
            num = int(shp[i + 1].tokens[1])
        except ValueError:
            raise _err(p, f"line {shp[i + 1].lineno} in [SHAPES]: bad num_samples {shp[i + 1].tokens[1]!r}") from None
        data = []
        j = i + 2
        while j < len(shp) and not shp[j].text.startswith("shape_id"):
            if not _NUM.match(shp[j].text):
                raise _err(p, f"line {shp[j].lineno} in [SHAPES]: not a number: {shp[j].text[:20]!r}")
            data.append(float(shp[j].text))
            if not math.isfinite(data[-1]):  # a NaN time or amplitude sample would reach every figure
                raise _err(
                    p, f"line {shp[j].lineno} in [SHAPES]: shape {sid} sample {shp[j].text[:20]!r} is not finite"
                )
            j += 1
        _check_shape(st, p, sid, num, data, shp[i].lineno, hint)
        st.shapes[sid] = (num, data, shp[i].lineno)
        i = j
    # every [BLOCKS] row as integers, once (validated above): sizes and references both read them
    blocks = [(ln.lineno, [int(float(x)) for x in ln.tokens]) for ln in st.sections["[BLOCKS]"]]
    _check_sizes(st, blocks, p)
    # references
    ext_ids = _extension_ids(st, p)
    grad_ids = ids["[GRADIENTS]"] | ids["[TRAP]"]
    old = st.major_minor < (1, 4)
    for lineno, t in blocks:
        if old and len(t) < 8:
            t = [*t, 0]  # 1.2.x: no extension column
        if old and t[1] and t[1] not in ids.get("[DELAYS]", set()):
            raise _err(p, f"line {lineno}: block {t[0]} uses delay {t[1]}, which is not defined{hint}")
        refs = (
            ("RF", t[2], ids["[RF]"]),
            ("gradient", t[3], grad_ids),
            ("gradient", t[4], grad_ids),
            ("gradient", t[5], grad_ids),
            ("ADC", t[6], ids["[ADC]"]),
        )
        for name, ref, have in (*refs, ("extension list", t[7], ext_ids)):
            if ref and ref not in have:
                raise _err(p, f"line {lineno}: block {t[0]} uses {name} {ref}, which is not defined{hint}")
    shape_cols = {
        (1, 5): {"[RF]": (2, 3, 4), "[GRADIENTS]": (4, 5)},
        (1, 4): {"[RF]": (2, 3, 4), "[GRADIENTS]": (2, 3)},
    }.get(st.major_minor, {"[RF]": (2, 3), "[GRADIENTS]": (2,)})
    for sec, cols in shape_cols.items():
        for ln in st.sections.get(sec, []):
            for c in cols:
                sid = int(float(ln.tokens[c]))
                if sid > 0 and sid not in st.shapes:
                    raise _err(p, f"line {ln.lineno} in {sec}: shape {sid} is not defined{hint}")


#: Largest |value| of an event amplitude: gradients in Hz/m (1e9 Hz/m = 23 T/m), RF in Hz (1e6 Hz = 23 mT).
MAX_GRAD_HZ_PER_M = 1e9
MAX_RF_HZ = 1e6
#: Named (column, what) per section and version: values that are durations/delays/counts (>= 0, integer).
_NONNEGATIVE = {
    (1, 5): {
        "[BLOCKS]": ((1, "duration"),),
        "[RF]": ((6, "delay"),),
        "[GRADIENTS]": ((6, "delay"),),
        "[TRAP]": ((2, "rise time"), (3, "flat time"), (4, "fall time"), (5, "delay")),
        "[ADC]": ((1, "number of samples"), (2, "dwell"), (3, "delay")),
    },
    (1, 3): {"[RF]": ((4, "delay"),), "[GRADIENTS]": ((3, "delay"),), "[DELAYS]": ((1, "delay"),)},
    (1, 2): {"[RF]": ((4, "delay"),), "[GRADIENTS]": ((3, "delay"),), "[DELAYS]": ((1, "delay"),)},
    (1, 4): {
        "[BLOCKS]": ((1, "duration"),),
        "[RF]": ((5, "delay"),),
        "[GRADIENTS]": ((4, "delay"),),
        "[TRAP]": ((2, "rise time"), (3, "flat time"), (4, "fall time"), (5, "delay")),
        "[ADC]": ((1, "number of samples"), (2, "dwell"), (3, "delay")),
    },
}
_AMPLITUDE_COL = {
    "[RF]": (1, MAX_RF_HZ, "Hz"),
    "[GRADIENTS]": (1, MAX_GRAD_HZ_PER_M, "Hz/m"),
    "[TRAP]": (1, MAX_GRAD_HZ_PER_M, "Hz/m"),
}


def _check_values(st: SeqText, sec: str, ln: SeqLine, numeric: list[str], p: Path) -> None:
    """Every number finite; integer columns integers; durations, delays and counts >= 0; amplitudes bounded."""
    vals = [float(x) for x in numeric]
    for c, v in enumerate(vals):
        if not math.isfinite(v):
            raise _err(p, f"line {ln.lineno} in {sec}: column {c + 1} is {numeric[c]!r}: numbers must be finite")
    for c in INTEGER_COLUMNS[st.major_minor].get(sec, ()):
        if c < len(vals) and not vals[c].is_integer():
            raise _err(p, f"line {ln.lineno} in {sec}: column {c + 1} must be an integer, got {numeric[c]!r}")
    for c, what in _NONNEGATIVE[st.major_minor].get(sec, ()):
        if vals[c] < 0:
            raise _err(p, f"line {ln.lineno} in {sec}: negative {what} {numeric[c]}")
    if sec == "[BLOCKS]" and any(v < 0 for v in vals[2:]):
        raise _err(p, f"line {ln.lineno} in [BLOCKS]: negative event id")
    if sec in _AMPLITUDE_COL:
        c, bound, unit = _AMPLITUDE_COL[sec]
        if abs(vals[c]) > bound:
            raise _err(
                p,
                f"line {ln.lineno} in {sec}: amplitude {numeric[c]} {unit} is beyond any scanner (|a| <= {bound:g} {unit})",
            )


def _extension_ids(st: SeqText, p: Path) -> set[int]:
    """Ids of the [EXTENSIONS] list (each line: id type ref next_id)."""
    out: set[int] = set()
    for ln in st.sections.get("[EXTENSIONS]", []):
        t = ln.tokens
        if len(t) == 4 and all(re.match(r"^\d+$", x) for x in t):
            out.add(int(t[0]))
    return out


def _check_sizes(st: SeqText, blocks: list[tuple[int, list[int]]], p: Path) -> None:
    """Refuse, before anything is allocated, a sequence whose load (the read, the IR, its masks and the nominal k:
    :func:`dtoc.util.cost.load_bytes`, measured constants) needs more than three quarters of this machine's memory
    (a duration or sample count off by orders of magnitude).  Only what the read cannot hold is refused here: what a
    command then does with the sequence is estimated by that command (an optimization: :mod:`dtoc.util.cost`).
    ``blocks``: (line, integer fields) of every [BLOCKS] row."""
    defs = st.definitions()

    def num(key: str, default: float) -> float:
        try:
            return float(defs.get(key, "").split()[0])
        except (ValueError, IndexError):
            return default

    block_raster = num("BlockDurationRaster", 10e-6)
    grad_raster = num("GradientRasterTime", 10e-6)
    if st.major_minor >= (1, 4):
        duration_s = sum(t[1] for _, t in blocks) * block_raster  # durations in block-raster ticks (1.4 and 1.5)
    else:  # before 1.4 the column is a [DELAYS] id: the delays give a lower bound
        dl = {int(float(ln.tokens[0])): float(ln.tokens[1]) * 1e-6 for ln in st.sections.get("[DELAYS]", [])}
        duration_s = sum(dl.get(t[1], 0.0) for _, t in blocks)
    n_raster = duration_s / grad_raster
    adc_num = {int(float(ln.tokens[0])): int(float(ln.tokens[1])) for ln in st.sections.get("[ADC]", [])}
    n_adc = sum(adc_num.get(t[6], 0) for _, t in blocks)
    need = load_bytes(n_raster, n_adc)
    budget = max_file_bytes() * 30  # three quarters of the memory
    if need > budget:
        raise _err(
            p,
            f"{duration_s:.4g} s of sequence ({n_raster:.3g} gradient raster steps) and {n_adc:.3g} ADC samples need "
            f"~{need / 1e9:.3g} GB to be read (estimate); this machine allows {budget / 1e9:.3g} GB (a duration or "
            "sample count off by orders of magnitude?)",
        )


def max_file_bytes() -> int:
    """Largest .seq dtoc parses on this machine: 1/40 of its memory (the parse holds ~20 bytes per byte)."""
    try:
        mem = os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        mem = 8 << 30
    return int(mem // 40)


def _compressed_length_ok(data: list[float], num: int) -> bool:
    """True if Pulseq run-length-compressed ``data`` expands to ``num`` samples."""
    n = 0
    k = 0
    while k < len(data):
        if k + 2 < len(data) and data[k] == data[k + 1] and float(data[k + 2]).is_integer() and data[k + 2] >= 0:
            n += 2 + int(data[k + 2])
            k += 3
        else:
            n += 1
            k += 1
    return n == num


def verify_signature(st: SeqText, require: bool = True) -> None:
    """Raise :class:`InputError` if the md5 signature is absent (when ``require``) or does not match."""
    if st.signature_hash is None:
        if require:
            raise _err(st.path, "unsigned: no [SIGNATURE] md5 hash, and a signed file was required")
        return
    if st.signature_type not in (None, "md5"):
        raise _err(st.path, f"unsupported signature type {st.signature_type!r} (expected md5)")
    got = st.content_md5()
    if got != st.signature_hash:
        raise _err(
            st.path,
            f"signature mismatch: md5 of content is {got}, file says {st.signature_hash} (modified after writing?)",
        )


def _signature_section(md5: str) -> bytes:
    """Pulseq's ``[SIGNATURE]`` section for the content md5 ``md5``, with the newline before it (pypulseq's words)."""
    return (
        "\n[SIGNATURE]\n"
        "# This is the hash of the Pulseq file, calculated right before the [SIGNATURE] section was added\n"
        "# It can be reproduced/verified with md5sum if the file trimmed to the position right above [SIGNATURE]\n"
        "# The new line character preceding [SIGNATURE] BELONGS to the signature (and needs to be stripped away for "
        "recalculating/verification)\n"
        f"Type md5\nHash {md5}\n"
    ).encode()


def sign_text(body: str | bytes) -> bytes:
    """Append a Pulseq md5 ``[SIGNATURE]`` section to ``body`` (any old signature is removed first)."""
    b = body.encode("utf-8") if isinstance(body, str) else body
    i = b.find(b"\n[SIGNATURE]")
    if i >= 0:
        b = b[:i]
    return b + _signature_section(hashlib.md5(b).hexdigest())


def sign_file(path: str | os.PathLike) -> None:
    """Append a Pulseq md5 ``[SIGNATURE]`` section to the unsigned text at ``path`` (:func:`sign_text`'s bytes),
    reading it in chunks: never whole in memory."""
    h = hashlib.md5()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 22), b""):
            h.update(chunk)
    with open(path, "ab") as f:
        f.write(_signature_section(h.hexdigest()))
