"""The CLI keeps freed memory for reuse (dtoc.util.allocator): a large block, once freed, stays in the process
for the next allocation instead of going back to the OS (to be page-faulted in again);
DTOC_MALLOC_TUNING=0 leaves glibc's defaults, which unmap it at once."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

PROBE = """
import numpy as np
from dtoc.util.allocator import keep_freed_memory

def rss_mb():
    for line in open("/proc/self/status"):
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024

applied = keep_freed_memory()
r0 = rss_mb()
a = np.ones(2**24)  # 128 MB, touched
r1 = rss_mb()
del a
print(int(applied), round(r1 - r0), round(rss_mb() - r0))
"""


def _run(env_value: str | None) -> tuple[int, int, int]:
    env = dict(os.environ)
    env.pop("DTOC_MALLOC_TUNING", None)
    if env_value is not None:
        env["DTOC_MALLOC_TUNING"] = env_value
    out = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, env=env, check=True)
    applied, grown, kept = (int(v) for v in out.stdout.split())
    return applied, grown, kept


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc mallopt, /proc")
def test_freed_blocks_stay_for_reuse_and_the_switch_turns_it_off():
    applied, grown, kept = _run(None)
    if not applied:
        pytest.skip("C library without mallopt (not glibc)")
    assert grown > 120, grown  # the 128 MB block was resident
    assert kept > 120, kept  # ... and stays after the free, for the next allocation
    for off in ("0", "off", " False "):
        off_applied, off_grown, off_kept = _run(off)
        assert off_applied == 0 and off_grown > 120, off
        assert off_kept < 10, (off, off_kept)  # glibc's default: a block this size is unmapped at free
