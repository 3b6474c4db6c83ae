"""``dtoc batch`` as a library call: expand the plan, skip what the store already holds, run the rest on an
engine, commit each finished job as it arrives, and report (docs/batch.md).

A failing job is one line in the report and does not stop the others.  An interrupt (SIGINT/SIGTERM) stops
the engine: jobs finished before it are kept (committed), running ones are dropped, and a re-run does the
rest.  Duplicate jobs (same key under two names) run once.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

from dtoc.batch.plan import OUT_MANIFEST, Job, expand, load_plan
from dtoc.batch.store import Store
from dtoc.util.interrupt import signals_ignored
from dtoc.version import __version__

#: per-job figures of the report (from the job's manifest; docs/cli.md report keys)
FIGURES = ("kspace_max_error_dk", "nrmse_percent", "ghost_ratio_percent")


def job_figures(manifest: dict) -> dict:
    """The report's figures of one job: before/after of :data:`FIGURES`, violations, discarded samples, time."""
    out: dict = {}
    for k in FIGURES:
        out[k] = {"before": manifest.get("before", {}).get(k), "after": manifest.get("after", {}).get(k)}
    out["limit_violations"] = manifest.get("limit_violations")
    out["check_failed"] = (manifest.get("output") or {}).get("check_failed")  # the written file's failed rules
    out["n_samples_discarded"] = manifest.get("n_samples_discarded")
    out["run_time_s"] = manifest.get("run_time_s")
    lim = manifest.get("limits", {})
    out["limits"] = {"gmax_mT_per_m": lim.get("gmax_mT_per_m"), "smax_T_per_m_per_s": lim.get("smax_T_per_m_per_s")}
    out["warnings"] = manifest.get("warnings", [])
    return out


def run_batch(
    plan_path: str | Path,
    out_dir: str | Path,
    *,
    engine: str = "local",
    workers: int | None = None,
    address: str | None = None,
    progress: Callable | None = None,
    report_path: str | Path | None = None,
    force: bool = False,
) -> dict:
    """Run the plan into ``out_dir``; returns the report (``jobs``: one record per job in plan order, with
    ``status`` ran | cached | failed | interrupted | not_run, ``error``, ``figures``, ``dir``).

    ``progress(stage, done, total, text)`` is called as jobs finish.  ``report_path``: where the caller will
    write the report; refused before any work if it exists (without ``force``) or is one of the plan's inputs.
    When interrupted, re-raises the KeyboardInterrupt with the report so far as its ``report`` attribute.
    """
    from dtoc.batch.engines import ENGINES, default_workers, make_engine
    from dtoc.errors import InputError
    from dtoc.util.atomic import check_outputs
    from dtoc.util.validate import check_range

    t0 = time.perf_counter()
    # everything is validated before the output folder is created or touched: a refused batch leaves no trace
    check_range("workers", workers, "--workers")
    if engine not in ENGINES:
        raise InputError(f"--engine {engine!r}: expected one of {', '.join(ENGINES)}")
    if engine == "local" and address:
        raise InputError("--address is for --engine dask")
    plan_path = Path(plan_path)
    plan = load_plan(plan_path)
    jobs = expand(plan, plan_path.resolve().parent)
    inputs = {f"{j.name} {label}": f for j in jobs for label, f in j.request.input_files().items()}
    check_outputs({"--json": report_path}, {"PLAN": plan_path, **inputs}, force)
    Store.check(out_dir, [j.name for j in jobs], {"PLAN": plan_path, **inputs})
    store = Store.open(out_dir)
    by_key: dict[str, list[Job]] = {}
    for j in jobs:
        by_key.setdefault(j.key, []).append(j)
    status: dict[str, dict] = {}
    for key, js in by_key.items():
        rec = store.lookup(key)
        if rec is not None:
            for j in js:
                store.link(j.name, key)
            status[key] = {"status": "cached", "record": rec}
    todo = [k for k in by_key if k not in status]
    n_workers = min(workers or default_workers(), max(1, len(todo)))
    threads_per_job = max(int(by_key[k][0].request.threads or 1) for k in by_key)
    report: dict = {
        "dtoc_batch": 1,
        "dtoc": __version__,
        "plan": str(plan_path),
        "out": str(out_dir),
        "engine": engine,
        "workers": n_workers if todo else 0,
        "threads_per_job": threads_per_job,
        "warnings": [],
    }
    if todo and n_workers * threads_per_job > default_workers():
        report["warnings"].append(
            f"{n_workers} workers x {threads_per_job} torch threads per job exceed the {default_workers()} cores: "
            "jobs will compete for them (lower --workers or the plan's threads)"
        )

    def tick() -> None:
        if progress is None:
            return
        c = [s["status"] for s in status.values()]
        text = f"{c.count('ran')} ran, {c.count('cached')} cached, {c.count('failed')} failed"
        progress("jobs", len(c), len(by_key), text)

    interrupted: BaseException | None = None
    eng = None
    futures: dict = {}
    try:
        tick()
        if todo:
            from dtoc.util.atomic import signals_held
            from dtoc.util.interrupt import fault_point

            eng = make_engine(engine, n_workers, threads_per_job, address)
            report["workers"] = eng.workers
            with signals_held():  # spawned workers start with SIGINT/SIGTERM blocked (see init_worker)
                for k in todo:
                    payload = {
                        "key": k,
                        "request": by_key[k][0].request.model_dump(mode="json"),
                        "work_root": str(store.staging) if eng.name == "local" else None,
                    }
                    futures[eng.submit(payload)] = k
            for f in eng.as_completed(futures):
                k = futures[f]
                try:
                    res = f.result()
                except Exception as e:  # noqa: BLE001 - a lost worker is a failed job, not a crashed batch
                    from dtoc.errors import describe

                    res = {"status": "failed", "error": f"worker lost: {describe(e)[0]}", "exit_code": 3}
                status[k] = _settle(store, k, by_key[k], res)
                tick()
                fault_point("batch_job")
    except KeyboardInterrupt as e:
        interrupted = e
        with signals_ignored():  # a second Ctrl-C does not cut the clean-up short
            if eng is not None:
                eng.abort([f for f, k in futures.items() if k not in status])
            store.close()
    finally:
        if interrupted is None:
            if eng is not None:
                eng.close()
            store.close()
    for k in by_key:
        status.setdefault(k, {"status": "interrupted" if interrupted is not None else "not_run"})
    report["jobs"] = [_job_report(store, j, status[j.key]) for j in jobs]
    c = [r["status"] for r in report["jobs"]]
    report.update(
        n_jobs=len(jobs),
        n_ran=c.count("ran"),
        n_cached=c.count("cached"),
        n_failed=c.count("failed"),
        n_not_run=c.count("interrupted") + c.count("not_run"),
        interrupted=interrupted is not None,
        wall_time_s=time.perf_counter() - t0,
    )
    if interrupted is not None:
        interrupted.report = report  # type: ignore[attr-defined]
        raise interrupted
    return report


def _settle(store: Store, key: str, js: list[Job], res: dict) -> dict:
    """Commit a finished job and link its names; a failure or interrupt is recorded, nothing written."""
    import json

    if res.get("status") != "ok":
        return {"status": res.get("status", "failed"), "error": res.get("error"), "exit_code": res.get("exit_code")}
    files = res["files"]
    manifest = json.loads(files[OUT_MANIFEST])
    record = {
        "names": sorted(j.name for j in js),
        "request": js[0].request.model_dump(mode="json"),
        "figures": job_figures(manifest),
        "seconds": res.get("seconds"),
        "worker": res.get("worker"),
        "worker_peak_rss_mb": res.get("peak_rss_mb"),
    }
    rec = store.commit(key, files, record)
    for j in js:
        store.link(j.name, key)
    return {"status": "ran", "record": rec}


def _job_report(store: Store, j: Job, st: dict) -> dict:
    rec = st.get("record") or {}
    out = {
        "name": j.name,
        "key": j.key,
        "status": st["status"],
        "dir": str(store.job_dir(j.key)) if rec else None,
        "figures": rec.get("figures"),
        "seconds": rec.get("seconds") if st["status"] == "ran" else None,
        "worker_peak_rss_mb": rec.get("worker_peak_rss_mb") if st["status"] == "ran" else None,
        "error": st.get("error"),
    }
    return out
