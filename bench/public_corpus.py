"""Public `.seq` files written by other people's software, through every command: the public-corpus table.

Run: ``python -m bench.public_corpus DIR [DIR ...] --girf H.npz [--budget-optimize 300] [--budget 120]``
-> the section "Public corpus" of docs/foreign.md (between its markers; the rest of the page is
``bench.foreign``'s and hand-written notes; ``--merge``: only the rerun files' rows are replaced, the rest of the
table kept, and the section's counts, classes, commits and dates rendered again over the merged table; ``--rows
F`` then ``--render F --merge`` merges rows run elsewhere, e.g. in parallel).  DIR holds ``.seq`` files as downloaded from public repositories (KomaMRI examples,
pypulseq and Pulseq test/demo outputs, MRzero, JEMRIS, a CEST library, field-camera groups); nothing of it is
committed.  An optional ``INDEX.tsv`` in DIR (columns path, source_repo, commit, ...) names each file's origin.

Each file, each step in its own subprocess with a wall-clock budget and a resident-memory cap (a step over
either is killed and its row says "timed out after N s" or "stopped at the bench's memory cap"; peak memory
is the step's own maximum resident set, from ``wait4``):

1. read: dtoc's reader (``dtoc.seq.load``) -> kind, ADC samples, duration, peak gradient and slew, the reader's
   notes (RF use taken or detected); its one-line refusal is the row's result when it cannot read the file;
2. ``dtoc check`` at the limits below;
3. ``dtoc predict --girf`` -> the realized k error (max over axes, dk);
4. ``dtoc simulate --girf`` -> NRMSE and k error (where the file has an image grid);
5. ``dtoc optimize --girf --gmax --smax`` -> before -> after (k in dk, NRMSE), or its one-line refusal.

Limits: the file's own (``MaxGrad_mT_per_m`` / ``MaxSlew_T_per_m_per_s`` definitions) where it records them,
else **assumed** 40 mT/m and 170 T/m/s (a common whole-body gradient) raised to the file's own peak + 2 % where
that is higher (the file was written for such a system); the table says which.  A figure that cannot mean
anything (no image grid, no ADC) is shown as its reason, never as a number.
"""

from __future__ import annotations

import argparse
import csv
import datetime as dt
import json
import os
import platform
import re
import subprocess
import sys
import tempfile
from pathlib import Path

from bench._proc import run_step

REPO = Path(__file__).resolve().parents[1]
DOC = REPO / "docs" / "foreign.md"
BEGIN, END = "<!-- public-corpus:begin -->", "<!-- public-corpus:end -->"
ASSUMED_GMAX, ASSUMED_SMAX = 40.0, 170.0
#: resident memory at which the bench stops a step (the machine is shared; --mem-cap-gb sets it), MB
MEM_CAP_MB = 6 * 1024.0


def _probe(path: str) -> None:
    """Step 1 (run in a subprocess): read the file as every command does; one JSON line on stdout."""
    import numpy as np

    from dtoc.errors import DtocError
    from dtoc.optimize.limits import waveform_extremes
    from dtoc.seq.check import system_from_definitions
    from dtoc.seq.load import load_sequence

    try:
        ir = load_sequence(Path(path))
    except DtocError as e:
        print(json.dumps({"ok": False, "error": str(e).splitlines()[0] if str(e) else type(e).__name__}))
        return
    ext = waveform_extremes(ir.grad_mT_per_m, ir.dt_fine_s)
    defs = {k: (str(v).split()[0] if str(v).split() else str(v)) for k, v in (ir.definitions or {}).items()}
    try:
        own = system_from_definitions(defs)
    except DtocError:
        own = None
    print(
        json.dumps(
            {
                "ok": True,
                "kind": ir.kind,
                "n_blocks": int(len(ir.block_edges_s) - 1),
                "n_adc_samples": ir.n_adc_samples,
                "n_rf": len(ir.rf),
                "rf_uses": sorted({r.use for r in ir.rf}),
                "duration_s": ir.duration_s,
                "gmax_mT_per_m": float(max(ext["gmax_mT_per_m"])),
                "smax_T_per_m_per_s": float(max(ext["smax_T_per_m_per_s"])),
                "fov_m": None if ir.fov_m is None else [float(x) for x in ir.fov_m],
                "matrix": None if ir.matrix is None else [int(x) for x in ir.matrix],
                "has_gradient": bool(np.any(ir.grad_mT_per_m)),
                "own_limits": None
                if own is None
                else [float(own.max_grad_mT_per_m), float(own.max_slew_T_per_m_per_s)],
                "notes": list(ir.meta.get("notes", [])),
            }
        )
    )


def _stopped(r: dict, budget_s: float) -> str | None:
    """The row's words for a step the bench stopped (over its time budget or its memory cap), else None."""
    if r.get("mem_capped"):
        return f"stopped at the bench's memory cap ({MEM_CAP_MB / 1024:.0f} GB resident) after {r['wall_s']:.0f} s"
    if r.get("timed_out"):
        return f"timed out after {budget_s:.0f} s"
    return None


def _last_line(text: str, seq: Path | None = None) -> str:
    if seq is not None:  # messages name the file by its name only (no machine paths in the table)
        text = text.replace(str(seq), seq.name).replace(str(seq.parent) + os.sep, "")
    lines = [ln.strip() for ln in text.strip().splitlines() if ln.strip()]
    errs = [ln for ln in lines if ln.startswith("dtoc: error") or "Error" in ln[:40]]
    s = (errs or lines or ["(no message)"])[-1]
    return s.removeprefix("dtoc: error: ")


def _failure(rc: int) -> str:
    """The row's word for a command's exit code (docs/cli.md, "Exit codes")."""
    return {2: "refused: ", 3: "internal error: "}.get(rc, f"exit {rc}: ")


def _json_of(text: str) -> dict | None:
    try:
        return json.loads(text)
    except (json.JSONDecodeError, ValueError):
        return None


def _dtoc(*args) -> list[str]:
    return [sys.executable, "-m", "dtoc", *[str(a) for a in args]]


def header_of(path: Path) -> tuple[str, str]:
    """(writer comment line, 'major.minor.revision' or '?') from the file's text (no parsing of the rest)."""
    writer, ver = "?", {}
    in_ver = False
    with open(path, "rb") as f:
        for i, raw in enumerate(f):
            if i > 200:
                break
            line = raw.decode("latin-1").strip()
            if writer == "?" and line.startswith("#") and re.search(r"creat|generat|written", line, re.I):
                writer = line.lstrip("# ").strip()
            if line.startswith("["):
                in_ver = line.upper() == "[VERSION]"
                continue
            if in_ver and line.split()[:1] and line.split()[0] in ("major", "minor", "revision"):
                ver[line.split()[0]] = line.split()[1] if len(line.split()) > 1 else "?"
    v = ".".join(ver.get(k, "?") for k in ("major", "minor", "revision")) if ver else "?"
    return writer, v


def _writer_short(w: str) -> str:
    for pat, name in (
        (r"pypulseq", "pypulseq"),
        (r"matlab", "Pulseq MATLAB"),
        (r"jemris", "JEMRIS"),
        (r"gammastar", "gammaSTAR"),
        (r"koma", "KomaMRI"),
        (r"dtoc", "dtoc"),
    ):
        if re.search(pat, w, re.I):
            return name
    return w[:30] or "?"


def _index(dirs: list[Path]) -> dict[str, dict]:
    out = {}
    for d in dirs:
        p = d / "INDEX.tsv"
        if p.exists():
            with open(p, newline="") as f:
                for r in csv.DictReader(f, delimiter="\t"):
                    out[str((d / r["path"]).resolve())] = r
    return out


def _limits(probe: dict | None) -> tuple[float, float, str]:
    if probe and probe.get("own_limits"):
        g, s = probe["own_limits"]
        return g, s, "file"
    g, s = ASSUMED_GMAX, ASSUMED_SMAX
    how = "assumed"
    if probe and probe.get("ok"):
        if probe["gmax_mT_per_m"] > g:
            g, how = round(probe["gmax_mT_per_m"] * 1.02, 2), "assumed, raised to the file's peak"
        if probe["smax_T_per_m_per_s"] > s:
            s, how = round(probe["smax_T_per_m_per_s"] * 1.02, 1), "assumed, raised to the file's peak"
    return g, s, how


def run_file(seq: Path, girf: Path, budgets: dict, work: Path, env: dict) -> dict:
    row: dict = {"file": str(seq)}
    row["writer_line"], row["version"] = header_of(seq)
    row["size_kb"] = seq.stat().st_size / 1024.0
    peak = 0.0
    total = 0.0

    def step(name, argv, budget):
        nonlocal peak, total
        r = run_step(argv, budget, env, MEM_CAP_MB)
        peak = max(peak, r["peak_mb"] or 0.0)
        total += r["wall_s"]
        row[f"{name}_s"] = r["wall_s"]
        row[f"{name}_cpu_s"] = r.get("cpu_s")  # (the rows JSON only: wall clock on a shared machine says little)
        return r

    r = step("read", [sys.executable, "-m", "bench.public_corpus", "--probe", str(seq)], budgets["read"])
    probe = _json_of(r["out"].strip().splitlines()[-1]) if r["out"].strip() else None
    if _stopped(r, budgets["read"]):
        row["read"] = _stopped(r, budgets["read"])
    elif probe is None:
        row["read"] = "internal error: " + _last_line(r["err"], seq)
    elif not probe["ok"]:
        row["read"] = probe["error"].replace(str(seq), seq.name)
    else:
        row["read"] = "ok"
        row["probe"] = probe
    g, s, how = _limits(probe)
    row["limits"] = {"gmax": g, "smax": s, "source": how}
    # check (reads the text itself: runs whatever the reader said)
    r = step("check", _dtoc("check", seq, "--gmax", g, "--smax", s, "--json", "-"), budgets["other"])
    res = _json_of(r["out"])
    if _stopped(r, budgets["other"]):
        row["check"] = _stopped(r, budgets["other"])
    elif res is not None and "violations" in res:
        rules = sorted({v.get("rule", "?") for v in res["violations"]})
        row["check"] = "ok" if not res["violations"] else f"{len(res['violations'])} violations: " + ", ".join(rules)
    else:
        row["check"] = _failure(r["rc"]) + _last_line(r["err"], seq)
    if row["read"] != "ok":
        stopped = "timed out" in row["read"] or "memory cap" in row["read"]
        row["result"] = ("refused: " if not stopped else "") + row["read"]
        row["time_s"], row["peak_mb"] = total, peak
        return row
    # predict
    r = step("predict", _dtoc("predict", seq, "--girf", girf, "--json", "-"), budgets["other"])
    res = _json_of(r["out"])
    if _stopped(r, budgets["other"]):
        row["predict"] = _stopped(r, budgets["other"])
    elif res is not None:
        kd = [v.get("max_dk") for v in (res.get("k_error") or {}).values() if v.get("max_dk") is not None]
        row["predict"] = "ok"
        row["predict_k_dk"] = max(kd) if kd else None
    else:
        row["predict"] = _failure(r["rc"]) + _last_line(r["err"], seq)
    # simulate
    r = step("simulate", _dtoc("simulate", seq, "--girf", girf, "--json", "-", "-q"), budgets["other"])
    res = _json_of(r["out"])
    if _stopped(r, budgets["other"]):
        row["simulate"] = _stopped(r, budgets["other"])
    elif res is not None:
        row["simulate"] = "ok"
        row["simulate_nrmse_pct"] = res.get("nrmse_percent")
        row["simulate_k_dk"] = res.get("kspace_max_error_dk")
    else:
        row["simulate"] = _failure(r["rc"]) + _last_line(r["err"], seq)
    # optimize
    out, man = work / (seq.stem + "_opt.seq"), work / (seq.stem + "_opt.json")
    argv = _dtoc("optimize", seq, "--girf", girf, "--gmax", g, "--smax", s, "-o", out, "--json", man, "-q", "--force")
    r = step("optimize", argv, budgets["optimize"])
    if _stopped(r, budgets["optimize"]):
        est = [ln for ln in r["err"].splitlines() if "estimat" in ln.lower()]
        row["result"] = _stopped(r, budgets["optimize"]) + (f" ({est[-1].strip()})" if est else "")
    elif r["rc"] in (0, 1) and man.exists():  # 1: written, but the output fails a check (docs/cli.md)
        m = json.loads(man.read_text())
        failed = (m.get("output") or {}).get("check_failed")
        row["result"] = "optimized" + (f"; output check FAILED: {failed}" if r["rc"] == 1 and failed else "")
        row["k_before_dk"] = m["before"].get("kspace_max_error_dk")
        row["k_after_dk"] = m["after"].get("kspace_max_error_dk")
        row["nrmse_before_pct"] = m["before"].get("nrmse_percent")
        row["nrmse_after_pct"] = m["after"].get("nrmse_percent")
        row["image_term"] = m["sequence"].get("image_term")
        row["image_reason"] = m["before"].get("image_reason")  # image figures not computed: why
        row["dk_source"] = m["sequence"].get("dk_source")
        row["output_check_ok"] = (m.get("output") or {}).get("check_ok")
    else:
        row["result"] = _failure(r["rc"]) + _last_line(r["err"], seq)
    for p in (out, man, out.with_suffix(".traj.npz")):
        p.unlink(missing_ok=True)
    row["time_s"], row["peak_mb"] = total, peak
    return row


def _f(v, nd=3) -> str:
    return "-" if v is None else f"{v:.{nd}g}"


def _cell(s: str) -> str:
    return s.replace("|", "/").replace("\n", " ")


def clean_result(s: str) -> str:
    """A result for the table: whole (never cut: a refusal's way out is at its end), without the machine's
    available memory (it changes between runs; the row's JSON keeps the message as printed)."""
    s = re.sub(r"; [\d.]+ [KMGT]iB available on this machine", "", s)
    return re.sub(
        r"more than (\d+ ?%) of the [\d.]+ [KMGT]iB available here", r"more than \1 of the memory available", s
    )


def _rf_use(row: dict) -> str:
    p = row.get("probe")
    if not p:
        return "-"
    uses = "/".join(p["rf_uses"]) or "no RF"
    notes = " ".join(p["notes"])
    if re.search(r"states no RF use: detected", notes):
        return uses + " (detected)"
    if re.search(r"use 'undefined'", notes):
        return uses + " (undefined: taken as excitation)"
    return uses


def _time_cell(r: dict) -> str:
    """All steps' wall time, and the optimize step's own wall and CPU seconds where it ran."""
    t = f"{r['time_s']:.0f}"
    if r.get("optimize_s") is not None:
        cpu = r.get("optimize_cpu_s")
        t += f" ({r['optimize_s']:.0f}" + ("" if cpu is None else f" / {cpu:.0f} CPU") + ")"
    return t


def row_line(r: dict, commit: str) -> str:
    """The table's line of one file's row."""
    name = Path(r["file"]).name
    for k in ("check", "predict", "simulate", "result"):  # the file column names the file
        if isinstance(r.get(k), str):
            r[k] = r[k].replace(f": {name}: ", ": ", 1).replace(f"{name}: ", "", 1)
    if r.get("check") == r["result"]:
        r["check"] = "(as result)"
    src = Path(r["file"]).parent.name
    p = r.get("probe") or {}
    lim = r["limits"]
    lim_s = f"{lim['gmax']:g} / {lim['smax']:g} ({lim['source']})"
    pred = _f(r.get("predict_k_dk")) if r.get("predict") == "ok" else _cell(r.get("predict", "-")).split("; ")[0]
    sim = _f(r.get("simulate_nrmse_pct")) if r.get("simulate") == "ok" else _cell(r.get("simulate", "-")).split("; ")[0]
    if r["result"].startswith("optimized"):
        kba = f"{_f(r.get('k_before_dk'))} -> {_f(r.get('k_after_dk'))}"
        nba = (
            f"{_f(r.get('nrmse_before_pct'))} -> {_f(r.get('nrmse_after_pct'))}"
            if r.get("nrmse_before_pct") is not None
            else f"'-': {_cell(r['image_reason'])}"
            if r.get("image_reason")
            else "k-space only (no image term)"
        )
    else:
        kba = nba = ""
    return (
        f"| {src} | {Path(r['file']).name} | {_cell(_writer_short(r['writer_line']))} | {r['version']} | "
        f"{p.get('kind') or '-'} | {r['size_kb']:.0f} | {lim_s} | {_cell(r.get('check', '-'))[:140]} | {pred} | {sim} | "
        f"{clean_result(_cell(r['result']))} | {kba} | {nba} | {_time_cell(r)} | {r['peak_mb']:.0f} | {_rf_use(r)} | "
        f"{r.get('commit') or commit} |"
    )


#: the table's columns (a rendered line has these cells, in this order)
COLUMNS = (
    "source", "file", "writer", "version", "kind", "size (kB)", "limits (mT/m, T/m/s)", "check", "predict k (dk)",
    "simulate NRMSE (%)", "result", "k before -> after (dk)", "NRMSE before -> after (%)",
    "time (s): all steps (optimize: wall / CPU)", "peak (MB)", "RF use", "commit",
)  # fmt: skip
C_FILE, C_WRITER, C_CHECK, C_PRED, C_SIM, C_RESULT, C_COMMIT = 1, 2, 7, 8, 9, 10, 16

#: the outcome classes of the result column, in the order the section lists them: (name, test on the result cell)
CLASSES = (
    ("optimized", lambda x: x.startswith("optimized") and "FAILED" not in x),
    ("optimized, but the output fails a check", lambda x: x.startswith("optimized") and "FAILED" in x),
    ("internal error", lambda x: "internal error" in x),  # (a reader's internal error reads "refused: internal ...")
    ("refused by the run's cost estimate (memory), before any work", lambda x: "optimize: estimate (" in x),
    ("refused: the base fails a timing rule its output would inherit", lambda x: "the base itself fails" in x),
    (
        "refused: nothing to optimize (no ADC, or every gradient sample held)",
        lambda x: "nothing to optimize" in x,
    ),
    ("refused: other (the reader, the format, the signature, the limits)", lambda x: x.startswith("refused")),
    ("timed out (the bench's budget)", lambda x: x.startswith("timed out")),
    ("stopped at the bench's memory cap", lambda x: x.startswith("stopped at the bench's memory cap")),
    ("killed by a signal", lambda x: bool(re.match(r"exit -\d", x))),
    ("other", lambda x: True),
)


def outcome(result: str) -> str:
    """The class (:data:`CLASSES`) of a result cell."""
    return next(name for name, test in CLASSES if test(result))


def _cpu_name() -> str:
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next((ln.split(":", 1)[1].strip() for ln in f if ln.startswith("model name")), cpu)
    except OSError:
        pass
    return cpu


def _plural(n: int, word: str) -> str:
    return f"{n} {word}{'' if n == 1 else 's'}"


def section(cells: list[list[str]], meta: dict) -> str:
    """The marked section of docs/foreign.md from the table's cells (one list per file, :data:`COLUMNS`): what the
    table is, how to reproduce it, the counts and the classes (recounted from the cells), the table, the sources.
    ``meta``: girf, budgets, mem_cap_gb, dates (sorted 'YYYY-MM-DD'), sources (repositories)."""
    res = [c[C_RESULT] for c in cells]
    by_class: dict[str, list[int]] = {}
    for i, x in enumerate(res):
        by_class.setdefault(outcome(x), []).append(i)
    n = {name: len(by_class.get(name, [])) for name, _ in CLASSES}
    n_ref = sum(v for k, v in n.items() if k.startswith("refused"))
    n_stop = sum(
        n[k] for k in ("timed out (the bench's budget)", "stopped at the bench's memory cap", "killed by a signal")
    )
    n_int = sum(any("internal error" in c[j] for j in (C_CHECK, C_PRED, C_SIM, C_RESULT)) for c in cells)
    writers = sorted({_writer_short(c[C_WRITER]) for c in cells})
    by_commit: dict[str, int] = {}
    for c in cells:
        by_commit[c[C_COMMIT]] = by_commit.get(c[C_COMMIT], 0) + 1
    commits = ", ".join(f"{k} ({_plural(v, 'row')})" for k, v in sorted(by_commit.items(), key=lambda x: (-x[1], x[0])))
    b = meta["budgets"]
    dates = meta.get("dates") or []
    when = "-" if not dates else (dates[0] if dates[0] == dates[-1] else f"{dates[0]} to {dates[-1]}")
    head = [
        BEGIN,
        "## Public corpus: files other people's software wrote",
        "",
        "Every `.seq` file of a folder of public example and test files (KomaMRI, JEMRIS, Pulseq MATLAB, pypulseq, "
        "MRzero, gammaSTAR, a CEST library, a field-camera vendor: the *source* column names the folder, the "
        "repositories are listed below the table) goes through what a new user would run: dtoc's reader, `dtoc "
        "check`, `dtoc predict`, `dtoc simulate` and `dtoc optimize`, each step in its own process with a wall-clock "
        f"budget (read, check, predict, simulate {b['other']:.0f} s each; optimize {b['optimize']:.0f} s) and a "
        f"resident-memory cap ({meta['mem_cap_gb']:g} GB; the machine is shared: a step over either is stopped and "
        "the row says so; rows run with other budgets: the change log below the table). Every row is either "
        "optimized, refused with one line (the line is the *result*), or "
        "stopped by the bench; an internal error (exit 3) is a bug. The files are not committed.",
        "",
        "Reproduce (the folder as downloaded, with an optional `INDEX.tsv` naming each file's repository and commit; "
        "the GIRF: the KCL 7 T Terra 2024 measurement of the shared data, imported as `bench.foreign` does):",
        "",
        "    nice python -m bench.public_corpus DIR --girf KCL2024.npz [--only NAME ...] --rows rows.jsonl",
        "    python -m bench.public_corpus --render rows.jsonl --merge   # into this table",
        "",
        f"Rows ran {when} (UTC) on {_cpu_name()}, {os.cpu_count()} cores shared with other engineers' jobs "
        f"(times are wall clock under that load; the rows' JSON holds each step's CPU seconds too), Python "
        f"{platform.python_version()}; commits {commits}. GIRF: {meta['girf']}.",
        "",
        f"**{len(cells)} files from {len(writers)} writers ({', '.join(writers)}): {n['optimized']} optimized, "
        f"{n_ref} refused with one line, {n_stop} stopped by the bench (time or memory), "
        f"{n['internal error']} internal errors in the result** (the reader's or optimize's; "
        f"{_plural(n_int, 'file')} with an internal error in any step). By class:",
        "",
    ]
    for name, _ in CLASSES:
        idx = by_class.get(name, [])
        if idx:
            head.append(f"- {name}: {len(idx)} ({', '.join(f'{cells[i][0]}/{cells[i][C_FILE]}' for i in idx)})")
    head += [
        "",
        "Columns: *version*: the file's `[VERSION]`; *kind*: dtoc's inference (gre, epi, or '-' when neither); "
        "*limits*: the file's own definitions, or assumed (40 mT/m, 170 T/m/s, raised to the file's own peak + 2 % "
        "where higher); *check*: `dtoc check` at those limits (no scanner profile: the vendor conventions are not "
        "checked); *predict k*: the realized k error of `dtoc predict` (max over axes, dk = 2 pi / FOV; '-' where the "
        "FOV is unknown); *simulate NRMSE*: `dtoc simulate`'s, or its one-line refusal; *result*: `dtoc optimize`, "
        "its refusal whole, with k (max, dk) and NRMSE (built-in phantom; 'k-space only' without an image term: no "
        "image grid, or a long file solved window by window) before -> after from its manifest; *time*: all steps "
        "together, and the optimize step's own wall and CPU seconds; *peak*: the largest resident set of any step; "
        "*RF use*: the uses dtoc took ('detected': the format states none, detected from each pulse as Pulseq's "
        "`detectRFuse` does, docs above); *commit*: the code the row ran on. A file dtoc's reader refuses is "
        "refused by every command with the same line: predict, simulate and optimize are then not run.",
        "",
        "| " + " | ".join(COLUMNS) + " |",
        "|" + "---|" * len(COLUMNS),
    ]
    lines = ["| " + " | ".join(c) + " |" for c in cells]
    tail = []
    if meta.get("sources"):
        tail = ["", "Sources (GitHub): " + ", ".join(f"`{x}`" for x in sorted(meta["sources"])) + "."]
    return "\n".join(head + lines + tail) + "\n" + END + "\n"


def render(rows: list[dict], girf_name: str, budgets: dict, commit: str, when: str | None = None) -> str:
    """The section of these rows alone."""
    for r in rows:  # rows of an earlier version of this script said "exit 3"
        for k in ("check", "predict", "simulate", "result"):
            if isinstance(r.get(k), str) and r[k].startswith("exit 3: "):
                r[k] = "internal error: " + r[k][len("exit 3: ") :]
    meta = {
        "girf": girf_name,
        "budgets": budgets,
        "mem_cap_gb": MEM_CAP_MB / 1024,
        "dates": sorted({(when or _now())[:10]} | {r["date"][:10] for r in rows if r.get("date")}),
        "sources": {r["source_repo"] for r in rows if r.get("source_repo")},
    }
    return section([_cells(row_line(r, commit)) for r in rows], meta)


def _now() -> str:
    return f"{dt.datetime.now(dt.timezone.utc):%Y-%m-%d %H:%M}"


def write_section(text: str) -> None:
    """Replace the marked section of docs/foreign.md (append it when absent); the rest of the page is untouched."""
    doc = DOC.read_text() if DOC.exists() else ""
    if BEGIN in doc and END in doc:
        a, b = doc.index(BEGIN), doc.index(END) + len(END)
        doc = doc[:a] + text.rstrip("\n") + doc[b:]
    else:
        doc = doc.rstrip("\n") + "\n\n" + text
    DOC.write_text(doc if doc.endswith("\n") else doc + "\n")


def _cells(line: str) -> list[str]:
    return [c.strip() for c in line.strip()[1:-1].split("|")]


def merge_section(rows: list[dict], commit: str, girf_name: str | None, budgets: dict, when: str | None = None) -> str:
    """The page's section with these rows in place of the same files' rows (source folder and file name), new
    files appended, the others kept (their result cells cleaned as :func:`clean_result` does), and everything else
    of the section (counts, classes, commits, dates, sources) rendered again over the merged table."""
    doc = DOC.read_text()
    if BEGIN not in doc or END not in doc:
        raise SystemExit("--merge: docs/foreign.md has no public-corpus section to merge into")
    sec = doc[doc.index(BEGIN) : doc.index(END)].splitlines()
    start = next(i for i, ln in enumerate(sec) if ln.startswith("| source |"))
    cells = []
    for ln in sec[start + 2 :]:
        if not ln.startswith("| "):
            break
        c = _cells(ln)
        if len(c) == len(COLUMNS):
            c[C_RESULT] = clean_result(c[C_RESULT])
            cells.append(c)
    pos = {tuple(c[:2]): i for i, c in enumerate(cells)}
    for r in rows:
        c = _cells(row_line(r, commit))
        if tuple(c[:2]) in pos:
            cells[pos[tuple(c[:2])]] = c
        else:
            pos[tuple(c[:2])] = len(cells)
            cells.append(c)
    text = "\n".join(sec)
    dates = set(re.findall(r"\d{4}-\d\d-\d\d", next((ln for ln in sec if ln.startswith("Rows ran ")), "")))
    dates |= {(when or _now())[:10]} | {r["date"][:10] for r in rows if r.get("date")}
    srcs = re.search(r"Sources \(GitHub\): (.*)\.", text)
    sources = set(re.findall(r"`([^`]+)`", srcs.group(1))) if srcs else set()
    sources |= {r["source_repo"] for r in rows if r.get("source_repo")}
    girf = re.search(r"GIRF: (.*)\.$", next((ln for ln in sec if ln.startswith("Rows ran ")), ""))
    girf_name = girf_name or (girf.group(1) if girf else "?")
    meta = {"girf": girf_name, "budgets": budgets, "mem_cap_gb": MEM_CAP_MB / 1024, "dates": sorted(dates)}
    meta["sources"] = sources
    return section(cells, meta)


def main() -> None:
    if len(sys.argv) == 3 and sys.argv[1] == "--probe":
        _probe(sys.argv[2])
        return
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dirs", nargs="*", type=Path, help="folders of .seq files (searched recursively)")
    ap.add_argument("--girf", type=Path, default=None, help="GIRF .npz (dtoc girf import ...); needed to run files")
    ap.add_argument("--budget-optimize", type=float, default=300.0, help="optimize wall-clock budget per file, s")
    ap.add_argument("--budget", type=float, default=120.0, help="read / check / predict / simulate budget per file, s")
    ap.add_argument("--mem-cap-gb", type=float, default=MEM_CAP_MB / 1024, help="resident memory that stops a step, GB")
    ap.add_argument("--only", nargs="*", default=None, help="substrings of the paths to run")
    ap.add_argument("--rows", type=Path, default=None, help="also write the rows as JSON lines here")
    ap.add_argument("--no-write", action="store_true", help="print the table, leave docs/foreign.md alone")
    ap.add_argument("--render", type=Path, default=None, help="only render the table of a --rows file (no runs)")
    ap.add_argument("--commit", default=None, help="with --render: the commit the rows ran on")
    ap.add_argument("--when", default=None, help="with --render: when the rows ran (default: now)")
    ap.add_argument("--girf-label", default=None, help="how the table names the GIRF (default: its file name)")
    ap.add_argument(
        "--merge",
        action="store_true",
        help="replace only these files' rows in docs/foreign.md's table (and its counts)",
    )
    a = ap.parse_args()
    budgets = {"read": a.budget, "other": a.budget, "optimize": a.budget_optimize}
    globals()["MEM_CAP_MB"] = 1024 * a.mem_cap_gb  # (the steps' cap, render's header)
    if a.render is not None:
        rows = [json.loads(ln) for ln in a.render.read_text().splitlines() if ln.strip()]
        _finish(rows, a, budgets, a.commit or "?")
        return
    if a.girf is None:
        ap.error("--girf is needed to run files (only --render goes without it)")
    files = sorted({p.resolve() for d in a.dirs for p in (d.rglob("*.seq") if d.is_dir() else [d])})
    if a.only:
        files = [f for f in files if any(s in str(f) for s in a.only)]
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", "1")}
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True, text=True).stdout
    idx = _index([d for d in a.dirs if d.is_dir()])
    rows = []
    with tempfile.TemporaryDirectory() as td:
        for f in files:
            row = run_file(f, a.girf.resolve(), budgets, Path(td), env)
            row["source_repo"] = (idx.get(str(f)) or {}).get("source_repo")
            row["commit"] = commit.strip() or "?"
            row["date"], row["budgets"] = _now(), {**budgets, "mem_cap_gb": a.mem_cap_gb}
            rows.append(row)
            print(json.dumps({k: v for k, v in row.items() if k != "probe"}), flush=True)
            if a.rows is not None:
                with open(a.rows, "a") as fo:
                    fo.write(json.dumps(row) + "\n")
    _finish(rows, a, budgets, commit.strip() or "?")


def _finish(rows: list[dict], a, budgets: dict, commit: str) -> None:
    label = a.girf_label or (a.girf.name if a.girf is not None else None)
    if a.merge:
        text = merge_section(rows, commit, a.girf_label, budgets, a.when)  # (the table's own GIRF label kept)
    else:
        text = render(rows, label or "?", budgets, commit, a.when)
    if not a.no_write:
        write_section(text)
    print(text)


if __name__ == "__main__":
    main()
