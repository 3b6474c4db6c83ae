"""The one validation layer at the command boundary: accepted ranges of options and file-borne values, names
that reach an output, ``.npz`` archives before they are opened, and cost estimates against this machine.

Every range is stated once, in :data:`RANGES` (docs/cli.md, "Accepted ranges", is the same table); a value
outside it is refused with one line naming the value, the option (or file and key) and the range, before
any work.  The ranges are physical (what any MR gradient system, phantom or run can mean), not a scanner's
limits: ``--gmax 1e6`` mT/m is a typo or a unit slip, never a scanner.
"""

from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass

from dtoc.errors import InputError


@dataclass(frozen=True)
class Range:
    """``lo <(=) value <(=) hi`` in ``unit``; ``integer`` values must be whole numbers."""

    lo: float
    hi: float
    unit: str = ""
    lo_open: bool = False
    integer: bool = False
    what: str = ""

    def text(self) -> str:
        lo = "(" if self.lo_open else "["
        u = f" {self.unit}" if self.unit else ""
        return f"{lo}{self.lo:g}, {self.hi:g}]{u}"


#: key -> accepted range (docs/cli.md, "Accepted ranges", lists the same)
RANGES: dict[str, Range] = {
    "gmax": Range(0, 5000, "mT/m", lo_open=True, what="gradient amplitude limit (human 20-300, preclinical <= 5000)"),
    "smax": Range(0, 1e5, "T/m/s", lo_open=True, what="slew-rate limit (human 50-1200, preclinical <= 1e5)"),
    "b0": Range(0, 21.1, "T", lo_open=True, what="field strength"),
    "seed": Range(0, 2**32 - 1, integer=True, what="random seed"),
    "weight": Range(0, 1e6, what="loss weight (--w-image, --w-k, --w-rf)"),
    "lr": Range(0, 1e3, lo_open=True, what="learning rate / first move, mT/m"),
    "iters": Range(0, 100_000, integer=True, what="iterations (--iters, --warm-iters)"),
    "k_tol": Range(0, 10, "dk", lo_open=True, what="k-space tolerance of the solver"),
    "augment": Range(0, 64, integer=True, what="rotated phantoms"),
    "dummies": Range(0, 100_000, integer=True, what="dummy repetitions"),
    "workers": Range(1, 1024, integer=True, what="batch workers"),
    "threads": Range(1, 1024, integer=True, what="torch threads"),
    "max_effects": Range(0, 64, integer=True, what="effects identify may add"),
    "jobs": Range(1, 10_000, integer=True, what="jobs of one batch plan"),
    "phantom_n": Range(4, 1024, integer=True, what="phantom matrix per axis"),
}

#: a name that reaches an output (a report, a table, a .seq definition): printable, one line, bounded
_NAME_OK = re.compile(r"^[A-Za-z0-9][A-Za-z0-9 _.,:;+()\[\]/@#%=-]{0,199}$")


def check_range(key: str, value, label: str | None = None) -> None:
    """Refuse ``value`` outside :data:`RANGES` ``[key]`` (None passes: not given).  ``label`` names where the
    value came from (an option, or ``file: key``); default ``--key``.

    Raises:
        InputError: ``"--gmax 1e+06 mT/m: outside the accepted range (0, 5000] mT/m (...)"``.
    """
    if value is None:
        return
    r = RANGES[key]
    label = label or f"--{key.replace('_', '-')}"
    u = f" {r.unit}" if r.unit else ""
    bad = isinstance(value, bool) or not isinstance(value, (int, float))
    if not bad:
        v = float(value) if not isinstance(value, int) else value
        if isinstance(v, float) and not math.isfinite(v):
            bad = True
        elif r.integer and isinstance(value, float) and not float(value).is_integer():
            bad = True
        else:
            bad = v < r.lo or v > r.hi or (r.lo_open and v == r.lo)
    if bad:
        shown = f"{value:g}" if isinstance(value, float) else str(value)
        kind = "a whole number in " if r.integer else ""
        raise InputError(f"{label} {shown}{u}: outside the accepted range: {kind}{r.text()} ({r.what}; docs/cli.md)")


def check_name(value: str, label: str) -> str:
    """A name printed in reports and tables: one line of printable characters (letters, digits, space and
    ``_ . , : ; + ( ) [ ] / @ # % = -``), at most 200; anything else (a newline that would forge a line) is refused."""
    if not isinstance(value, str) or not _NAME_OK.match(value):
        raise InputError(
            f"{label} {escape(str(value))}: a name must be one line of letters, digits, space and _.,:;+()[]/@#%=- "
            "(at most 200 characters, starting with a letter or digit)"
        )
    return value


def escape(text: str, limit: int = 80) -> str:
    """``text`` safe to print on one line: control characters escaped, quoted, cut at ``limit``."""
    r = repr(str(text)[:limit])
    return r + ("..." if len(str(text)) > limit else "")


# ------------------------------------------------------------------------------------------------------
# the machine
# ------------------------------------------------------------------------------------------------------
def available_memory_bytes() -> int:
    """Memory this process may still use: MemAvailable (Linux), else physical memory; at most the cgroup limit."""
    avail = None
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    avail = int(line.split()[1]) * 1024
                    break
    except OSError:
        pass
    if avail is None:
        try:
            avail = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
        except (ValueError, OSError, AttributeError):
            avail = 8 << 30
    for cg in ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory/memory.limit_in_bytes"):
        try:
            with open(cg) as f:
                t = f.read().strip()
            if t.isdigit():
                avail = min(avail, int(t))
        except OSError:
            pass
    return int(avail)


def cores() -> int:
    """CPU cores this process may run on."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def gib(n: float) -> str:
    return f"{n / 2**30:.3g} GiB"


#: the largest .npz dtoc opens (GIRFs, phantoms within MAX_PHANTOM_VOXELS, measurements, checkpoints)
NPZ_MAX_BYTES = 2 << 30


# ------------------------------------------------------------------------------------------------------
# .npz archives: checked before numpy inflates them
# ------------------------------------------------------------------------------------------------------
def check_npz_archive(path: str | os.PathLike, label: str = "", max_bytes: float | None = None) -> dict:
    """Refuse an ``.npz`` whose members are pickled objects, not ``.npy`` arrays, or whose declared sizes
    (zip entry sizes and ``.npy`` header shapes, read without inflating) exceed ``max_bytes`` (default: a
    quarter of the available memory) or disagree with each other (a zip bomb).  A file that is not a zip is
    left to its loader (which names what it expected).  Returns {member name without .npy: declared shape}."""
    import zipfile

    import numpy as np

    where = f"{path}" + (f" ({label})" if label else "")
    cap = max_bytes if max_bytes is not None else min(available_memory_bytes() / 8, NPZ_MAX_BYTES)
    try:
        zf = zipfile.ZipFile(path)
    except (zipfile.BadZipFile, OSError, ValueError):
        return {}
    total = 0
    shapes: dict = {}
    with zf:
        infos = zf.infolist()
        if len(infos) > 10_000:
            raise InputError(f"{where}: {len(infos)} archive members: not a dtoc .npz")
        for info in infos:
            total += info.file_size
            if total > cap:
                raise InputError(
                    f"{where}: members declare {gib(total)} uncompressed, more than the {gib(cap)} accepted "
                    "(2 GiB, at most an eighth of the available memory): refused before inflating"
                )
            if info.file_size > 256 << 20 and info.file_size > 200 * max(info.compress_size, 1):
                raise InputError(
                    f"{where}: member {escape(info.filename)} inflates {info.compress_size} bytes to {gib(info.file_size)} "
                    f"({info.file_size / max(info.compress_size, 1):.0f}x): refused before inflating (a zip bomb)"
                )
            if not info.filename.endswith(".npy"):
                continue
            try:
                with zf.open(info) as f:
                    version = np.lib.format.read_magic(f)
                    if version == (1, 0):
                        shape, _fortran, dtype = np.lib.format.read_array_header_1_0(f)
                    else:
                        shape, _fortran, dtype = np.lib.format.read_array_header_2_0(f)
            except Exception:  # noqa: BLE001 - a damaged member: one line
                raise InputError(f"{where}: member {escape(info.filename)} is not a readable .npy array") from None
            if dtype.hasobject:
                raise InputError(
                    f"{where}: member {escape(info.filename)} holds pickled Python objects: never loaded (numbers only)"
                )
            n = math.prod(int(x) for x in shape) * dtype.itemsize
            if n > cap:
                raise InputError(
                    f"{where}: member {escape(info.filename)} declares shape {tuple(shape)} ({gib(n)}), more than the "
                    f"{gib(cap)} accepted: refused before inflating"
                )
            if n > info.file_size + 4096:  # the header's shape promises more data than the entry holds
                raise InputError(f"{where}: member {escape(info.filename)} is truncated (shape {tuple(shape)})")
            shapes[info.filename[: -len(".npy")]] = tuple(int(x) for x in shape)
    return shapes
