"""The dense linear algebra's thread count (OpenBLAS, as loaded by numpy and scipy), set for a stretch of work.

torch's thread count is fixed per run (``OptimizeConfig.threads``, :func:`dtoc.optimize.optimizer.set_deterministic`);
numpy's and scipy's OpenBLAS start one thread per core.  For the windowed solve's many small dense products
(matrix-vector products of ~1,600 x 1,600, one window after another) those threads cost more than they give on a
shared machine: a product took 4.5 ms CPU / 13 ms wall with two threads and 0.8 ms / 2.2 ms with one on a 2-core
machine at load 11 (docs/benchmarks.md, "Long sequences").  And a product's last bits depend on the thread count,
so a run's numbers would otherwise depend on the machine's cores.

The libraries are found among the ones this process has loaded (``/proc/self/maps``: Linux); elsewhere, or for a
BLAS other than OpenBLAS, :func:`blas_threads` changes nothing.
"""

from __future__ import annotations

import ctypes
import functools
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import ParamSpec, TypeVar

P = ParamSpec("P")
R = TypeVar("R")

#: the (get, set) entry points of OpenBLAS builds: plain, 64-bit interface, and the scipy-openblas wheels' prefixed
_NAMES = [
    (p + "openblas_get_num_threads" + s, p + "openblas_set_num_threads" + s)
    for p in ("", "scipy_")
    for s in ("", "64_")
]
_found: list[tuple] | None = None


def _openblas() -> list[tuple]:
    """(get, set) of every loaded OpenBLAS library (found once per process)."""
    global _found
    if _found is not None:
        return _found
    out: list[tuple] = []
    try:
        with open("/proc/self/maps") as f:
            paths = sorted({ln.split()[-1] for ln in f if "openblas" in ln.lower() and "/" in ln})
    except OSError:
        paths = []
    for p in paths:
        try:
            lib = ctypes.CDLL(p)
        except OSError:
            continue
        for g, s in _NAMES:
            get, set_ = getattr(lib, g, None), getattr(lib, s, None)
            if get is not None and set_ is not None:
                get.restype, set_.argtypes = ctypes.c_int, [ctypes.c_int]
                out.append((get, set_))
                break
    _found = out
    return out


@contextmanager
def blas_threads(n: int) -> Iterator[None]:
    """Run the block with every loaded OpenBLAS on ``n`` threads (at least 1); the previous counts are restored."""
    libs = _openblas()
    old = [get() for get, _ in libs]
    for _, set_ in libs:
        set_(max(int(n), 1))
    try:
        yield
    finally:
        for (_, set_), k in zip(libs, old):
            set_(k)


def on_torch_threads(fn: Callable[P, R]) -> Callable[P, R]:
    """Decorate ``fn`` to run with every loaded OpenBLAS on torch's thread count (the run's, as
    :func:`dtoc.optimize.optimizer.set_deterministic` set it)."""

    @functools.wraps(fn)
    def wrapped(*args: P.args, **kwargs: P.kwargs) -> R:
        import torch

        with blas_threads(torch.get_num_threads()):
            return fn(*args, **kwargs)

    return wrapped
