"""Atomic, non-clobbering output files, written all together or not at all.

Every file dtoc writes goes through :func:`atomic_write_bytes` / :func:`atomic_write_text`:
the content is written to a temporary file in the destination folder, flushed, fsync'ed and then
renamed over the destination, so a reader never sees a half-written file.  An existing destination
is only replaced when ``force=True``.

Inside :func:`outputs_together` (every command with more than one output uses it) the renames wait
for the end of the block: a failure or an interrupt anywhere before it leaves no output written or
changed; at the end all staged files are moved into place with SIGINT/SIGTERM held back, and a failed
move restores the files already replaced (all or none).
"""

from __future__ import annotations

import contextlib
import contextvars
import hashlib
import os
import shutil
import signal
import tempfile
from collections.abc import Iterator
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


class _Staged:
    """Files written to temporaries, waiting to be moved into place together."""

    def __init__(self) -> None:
        self.items: list[tuple[str, Path]] = []  # (temporary, destination)

    def discard(self) -> None:
        for tmp, _ in self.items:
            _unlink(tmp)
        self.items.clear()

    def commit(self) -> None:
        """Move every staged file into place; on a failure undo the moves already done and re-raise."""
        done: list[tuple[Path, str | None]] = []  # (destination, backup of what it replaced)
        with signals_held():
            try:
                for tmp, dest in self.items:
                    backup = None
                    if dest.exists():
                        backup = _temp_name(dest, ".bak")
                        try:
                            os.link(dest, backup)
                        except OSError:  # no hard links on this file system
                            shutil.copyfile(dest, backup)
                    os.replace(tmp, dest)
                    done.append((dest, backup))
            except BaseException:
                for dest, backup in reversed(done):
                    if backup is not None:
                        os.replace(backup, dest)
                    else:
                        _unlink(dest)
                self.discard()
                raise
            for _, backup in done:
                if backup is not None:
                    _unlink(backup)
            self.items.clear()


_STAGE: contextvars.ContextVar[_Staged | None] = contextvars.ContextVar("dtoc_outputs_together", default=None)


@contextlib.contextmanager
def outputs_together() -> Iterator[None]:
    """Hold back every :func:`atomic_write_bytes` of the block and move the files into place at its end, all
    together; an exception (or interrupt) inside the block writes none of them.  Nested blocks join the
    outermost one."""
    if _STAGE.get() is not None:
        yield
        return
    staged = _Staged()
    token = _STAGE.set(staged)
    try:
        yield
    except BaseException:
        staged.discard()
        raise
    finally:
        _STAGE.reset(token)
    staged.commit()


@contextlib.contextmanager
def signals_held() -> Iterator[None]:
    """Block SIGINT/SIGTERM (main thread, POSIX) while the staged files move; delivered right after."""
    can = hasattr(signal, "pthread_sigmask")
    old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT, signal.SIGTERM}) if can else None
    try:
        yield
    finally:
        if can and old is not None:
            signal.pthread_sigmask(signal.SIG_SETMASK, old)


def _temp_name(p: Path, suffix: str) -> str:
    fd, name = tempfile.mkstemp(prefix=f".{p.name}.", suffix=suffix, dir=p.parent if str(p.parent) else ".")
    os.close(fd)
    os.unlink(name)
    return name


def _unlink(name: str | os.PathLike) -> None:
    try:
        os.unlink(name)
    except OSError:
        pass


def atomic_write_bytes(path: str | os.PathLike, data: bytes, force: bool = False) -> Path:
    """Write ``data`` to ``path`` atomically; refuse to overwrite unless ``force``.  Inside
    :func:`outputs_together` the file appears at the end of that block, together with the others."""
    p = check_output_path(path, force)
    staged = _STAGE.get()
    if staged is not None and any(os.path.realpath(d) == os.path.realpath(p) for _, d in staged.items):
        raise InputError(f"{p}: written twice by one command")
    fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=".tmp", dir=p.parent if str(p.parent) else ".")
    try:
        umask = os.umask(0)
        os.umask(umask)
        os.fchmod(fd, 0o666 & ~umask)  # mkstemp creates 0600; give the file ordinary permissions
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        if staged is not None:
            staged.items.append((tmp, p))
        else:
            os.replace(tmp, p)
    except BaseException:
        _unlink(tmp)
        raise
    return p


def atomic_write_text(path: str | os.PathLike, text: str, force: bool = False) -> Path:
    """Write ``text`` (UTF-8, LF line endings kept as given) atomically."""
    return atomic_write_bytes(path, text.encode("utf-8"), force=force)


def sha256_bytes(data: bytes) -> str:
    """Hex sha256 of ``data``."""
    return hashlib.sha256(data).hexdigest()


def sha256_file(path: str | os.PathLike) -> str:
    """Hex sha256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()
