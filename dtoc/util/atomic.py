"""Atomic, non-clobbering output files.

Every file dtoc writes goes through :func:`atomic_write_bytes` / :func:`atomic_write_text`:
the content is written to a temporary file in the destination folder, flushed, fsync'ed and then
renamed over the destination, so a reader never sees a half-written file.  An existing destination
is only replaced when ``force=True``.
"""

from __future__ import annotations

import hashlib
import os
import tempfile
from pathlib import Path

from dtoc.errors import InputError


def check_output_path(path: str | os.PathLike, force: bool) -> Path:
    """Raise unless ``path`` may be written (parent exists; not existing, or ``force``)."""
    p = Path(path)
    if p.exists() and not force:
        raise InputError(f"{p}: output exists; pass --force to overwrite")
    if p.is_dir():
        raise InputError(f"{p}: output is a directory")
    parent = p.parent if str(p.parent) else Path(".")
    if not parent.is_dir():
        raise InputError(f"{p}: output folder {parent} does not exist")
    return p


def check_outputs(outputs: dict, inputs: dict, force: bool) -> None:
    """Refuse, before any work, outputs that exist (without ``force``), that lack a folder, that name the
    same file twice, or that resolve to an input (even with ``force``: an input is never destroyed).

    ``outputs`` / ``inputs``: {option name: path or None}; an output ``"-"`` is standard output (skipped).

    Raises:
        InputError naming the option(s).
    """
    seen: dict[str, str] = {}
    ins = {os.path.realpath(v): k for k, v in inputs.items() if v is not None and str(v) != "-"}
    for opt, p in outputs.items():
        if p is None or str(p) == "-":
            continue
        real = os.path.realpath(p)
        if real in ins:
            raise InputError(f"{p}: {opt} would overwrite the {ins[real]} input; choose another output path")
        if real in seen:
            raise InputError(f"{p}: given for both {seen[real]} and {opt}; each output needs its own path")
        seen[real] = opt
        check_output_path(p, force)


def atomic_write_bytes(path: str | os.PathLike, data: bytes, force: bool = False) -> Path:
    """Write ``data`` to ``path`` atomically; refuse to overwrite unless ``force``."""
    p = check_output_path(path, force)
    fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=".tmp", dir=p.parent if str(p.parent) else ".")
    try:
        umask = os.umask(0)
        os.umask(umask)
        os.fchmod(fd, 0o666 & ~umask)  # mkstemp creates 0600; give the file ordinary permissions
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, p)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
    return p


def atomic_write_text(path: str | os.PathLike, text: str, force: bool = False) -> Path:
    """Write ``text`` (UTF-8, LF line endings kept as given) atomically."""
    return atomic_write_bytes(path, text.encode("utf-8"), force=force)


def sha256_file(path: str | os.PathLike) -> str:
    """Hex sha256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()
