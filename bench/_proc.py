"""One benchmark step as its own process: wall time, CPU and peak resident memory from ``wait4``, a time
budget and an optional resident-memory cap (shared by bench.public_corpus and bench.protocols)."""

from __future__ import annotations

import os
import signal
import subprocess
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _group_rss_mb(pgid: int) -> float:
    """Resident memory of every process of session/group ``pgid`` (Linux /proc), MB."""
    total = 0
    for d in os.listdir("/proc"):
        if not d.isdigit():
            continue
        try:
            with open(f"/proc/{d}/stat") as f:
                fields = f.read().rsplit(")", 1)[1].split()
            if int(fields[2]) == pgid:  # (state ppid pgrp ...): pgrp
                total += int(fields[21]) * os.sysconf("SC_PAGE_SIZE")  # rss in pages
        except (OSError, ValueError, IndexError):
            continue
    return total / 2**20


def run_step(argv: list[str], budget_s: float, env: dict | None = None, mem_cap_mb: float | None = None) -> dict:
    """Run one subprocess within ``budget_s`` and, where given, ``mem_cap_mb`` of resident memory (the machine is
    shared: a step over it is killed before the kernel's OOM killer picks a neighbour; None: no cap); ``env``
    None: this process's environment.  Returns {rc, out, err, wall_s, cpu_s, peak_mb, timed_out, mem_capped}."""
    t0 = time.perf_counter()
    with tempfile.TemporaryFile() as fo, tempfile.TemporaryFile() as fe:
        p = subprocess.Popen(argv, stdout=fo, stderr=fe, env=env, cwd=REPO, start_new_session=True)
        timed_out, capped, ru, status, n = False, False, None, 0, 0
        while True:
            pid, status, ru = os.wait4(p.pid, os.WNOHANG)
            if pid:
                break
            over = time.perf_counter() - t0 > budget_s
            n += 1
            if not over and mem_cap_mb and n % 5 == 0 and _group_rss_mb(p.pid) > mem_cap_mb:
                capped = over = True
            if over:
                os.killpg(p.pid, signal.SIGKILL)
                _, status, ru = os.wait4(p.pid, 0)
                timed_out = not capped
                break
            time.sleep(0.1)
        p.returncode = os.waitstatus_to_exitcode(status)
        fo.seek(0)
        fe.seek(0)
        out, err = fo.read().decode(errors="replace"), fe.read().decode(errors="replace")
    return {
        "rc": p.returncode,
        "out": out,
        "err": err,
        "wall_s": time.perf_counter() - t0,
        "cpu_s": ru.ru_utime + ru.ru_stime if ru is not None else None,
        "peak_mb": ru.ru_maxrss / 1024.0 if ru is not None else None,
        "timed_out": timed_out,
        "mem_capped": capped,
    }
