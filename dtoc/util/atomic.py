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
import errno
import hashlib
import os
import shutil
import signal
import stat
import tempfile
from collections.abc import Iterator
from pathlib import Path

from dtoc.errors import InputError


def check_output_path(path: str | os.PathLike, force: bool) -> Path:
    """Raise unless ``path`` may be written: its folder exists, and it does not exist or (with ``force``) is a
    regular file.  A symbolic link (``/dev/stdout`` and the like), a device node, a FIFO, a socket or a
    folder is never written through nor replaced, ``--force`` or not (standard output is ``-``)."""
    p = Path(path)
    try:
        st = os.lstat(p)
    except FileNotFoundError:
        st = None
    except OSError as e:
        raise InputError(f"{p}: output path unusable ({e.strerror})") from None
    if st is not None:
        if stat.S_ISLNK(st.st_mode):
            raise InputError(
                f"{p}: output is a symbolic link: dtoc never writes through or replaces a link; give the real "
                "path (or '-' for standard output where the option takes it)"
            )
        if stat.S_ISDIR(st.st_mode):
            raise InputError(f"{p}: output is a directory")
        if not stat.S_ISREG(st.st_mode):
            raise InputError(
                f"{p}: output is not a regular file (a device, FIFO or socket): never written or replaced, "
                "--force or not"
            )
        if not force:
            raise InputError(f"{p}: output exists; pass --force to overwrite")
    parent = p.parent if str(p.parent) else Path(".")
    if not parent.is_dir():
        raise InputError(f"{p}: output folder {parent} does not exist")
    return p


def unused_path(path: str | os.PathLike, keep: str | os.PathLike | None = None) -> Path:
    """``path`` if nothing exists there (or it is ``keep``, a file this command may replace), else the first of
    ``<stem>-2<suffix>``, ``-3``, ... that is free: a default output name never replaces an unrelated file."""
    p = Path(path)
    if not os.path.lexists(p) or (keep is not None and os.path.realpath(p) == os.path.realpath(keep)):
        return p
    name, dot, ext = p.name.partition(".")
    for i in range(2, 10_000):
        q = p.with_name(f"{name}-{i}{dot}{ext}")
        if not os.path.lexists(q):
            return q
    raise InputError(f"{p}: no free name beside it for the default output")


def _identity(path: str | os.PathLike) -> tuple[int, int] | None:
    """(device, inode) of an existing file (hard links to one file share it), else None."""
    try:
        st = os.stat(path)
    except (OSError, ValueError):
        return None
    return (st.st_dev, st.st_ino)


def check_outputs(outputs: dict, inputs: dict, force: bool) -> None:
    """Refuse, before any work, outputs that exist (without ``force``), that lack a folder, that are links or
    not regular files, that name the same file twice, or that resolve to an input (even with ``force``: an
    input is never destroyed; the same file under another name or a hard link counts as the input).  The input
    files are checked too (:func:`check_input_files`: regular files, ``.npz`` archives within their bounds).

    ``outputs`` / ``inputs``: {option name: path or None}; an output ``"-"`` is standard output (skipped).

    Raises:
        InputError naming the option(s).
    """
    seen: dict[str, str] = {}
    live = {k: v for k, v in inputs.items() if v is not None and str(v) != "-"}
    ins = {os.path.realpath(v): k for k, v in live.items()}
    ids = {i: k for k, v in live.items() if (i := _identity(v)) is not None}
    for opt, p in outputs.items():
        if p is None or str(p) == "-":
            continue
        real = os.path.realpath(p)
        ident = _identity(p)
        hit = ins.get(real) or (ids.get(ident) if ident is not None else None)
        if hit is not None:
            raise InputError(f"{p}: {opt} would overwrite the {hit} input; choose another output path")
        if real in seen:
            raise InputError(f"{p}: given for both {seen[real]} and {opt}; each output needs its own path")
        seen[real] = opt
        check_output_path(p, force)
    check_input_files(live)


def check_input_files(inputs: dict) -> None:
    """Every existing input that is a ``.npz`` archive is checked before it is opened
    (:func:`dtoc.util.validate.check_npz_archive`: no pickles, members' declared sizes within memory)."""
    from dtoc.util.validate import check_npz_archive

    for opt, p in inputs.items():
        if str(p).lower().endswith(".npz") and os.path.isfile(p):
            check_npz_archive(p, opt)


def _publish(tmp: str, dest: Path, force: bool) -> None:
    """Move the complete temporary ``tmp`` to ``dest``.  Without ``force`` the destination must not exist: the
    file is published with a hard link, which fails if another writer got there first (exactly one of two
    concurrent writers wins; the other gets one line, and nothing is replaced).  With ``force`` an existing
    regular file is replaced in one rename; a link or non-regular file that appeared meanwhile is refused."""
    if not force:
        try:
            os.link(tmp, dest)
        except FileExistsError:
            raise InputError(
                f"{dest}: output appeared while this command ran (another writer?); nothing replaced"
            ) from None
        except OSError as e:
            if e.errno not in (errno.EPERM, errno.ENOTSUP, errno.EOPNOTSUPP, errno.EXDEV, errno.EMLINK):
                raise
            # no hard links on this file system: reserve the name exclusively, then replace the reservation
            try:
                fd = os.open(dest, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
            except FileExistsError:
                raise InputError(
                    f"{dest}: output appeared while this command ran (another writer?); nothing replaced"
                ) from None
            os.close(fd)
            os.replace(tmp, dest)
            return
        _unlink(tmp)
        return
    check_output_path(dest, True)  # still a regular file (or absent) right before the rename
    os.replace(tmp, dest)


class _Staged:
    """Files written to temporaries, waiting to be moved into place together."""

    def __init__(self) -> None:
        self.items: list[tuple[str, Path, bool]] = []  # (temporary, destination, force)

    def discard(self) -> None:
        for tmp, _, _ in self.items:
            _unlink(tmp)
        self.items.clear()

    def commit(self) -> None:
        """Move every staged file into place; on a failure undo the moves already done and re-raise."""
        done: list[tuple[Path, str | None]] = []  # (destination, backup of what it replaced)
        with signals_held():
            try:
                for tmp, dest, force in self.items:
                    backup = None
                    if force and os.path.lexists(dest):
                        check_output_path(dest, True)
                        backup = _temp_name(dest, ".bak")
                        try:
                            os.link(dest, backup)
                        except OSError:  # no hard links on this file system
                            shutil.copyfile(dest, backup)
                    _publish(tmp, dest, force)
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
    p = _not_staged(check_output_path(path, force))
    fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=".tmp", dir=p.parent if str(p.parent) else ".")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        _place(tmp, p, force)
    except BaseException:
        _unlink(tmp)
        raise
    return p


def atomic_move_file(src: str | os.PathLike, path: str | os.PathLike, force: bool = False) -> Path:
    """Move the complete file ``src`` (on the file system of ``path``'s folder: a temporary there) to ``path``
    as :func:`atomic_write_bytes` writes bytes: never read into memory (a long sequence's text)."""
    p = _not_staged(check_output_path(path, force))
    fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=".tmp", dir=p.parent if str(p.parent) else ".")
    os.close(fd)
    try:
        os.replace(src, tmp)
        _place(tmp, p, force)
    except BaseException:
        _unlink(tmp)
        raise
    return p


def _not_staged(p: Path) -> Path:
    """``p``, refused if this command's :func:`outputs_together` block already stages a file there."""
    staged = _STAGE.get()
    if staged is not None and any(os.path.realpath(d) == os.path.realpath(p) for _, d, _ in staged.items):
        raise InputError(f"{p}: written twice by one command")
    return p


def _place(tmp: str, p: Path, force: bool) -> None:
    """The complete temporary ``tmp`` made durable with ordinary permissions, then moved to ``p`` (or staged
    there, inside :func:`outputs_together`)."""
    staged = _STAGE.get()
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)  # mkstemp creates 0600; give the file ordinary permissions
    with open(tmp, "rb") as f:
        os.fsync(f.fileno())
    if staged is not None:
        staged.items.append((tmp, p, force))
    else:
        with signals_held():
            _publish(tmp, p, force)


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
