"""Write one benchmark's results into its own section of docs/benchmarks.md.

Each benchmark owns the text between ``<!-- bench:NAME -->`` and ``<!-- /bench:NAME -->``; running it
replaces only that section (adding it at the end the first time), stamped with date and machine.
"""

from __future__ import annotations

import datetime as _dt
import os
import platform
import re
from pathlib import Path

DOC = Path(__file__).resolve().parents[1] / "docs" / "benchmarks.md"
HEADER = "# Benchmarks\n\nEach section is written by the command named in it; numbers are from one run on the machine stated.\n"


def machine_line() -> str:
    """Date, CPU, core count, Python and torch versions, as one markdown line."""
    import torch

    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return (
        f"Run {_dt.date.today().isoformat()} on {cpu}, {os.cpu_count()} cores, "
        f"Python {platform.python_version()}, torch {torch.__version__} (threads {torch.get_num_threads()})."
    )


def write_section(name: str, title: str, body_md: str, command: str, doc: Path = DOC) -> Path:
    """Replace (or append) the section ``name`` of ``doc`` (default docs/benchmarks.md)."""
    text = doc.read_text() if doc.exists() else HEADER
    block = (
        f"<!-- bench:{name} -->\n## {title}\n\nCommand: `{command}`. {machine_line()}\n\n{body_md.strip()}\n"
        f"<!-- /bench:{name} -->\n"
    )
    pat = re.compile(rf"<!-- bench:{re.escape(name)} -->.*?<!-- /bench:{re.escape(name)} -->\n", re.S)
    text = pat.sub(lambda _m: block, text) if pat.search(text) else text.rstrip("\n") + "\n\n" + block
    tmp = doc.with_suffix(".md.tmp")
    tmp.write_text(text)
    os.replace(tmp, doc)
    return doc
