"""Self-contained pieces of a written Pulseq text, so that a long output is read back piece by piece.

A piece is a Pulseq text of the same format version: the whole text's [VERSION] and [DEFINITIONS] (and any
other leading section) verbatim, a run of consecutive [BLOCKS] lines, and only the library lines they use --
RF, gradient, trapezoid and ADC events, the extension list entries their chains reach, the extension lines
those entries name, and the shapes of all of these -- each line copied byte for byte, in the order of the
whole text.  Library entries that no block uses are shared out over the pieces (each in exactly one), so every
line a reader of the whole text would parse is parsed in some piece.  [SIGNATURE] is left out of the pieces
(the whole text's signature is checked once, :func:`signature_ok`).

:class:`TextIndex` holds, per section, one row per line (id, byte range and the ids it refers to) as integer
arrays -- a few tens of bytes per library entry and per block, nothing per shape sample -- and the text itself
is not copied: a piece's bytes are assembled from slices of it.

Formats 1.4.x and 1.5.x (what dtoc writes); :class:`TextIndex` raises :class:`PieceError` for anything else
(the caller then reads the text whole).
"""

from __future__ import annotations

import contextlib
import hashlib
import mmap
import os
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np

#: bytes of the text scanned between two releases of a mapped text's pages (:func:`mapped_text`)
SCAN_WINDOW = 1 << 26


class PieceError(Exception):
    """The text does not split (a layout this module does not cut, or a reference to nothing): one line."""


@dataclass
class _Rows:
    """One section's data lines: id, byte range [start, end) (end after the newline), integer columns."""

    ids: np.ndarray
    start: np.ndarray
    end: np.ndarray
    cols: np.ndarray  # (n, k) int64: the columns named by the section's reference layout
    order: np.ndarray  # argsort of ids

    def positions(self, ids: np.ndarray, what: str) -> np.ndarray:
        """Row positions of ``ids`` (all must exist)."""
        ids = np.asarray(ids, dtype=np.int64)
        if ids.size == 0:
            return ids
        i = np.searchsorted(self.ids, ids, sorter=self.order)
        i = np.minimum(i, max(len(self.ids) - 1, 0))
        pos = self.order[i] if len(self.ids) else np.zeros_like(ids)
        bad = (self.ids[pos] != ids) if len(self.ids) else np.ones(ids.shape, dtype=bool)
        if np.any(bad):
            raise PieceError(f"{what} {int(ids[np.argmax(bad)])} is not defined")
        return pos


#: the integer columns kept per section (after the id), by (major, minor): shape references and the like
_REF_COLS = {
    (1, 5): {"[BLOCKS]": (1, 2, 3, 4, 5, 6, 7), "[RF]": (2, 3, 4), "[GRADIENTS]": (4, 5), "[TRAP]": (), "[ADC]": (8,)},
    (1, 4): {"[BLOCKS]": (1, 2, 3, 4, 5, 6, 7), "[RF]": (2, 3, 4), "[GRADIENTS]": (2, 3), "[TRAP]": (), "[ADC]": ()},
}
_LIBRARIES = ("[RF]", "[GRADIENTS]", "[TRAP]", "[ADC]", "[EXTENSIONS]")


def _int(tok: bytes) -> int:
    f = float(tok)
    if not f.is_integer():
        raise PieceError(f"not an integer: {tok[:20]!r}")
    return int(f)


class TextIndex:
    """The sections of ``data`` (a Pulseq 1.4/1.5 text) as row tables (module doc)."""

    def __init__(self, data, drop: Callable[[], None] | None = None):
        """``data``: the text (bytes, or a read-only buffer of it such as :func:`mapped_text`'s); ``drop``: called
        every :data:`SCAN_WINDOW` bytes of scanning (a mapped text's pages released: a long text is not held)."""
        self.data = data
        self._drop = drop or (lambda: None)
        self.heads: list[tuple[str, int, int, int]] = []  # (name, header line start, body start, body end)
        self._scan_headers()
        names = [h[0] for h in self.heads]
        if "[VERSION]" not in names or "[BLOCKS]" not in names:
            raise PieceError("no [VERSION] or [BLOCKS] section")
        self.version = self._version()
        if self.version[:2] not in _REF_COLS:
            raise PieceError(f"format {self.version} is not cut in pieces")
        cols = _REF_COLS[self.version[:2]]
        self.rows: dict[str, _Rows] = {}
        self.ext_rows: dict[int, _Rows] = {}  # extension type number -> its lines (id ...)
        self.ext_heads: dict[int, str] = {}
        self.shapes: _Rows | None = None
        for name, _, s, e in self.heads:
            if name in cols:
                self.rows[name] = self._rows(s, e, cols[name])
            elif name == "[EXTENSIONS]":
                self.rows[name] = self._rows(s, e, (1, 2, 3))
            elif name.startswith("extension "):
                parts = name.split()
                if len(parts) != 3 or not parts[2].isdigit():
                    raise PieceError(f"malformed extension header {name[:40]!r}")
                self.ext_rows[int(parts[2])] = self._rows(s, e, (), numeric=False)
                self.ext_heads[int(parts[2])] = name
            elif name == "[SHAPES]":
                self.shapes = self._shape_rows(s, e)
            elif name not in ("[VERSION]", "[DEFINITIONS]", "[SIGNATURE]"):
                raise PieceError(f"section {name[:40]} is not cut in pieces")
        empty = _Rows(
            *(np.zeros(0, dtype=np.int64) for _ in range(3)), np.zeros((0, 0), np.int64), np.zeros(0, np.int64)
        )
        for name in _LIBRARIES:
            self.rows.setdefault(name, empty)
        if self.shapes is None:
            self.shapes = empty
        for name, r in (*self.rows.items(), ("[SHAPES]", self.shapes)):
            if name != "[BLOCKS]" and len(np.unique(r.ids)) != len(r.ids):
                raise PieceError(f"{name} defines an id twice")
        self.n_blocks = len(self.rows["[BLOCKS]"].ids)

    # ---------------------------------------------------------------- parsing
    def _scan_headers(self) -> None:
        d = self.data
        starts = []
        for pat in (b"\n[", b"\nextension "):
            for a in range(0, len(d), SCAN_WINDOW):  # (matches starting in the window: none found twice)
                b = min(a + SCAN_WINDOW + len(pat) - 1, len(d))
                i = d.find(pat, a, b)
                while i >= 0:
                    starts.append(i + 1)
                    i = d.find(pat, i + 1, b)
                self._drop()
        if bytes(d[:16]).startswith((b"[", b"extension ")):
            starts.append(0)
        starts.sort()
        for k, s in enumerate(starts):
            eol = d.find(b"\n", s)
            eol = len(d) if eol < 0 else eol
            name = d[s:eol].decode("ascii", "replace").strip()
            end = starts[k + 1] if k + 1 < len(starts) else len(d)
            self.heads.append((name, s, min(eol + 1, len(d)), end))

    def _version(self) -> tuple[int, int, int]:
        s, e = next((s, e) for n, _, s, e in self.heads if n == "[VERSION]")
        v = {}
        for line in self.data[s:e].split(b"\n"):
            t = line.split()
            if len(t) == 2 and t[0] in (b"major", b"minor", b"revision"):
                v[t[0].decode()] = int(t[1])
        return (v.get("major", 0), v.get("minor", 0), v.get("revision", 0))

    def _rows(self, s: int, e: int, cols: tuple[int, ...], numeric: bool = True) -> _Rows:
        ids, st, en, cc = [], [], [], []
        pos = s
        for line in self.data[s:e].split(b"\n"):
            a, pos = pos, pos + len(line) + 1
            t = line.split()
            if not t or t[0].startswith(b"#"):
                continue
            try:
                ids.append(_int(t[0]))
                cc.append([_int(t[c]) for c in cols] if numeric else [])
            except (ValueError, IndexError):
                raise PieceError(f"malformed line {line[:40]!r}") from None
            st.append(a)
            en.append(min(pos, e))
        ids_a = np.asarray(ids, dtype=np.int64)
        return _Rows(
            ids_a,
            np.asarray(st, dtype=np.int64),
            np.asarray(en, dtype=np.int64),
            np.asarray(cc, dtype=np.int64).reshape(len(ids), len(cols)),
            np.argsort(ids_a, kind="stable"),
        )

    def _shape_rows(self, s: int, e: int) -> _Rows:
        d = self.data
        st = []
        i, dropped = d.find(b"shape_id", s, e), s
        while i >= 0:
            st.append(i)
            i = d.find(b"\nshape_id", i, e)
            i = i + 1 if i >= 0 else -1
            if i - dropped > SCAN_WINDOW:
                self._drop()
                dropped = i
        ids = []
        for a in st:
            eol = d.find(b"\n", a, e)
            t = d[a : eol if eol >= 0 else e].split()
            if len(t) != 2:
                raise PieceError(f"malformed shape header {d[a : a + 40]!r}")
            ids.append(_int(t[1]))
        ids_a = np.asarray(ids, dtype=np.int64)
        en = np.asarray([*st[1:], e], dtype=np.int64)
        return _Rows(ids_a, np.asarray(st, dtype=np.int64), en, np.zeros((len(st), 0), np.int64), np.argsort(ids_a))

    # ---------------------------------------------------------------- closure
    def _closure(self, block_pos: np.ndarray) -> dict:
        """{section: row positions} used by the blocks at ``block_pos`` ('ext:N': extension type N's lines)."""
        b = self.rows["[BLOCKS]"].cols[block_pos]
        out: dict = {}
        rf, ad = b[:, 1], b[:, 5]
        out["[RF]"] = self.rows["[RF]"].positions(np.unique(rf[rf > 0]), "RF event")
        out["[ADC]"] = self.rows["[ADC]"].positions(np.unique(ad[ad > 0]), "ADC event")
        g = np.unique(b[:, 2:5])
        g = g[g > 0]
        in_trap = np.isin(g, self.rows["[TRAP]"].ids)
        out["[TRAP]"] = self.rows["[TRAP]"].positions(g[in_trap], "gradient")
        out["[GRADIENTS]"] = self.rows["[GRADIENTS]"].positions(g[~in_trap], "gradient")
        ext = np.unique(b[:, 6])
        self._add_extensions(ext[ext > 0], out)
        self._add_shapes(out)
        return out

    def _add_extensions(self, ext_ids: np.ndarray, out: dict) -> None:
        rows = self.rows["[EXTENSIONS]"]
        seen = np.zeros(len(rows.ids), dtype=bool)
        todo = rows.positions(ext_ids, "extension list entry")
        while todo.size:
            todo = todo[~seen[todo]]
            seen[todo] = True
            nxt = rows.cols[todo, 2]
            todo = rows.positions(np.unique(nxt[nxt > 0]), "extension list entry")
        pos = np.flatnonzero(seen)
        out["[EXTENSIONS]"] = np.union1d(out.get("[EXTENSIONS]", np.zeros(0, np.int64)), pos)
        self._add_extension_lines(rows.cols[pos], out)

    def _add_extension_lines(self, type_ref: np.ndarray, out: dict) -> None:
        if type_ref.size == 0:
            return
        for typ in np.unique(type_ref[:, 0]):
            if int(typ) not in self.ext_rows:
                raise PieceError(f"extension type {int(typ)} has no section")
            refs = np.unique(type_ref[type_ref[:, 0] == typ, 1])
            key = f"ext:{int(typ)}"
            new = self.ext_rows[int(typ)].positions(refs, f"extension {self.ext_heads[int(typ)].split()[1]} entry")
            out[key] = np.union1d(out.get(key, np.zeros(0, np.int64)), new)

    def _add_shapes(self, out: dict) -> None:
        refs = [self.rows[s].cols[out[s]].ravel() for s in ("[RF]", "[GRADIENTS]", "[ADC]") if s in out]
        ids = np.unique(np.concatenate([np.zeros(0, np.int64), *refs]))
        new = self.shapes.positions(ids[ids > 0], "shape")  # type: ignore[union-attr]
        out["[SHAPES]"] = np.union1d(out.get("[SHAPES]", np.zeros(0, np.int64)), new)

    def unused(self) -> dict:
        """{section: row positions} of the library entries no block uses (directly or through others)."""
        used = self._closure(np.arange(self.n_blocks))
        out = {}
        for name in _LIBRARIES:
            out[name] = np.setdiff1d(np.arange(len(self.rows[name].ids)), used.get(name, []))
        for typ, r in self.ext_rows.items():
            out[f"ext:{typ}"] = np.setdiff1d(np.arange(len(r.ids)), used.get(f"ext:{typ}", []))
        # (a share's entries bring their shapes along, :meth:`piece`; these are the shapes no block uses)
        out["[SHAPES]"] = np.setdiff1d(np.arange(len(self.shapes.ids)), used["[SHAPES]"])  # type: ignore[union-attr]
        return out

    # ---------------------------------------------------------------- assembly
    def piece(self, b0: int, b1: int, extra: dict | None = None) -> bytes:
        """The text of blocks ``b0`` .. ``b1 - 1`` (0-based, file order) with the library lines they use, and the
        rows ``extra`` ({section: row positions}, e.g. a share of :meth:`unused`) with what those use."""
        sel = self._closure(np.arange(b0, b1))
        if extra:
            for k, v in extra.items():
                if k == "[EXTENSIONS]":  # with the entries their chains reach and the lines they name
                    self._add_extensions(self.rows[k].ids[v], sel)
                else:
                    sel[k] = np.union1d(sel.get(k, np.zeros(0, np.int64)), v)
            self._add_shapes(sel)
        d = self.data
        parts: list[bytes] = []
        for name, hs, s, e in self.heads:
            if name == "[SIGNATURE]":
                continue
            if name in ("[VERSION]", "[DEFINITIONS]"):
                parts.append(d[hs:e].rstrip(b"\n") + b"\n\n")
                continue
            if name == "[BLOCKS]":
                r, pos = self.rows[name], np.arange(b0, b1)
            elif name == "[SHAPES]":
                r, pos = self.shapes, sel["[SHAPES]"]  # type: ignore[assignment]
            elif name.startswith("extension "):
                typ = int(name.split()[2])
                r, pos = self.ext_rows[typ], sel.get(f"ext:{typ}", np.zeros(0, np.int64))
            else:
                r, pos = self.rows[name], sel.get(name, np.zeros(0, np.int64))
            if pos.size == 0:
                continue
            parts.append(d[hs:s])
            if name == "[SHAPES]":
                parts.append(b"\n")
                parts.extend(
                    d[int(a) : int(z)].rstrip(b"\n") + b"\n\n" for a, z in zip(r.start[pos], r.end[pos], strict=True)
                )
            else:
                pos = np.sort(pos)
                parts.extend(d[int(a) : int(z)] for a, z in zip(r.start[pos], r.end[pos], strict=True))
                parts.append(b"\n")
        return b"".join(parts) + b"\n"


def share(unused: dict, n: int) -> list[dict]:
    """``unused`` ({section: row positions}) cut into ``n`` shares (contiguous runs, in order)."""
    out: list[dict] = [{} for _ in range(n)]
    for k, v in unused.items():
        for i, chunk in enumerate(np.array_split(np.asarray(v, dtype=np.int64), n)):
            if chunk.size:
                out[i][k] = chunk
    return out


@dataclass(frozen=True)
class TextFacts:
    """What a whole text's own checks read of it (:func:`text_facts`), without holding it."""

    has_cr: bool  # holds a carriage return
    signed: bool  # holds a [SIGNATURE] section
    signature_ok: bool  # :func:`signature_ok`
    signature_types: tuple[bytes, ...]  # the [SIGNATURE] section's stated types (``Type x`` lines)
    markers: frozenset[bytes]  # those of the markers asked for that occur in it


def text_facts(path: str | os.PathLike, markers: tuple[bytes, ...] = ()) -> TextFacts:
    """:class:`TextFacts` of the text at ``path``, read once in chunks (the md5 over the bytes before the newline
    that precedes [SIGNATURE], as :func:`signature_ok`; the first [SIGNATURE] counts)."""
    sig = b"\n[SIGNATURE]"
    keep = max([len(sig), *(len(m) for m in markers)]) - 1
    h, carry, tail = hashlib.md5(), b"", None
    found: set[bytes] = set()
    has_cr = False
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 22), b""):
            has_cr = has_cr or b"\r" in chunk
            if tail is not None:
                tail += chunk
                continue
            buf = carry + chunk
            found.update(m for m in markers if m in buf)
            i = buf.find(sig)
            if i >= 0:
                h.update(buf[:i])
                tail = buf[i:]
                continue
            cut = max(len(buf) - keep, 0)
            h.update(buf[:cut])
            carry = buf[cut:]
    if tail is None:
        h.update(carry)
        return TextFacts(has_cr, False, True, (), frozenset(found))
    found.update(m for m in markers if m in tail)
    stated, types = _signature_fields(tail)
    ok = stated is not None and h.hexdigest() == stated
    return TextFacts(has_cr, True, ok, tuple(types), frozenset(found))


@contextlib.contextmanager
def mapped_text(path: str | os.PathLike) -> Iterator[tuple[mmap.mmap | bytes, Callable[[], None]]]:
    """(the text at ``path`` as a read-only memory map, a function that releases its resident pages): a long
    text read in pieces is not held in memory (its pages come back from the page cache when read again).  An
    empty file is ``b""`` (no map)."""
    with open(path, "rb") as f:
        if os.fstat(f.fileno()).st_size == 0:
            yield b"", lambda: None
            return
        mm = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
    advise = getattr(mm, "madvise", None)
    dontneed = getattr(mmap, "MADV_DONTNEED", None)

    def drop() -> None:
        if advise is not None and dontneed is not None:
            advise(dontneed)

    try:
        yield mm, drop
    finally:
        mm.close()


def signature_ok(data: bytes) -> bool:
    """The whole text's md5 [SIGNATURE] (Pulseq's: over the bytes before the newline that precedes it) matches;
    True for an unsigned text."""
    i = data.find(b"\n[SIGNATURE]")
    if i < 0:
        return True
    stated = _signature_fields(data[i:])[0]
    return stated is not None and hashlib.md5(data[:i]).hexdigest() == stated


def _signature_fields(section: bytes) -> tuple[str | None, tuple[bytes, ...]]:
    """(the last stated ``Hash``, lower case, or None; every stated ``Type``) of a [SIGNATURE] section's bytes."""
    stated, types = None, []
    for line in section.split(b"\n"):
        t = line.split()
        if len(t) == 2 and t[0] == b"Hash":
            stated = t[1].decode("ascii", "replace").lower()
        if len(t) == 2 and t[0] == b"Type":
            types.append(t[1])
    return stated, tuple(types)
