"""The batch output folder: a content-addressed store of finished jobs, and a link per job name.

Layout (docs/batch.md)::

    OUT/.dtoc-batch              marker: this folder is dtoc's (a non-empty folder without it is refused)
    OUT/jobs/<key20>/            one finished job: optimized.seq, manifest.json, report.png,
                                 optimized.traj.npz and job.json (key, request, sha256 of each file, figures)
    OUT/<job name> -> jobs/<key20>
    OUT/.staging/                commits in progress (removed at the start of every run)

Only the process that runs the batch writes here.  A job folder is written complete under ``.staging`` and
renamed into ``jobs/`` in one step (a rename of a folder is atomic), so ``jobs/`` holds finished jobs or
nothing; a folder whose files no longer match the hashes of its ``job.json`` is not a cache hit (it is
moved aside and the job runs again).  A job folder is never rewritten: a changed input gives a new key.
"""

from __future__ import annotations

import json
import os
import shutil
import uuid
from pathlib import Path

from dtoc.errors import InputError

MARKER = ".dtoc-batch"
LOCK = ".dtoc-batch.lock"
RECORD = "job.json"
KEY_CHARS = 20


class Store:
    """The output folder of one batch (see module docstring)."""

    def __init__(self, root: Path) -> None:
        self.root = Path(root)
        self.jobs = self.root / "jobs"
        self.staging = self.root / ".staging"
        self._lock_fd: int | None = None

    @classmethod
    def check(cls, root: str | Path, names: list[str], inputs: dict | None = None) -> None:
        """Refuse, before the folder is created or touched: a file, a foreign non-empty folder, a folder that is
        (or holds) an input, and a job name whose link would clash with something that is not a job link."""
        r = Path(root)
        if os.path.lexists(r) and not r.is_dir():
            raise InputError(f"{r}: --out must be a folder (it is a file)")
        if r.is_dir() and any(x.name != LOCK for x in r.iterdir()) and not (r / MARKER).is_file():
            raise InputError(f"{r}: not empty and not a dtoc batch folder (no {MARKER}): give a new or empty folder")
        if not r.parent.is_dir():
            raise InputError(f"{r}: --out's parent folder {r.parent} does not exist")
        real = os.path.realpath(r)
        for label, p in (inputs or {}).items():
            rp = os.path.realpath(p)
            if rp == real or rp.startswith(real + os.sep):
                raise InputError(f"{r}: --out holds the {label} input {p}; choose another --out")
        for n in names:
            d = r / n
            if n in ("jobs", MARKER, LOCK, ".staging") or (os.path.lexists(d) and not d.is_symlink()):
                raise InputError(
                    f"{d}: job {n} would replace something that is not a job link of dtoc batch; rename the job "
                    "or choose another --out"
                )

    @classmethod
    def open(cls, root: str | Path) -> Store:
        """Create or reopen ``root`` and lock it for this batch (a second batch on it is refused in one line);
        refuse a non-empty folder that is not a batch folder, or a file."""
        r = Path(root)
        cls.check(r, [])
        created = not r.exists()
        r.mkdir(exist_ok=True)
        s = cls(r)
        try:
            s._lock()
        except BaseException:
            if created:
                shutil.rmtree(r, ignore_errors=True)
            raise
        s.jobs.mkdir(parents=True, exist_ok=True)
        (r / MARKER).write_text("dtoc batch output folder (docs/batch.md)\n")
        shutil.rmtree(s.staging, ignore_errors=True)  # commits a killed run left half-done
        s.staging.mkdir()
        return s

    def _lock(self) -> None:
        """An exclusive lock on ``OUT/.dtoc-batch.lock`` held until :meth:`close` (released by the OS if the
        process dies): two batches never write one folder."""
        import fcntl

        fd = os.open(self.root / LOCK, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(fd)
            raise InputError(
                f"{self.root}: another dtoc batch is running on this --out (it holds {LOCK}); wait for it or choose "
                "another --out"
            ) from None
        self._lock_fd = fd

    def job_dir(self, key: str) -> Path:
        return self.jobs / key[:KEY_CHARS]

    def lookup(self, key: str) -> dict | None:
        """The record of the finished job ``key``, or None (absent, or its files do not match their hashes)."""
        from dtoc.util.atomic import sha256_file

        d = self.job_dir(key)
        try:
            rec = json.loads((d / RECORD).read_text())
            ok = rec.get("key") == key and all(sha256_file(d / f) == h for f, h in rec["files"].items())
        except (OSError, ValueError, KeyError, TypeError, AttributeError):
            ok = False
        if ok:
            return rec
        if d.exists():  # damaged or foreign: set aside, never trusted, never deleted silently
            d.rename(self.staging.parent / f".damaged-{d.name}-{uuid.uuid4().hex[:8]}")
        return None

    def commit(self, key: str, files: dict[str, bytes], record: dict) -> dict:
        """Write a finished job (its output files and ``job.json``) and move it into place in one rename.
        Returns the record (the existing one if the same key was committed meanwhile)."""
        from dtoc.util.atomic import sha256_bytes, signals_held

        tmp = self.staging / f"{key[:KEY_CHARS]}.{uuid.uuid4().hex[:8]}"
        tmp.mkdir()
        rec = {**record, "key": key, "files": {n: sha256_bytes(b) for n, b in sorted(files.items())}}
        for n, b in sorted(files.items()):
            _write(tmp / n, b)
        _write(tmp / RECORD, (json.dumps(rec, indent=1, sort_keys=True) + "\n").encode())
        _fsync_dir(tmp)
        with signals_held():
            try:
                tmp.rename(self.job_dir(key))
            except OSError:
                shutil.rmtree(tmp, ignore_errors=True)
                existing = self.lookup(key)
                if existing is None:
                    raise
                return existing
            _fsync_dir(self.jobs)
        return rec

    def link(self, name: str, key: str) -> None:
        """``OUT/<name>`` -> ``jobs/<key20>`` (replaced in one step; a non-link of that name is refused)."""
        dst = self.root / name
        if dst.exists() and not dst.is_symlink():
            raise InputError(f"{dst}: exists and is not a job link of dtoc batch; remove it or choose another --out")
        target = Path("jobs") / self.job_dir(key).name
        if dst.is_symlink() and Path(os.readlink(dst)) == target:
            return
        tmp = self.root / f".{name}.{uuid.uuid4().hex[:8]}"
        os.symlink(target, tmp)
        os.replace(tmp, dst)

    def close(self) -> None:
        shutil.rmtree(self.staging, ignore_errors=True)
        if self._lock_fd is not None:
            os.close(self._lock_fd)  # releases the lock
            self._lock_fd = None


def _write(p: Path, b: bytes) -> None:
    with open(p, "wb") as f:
        f.write(b)
        f.flush()
        os.fsync(f.fileno())


def _fsync_dir(p: Path) -> None:
    try:
        fd = os.open(p, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)
