"""What runs on a worker: one job = one :func:`dtoc.optimize.request.run_request` in a private folder.

The worker runs the job's request with that folder as working directory (the request names its outputs
``optimized.seq``, ``manifest.json``, ... relative to it, as ``dtoc optimize`` run in a job folder would),
reads the outputs back as bytes and returns them: results travel back to the batch process, which alone
writes the output folder.  Inputs are read where the plan names them (absolute paths: on a cluster, a file
system the workers share).  Nothing here imports torch at module level (spawned workers start fast).

Errors never escape as tracebacks: a job that fails returns ``status: failed`` with the one line ``dtoc``
would print (:func:`dtoc.errors.describe`).
"""

from __future__ import annotations

import os
import shutil
import signal
import tempfile
import threading
import time
from pathlib import Path

#: one job at a time per process (the working directory is per process)
_LOCK = threading.Lock()
#: threads of the numeric libraries per worker, set by :func:`init_worker` before torch is imported
THREAD_ENV = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")


def init_worker(threads: int) -> None:
    """Process-pool initializer: SIGINT ignored (the batch process decides what an interrupt does; a terminal's
    Ctrl-C reaches the whole process group), SIGTERM the default action (a worker sent SIGTERM by someone else
    ends at once, without a Python exception surfacing half-way through an import), numeric libraries limited to
    ``threads`` threads, and the signals the parent held back while starting us released."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    for k in THREAD_ENV:
        os.environ[k] = str(threads)
    if hasattr(signal, "pthread_sigmask"):
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT, signal.SIGTERM})


def run_job(payload: dict) -> dict:
    """Run one job.  ``payload``: ``request`` (OptimizeRequest fields, JSON-able), ``key``, ``work_root``
    (folder for the private working folder; None: the system's temporary folder).

    Returns ``status`` ('ok', 'failed', 'interrupted'), ``files`` {name: bytes} (ok only), ``error`` (one
    line), ``exit_code``, ``seconds``, ``worker`` (host:pid) and ``peak_rss_mb`` (the worker process's so far).
    """
    from dtoc.errors import describe

    t0 = time.perf_counter()
    out: dict = {"key": payload["key"], "worker": f"{os.uname().nodename}:{os.getpid()}"}
    with _LOCK:
        work = tempfile.mkdtemp(prefix=f"job-{payload['key'][:12]}-", dir=payload.get("work_root"))
        old = os.getcwd()
        try:
            os.chdir(work)
            from dtoc.optimize.request import OptimizeRequest, run_request

            manifest = run_request(OptimizeRequest(**payload["request"]))
            if manifest.get("interrupted"):
                out.update(status="interrupted", error="interrupted", exit_code=130)
            else:
                files = {
                    p.name: p.read_bytes()
                    for p in sorted(Path(".").iterdir())
                    if p.is_file() and not p.name.startswith(".") and not p.name.endswith(".ckpt.npz")
                }
                out.update(status="ok", files=files, exit_code=0)
        except KeyboardInterrupt:
            out.update(status="interrupted", error="interrupted", exit_code=130)
        except Exception as e:  # noqa: BLE001 - a job's failure is a line in the report, never a traceback
            msg, code = describe(e)
            out.update(status="failed", error=msg, exit_code=code)
        finally:
            os.chdir(old)
            shutil.rmtree(work, ignore_errors=True)
    out["seconds"] = time.perf_counter() - t0
    out["peak_rss_mb"] = _peak_rss_mb()
    return out


def _peak_rss_mb() -> float | None:
    """Peak resident memory of this worker process so far, MB (None where the platform does not say)."""
    try:
        import resource
    except ImportError:
        return None
    kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return kb / 1024.0 if os.uname().sysname != "Darwin" else kb / 2**20
