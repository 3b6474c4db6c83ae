"""The export of a long output against its length: time and peak memory of writing and checking the ``.seq``.

Run: ``python -m bench.export_scale [--partitions 2 8 32 96]``.  The base: bench.protocols' 3D FLASH at 1 mm
(``gre3d_1mm``, 960 blocks and 125,000 raster steps per partition, 96 partitions = the 2-minute protocol), read as
dtoc reads it (``load_sequence``); every free raster edge is moved by a smooth perturbation of 0.02 mT/m (far
within the limits: its slew is < 0.1 T/m/s; its period, sqrt(2) ms, shares no multiple with the TR, so no two TRs
write the same shape), so every block with a free edge is rewritten as an arbitrary waveform,
as an optimized output is.  Then the write path of ``dtoc optimize``'s export stage: ``seq_bytes_of(verify=False)``
(the text), then the read-back of the written text and the check ``write_checked`` makes of it, on one reading of
each piece (``verify_and_check``: in pieces above ``VERIFY_PIECE_RASTER`` raster steps); ``--separate``: the
read-back (``verify_written``) and the check (``check_file_pieces``; ``--whole-check``: ``check_file`` on the whole
text) each on its own reading, as before.  Each step timed (wall and CPU) with its peak resident
memory (``VmHWM`` reset before each step through ``/proc/self/clear_refs``).  Each length runs in its own process
(the peaks do not mix); one JSON line per length on stdout, then a table.  Nothing is written to docs/.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _rss_mb(field: str) -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(field + ":"):
                return int(line.split()[1]) / 1024
    return float("nan")


def _reset_peak() -> None:
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")


def _step(fn):
    """(result, {wall_s, cpu_s, rss_start_mb, peak_mb, rss_after_mb}) of ``fn()``."""
    _reset_peak()
    r0, t, c = _rss_mb("VmRSS"), time.perf_counter(), time.process_time()
    out = fn()
    stats = {"wall_s": time.perf_counter() - t, "cpu_s": time.process_time() - c, "rss_start_mb": r0}
    return out, {**stats, "peak_mb": _rss_mb("VmHWM"), "rss_after_mb": _rss_mb("VmRSS")}


def one(partitions: int, whole_check: bool = False, separate: bool = False) -> dict:
    """One length, in this process."""
    import tempfile

    import numpy as np

    sys.path.insert(0, str(REPO))
    from bench.protocols import gre3d_1mm
    from dtoc.seq import check as C
    from dtoc.seq.ir import edges_to_fine
    from dtoc.seq.load import load_sequence
    from dtoc.seq.system import SystemSpec
    from dtoc.seq.write import seq_bytes_of, verify_and_check, verify_spans, verify_written, writable_version

    row: dict = {"partitions": partitions}
    with tempfile.TemporaryDirectory() as td:
        p = Path(td) / "base.seq"
        p.write_bytes(gre3d_1mm(partitions=partitions))
        row["base_mb"] = p.stat().st_size / 1e6
        ir = load_sequence(p)
    row["rss_loaded_mb"] = _rss_mb("VmRSS")
    edges = ir.edge_grad_mT_per_m
    free = ir.free_mask[:, ::2]
    n = edges.shape[1]
    t = np.arange(n) * ir.raster_s
    e = edges + np.where(free, 0.02 * np.sin(2 * np.pi * t / (1e-3 * np.sqrt(2)))[None, :], 0.0)
    out = ir.with_grad(edges_to_fine(e))
    del e, t, edges
    row.update(
        blocks=len(ir.block_edges_s) - 1, raster_steps=n - 1, duration_s=float(ir.duration_s),
        free_edges=int(free.sum()), rss_before_export_mb=_rss_mb("VmRSS"),
    )  # fmt: skip
    v = writable_version(out)
    data, row["write"] = _step(lambda: seq_bytes_of(out, version=v, verify=False))
    row["out_mb"] = len(data) / 1e6
    sysspec = SystemSpec(max_grad_mT_per_m=80.0, max_slew_T_per_m_per_s=200.0, grad_raster_s=out.raster_s)
    if not (separate or whole_check):  # the export's: one reading of each piece for the read-back and the check
        with tempfile.TemporaryDirectory() as td:
            p = Path(td) / "out.seq"
            p.write_bytes(data)
            data = b""  # (write_checked holds no copy of the text while it checks the file)
            res, row["verify_check"] = _step(lambda: verify_and_check(out, p, v, sysspec, None))
        row.update(check_whole=False, check_violations=len(res.violations))
        return row
    _, row["verify"] = _step(lambda: verify_written(out, data, v))
    with tempfile.TemporaryDirectory() as td:  # the check reads the file, as write_checked's does
        p = Path(td) / "out.seq"
        p.write_bytes(data)
        data = b""  # (write_checked holds no copy of the text while it checks the file)
        if whole_check:
            res, row["check"] = _step(lambda: C.check_file(p, sysspec, None, conventions=None))
        else:
            res, row["check"] = _step(
                lambda: C.check_file_pieces(p, verify_spans(out), sysspec, None, conventions=None)
            )
    row.update(check_whole=whole_check, check_violations=len(res.violations))
    return row


def _over(step: dict) -> float:
    """A step's peak resident memory over its start, MB."""
    return step["peak_mb"] - step["rss_start_mb"]


def _read_back(r: dict) -> dict:
    """The read-back and check of a row: the shared step, or the separate ones summed (times) and maxed (peaks)."""
    if "verify_check" in r:
        return r["verify_check"]
    a, b = r["verify"], r["check"]
    return {
        "wall_s": a["wall_s"] + b["wall_s"],
        "cpu_s": a["cpu_s"] + b["cpu_s"],
        "rss_start_mb": a["rss_start_mb"],
        "peak_mb": max(a["peak_mb"], b["peak_mb"]),
    }


def render(rows: list[dict]) -> str:
    head = (
        "| partitions | blocks | raster steps | duration (s) | output (MB) | RSS loaded (MB) | write: wall / CPU (s) | "
        "write: peak RSS over its start (MB) | read-back and check: wall / CPU (s) | read-back and check: peak RSS "
        "over its start (MB) | export: CPU (s) | export's peak RSS (MB) |\n"
        "|---|---|---|---|---|---|---|---|---|---|---|---|\n"
    )
    lines = [
        f"| {r['partitions']} | {r['blocks']} | {r['raster_steps']} | {r['duration_s']:.1f} | {r['out_mb']:.0f} | "
        f"{r['rss_before_export_mb']:.0f} | {r['write']['wall_s']:.1f} / {r['write']['cpu_s']:.1f} | "
        f"{_over(r['write']):.0f} | {_read_back(r)['wall_s']:.1f} / {_read_back(r)['cpu_s']:.1f} | "
        f"{_over(_read_back(r)):.0f} | {r['write']['cpu_s'] + _read_back(r)['cpu_s']:.1f} | "
        f"{max(r['write']['peak_mb'], _read_back(r)['peak_mb']):.0f} |"
        for r in rows
    ]
    out = head + "\n".join(lines) + "\n"
    a, b = rows[0], rows[-1]
    steps = b["raster_steps"] - a["raster_steps"]
    if steps > 0:  # (two lengths or more)
        per = [
            f"{k}: {(_over(f(b)) - _over(f(a))) * 2**20 / steps:.0f}"
            for k, f in (("write", lambda r: r["write"]), ("read-back and check", _read_back))
        ]
        out += (
            f"\nPeak RSS over the step's start, per raster step ({a['partitions']} -> {b['partitions']} partitions), bytes: "
            + ", ".join(per)
            + f"; the loaded IR: {(b['rss_before_export_mb'] - a['rss_before_export_mb']) * 2**20 / steps:.0f}.\n"
        )
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--partitions", type=int, nargs="+", default=[2, 8, 32, 96])
    ap.add_argument("--whole-check", action="store_true", help="check the whole text (check_file), as before")
    ap.add_argument("--separate", action="store_true", help="the read-back and the check each on its own reading")
    ap.add_argument("--one", type=int, help=argparse.SUPPRESS)  # internal: one length in this process
    a = ap.parse_args(argv)
    if a.one is not None:
        print(json.dumps(one(a.one, a.whole_check, a.separate)), flush=True)
        return
    rows = []
    for p in a.partitions:
        r = subprocess.run(
            [
                sys.executable,
                "-m",
                "bench.export_scale",
                "--one",
                str(p),
                *(["--whole-check"] if a.whole_check else []),
                *(["--separate"] if a.separate else []),
            ],
            cwd=REPO,
            capture_output=True,
        )
        if r.returncode:
            sys.stderr.write(r.stderr.decode(errors="replace")[-3000:])
            print(json.dumps({"partitions": p, "rc": r.returncode}), flush=True)
            continue
        rows.append(json.loads(r.stdout.decode().strip().splitlines()[-1]))
        print(json.dumps(rows[-1]), flush=True)
    print(render(rows))


if __name__ == "__main__":
    main()
