"""CLI command ``dtoc batch`` (registered by :mod:`dtoc.cli.main`): a thin layer over :func:`dtoc.batch.run.run_batch`."""

from __future__ import annotations

from pathlib import Path

import typer

from dtoc.cli.output import Output, json_option, note


def batch_cmd(
    plan: Path = typer.Argument(
        ..., help="batch plan YAML (docs/batch.md): sequences, hardware, orientations, options"
    ),
    out: Path = typer.Option(..., "--out", "-o", help="output folder (new, empty, or one of an earlier dtoc batch)"),
    engine: str = typer.Option("local", "--engine", help="local (process pool, default) or dask"),
    workers: int | None = typer.Option(None, "--workers", help="workers (default: the cores of this machine)"),
    address: str | None = typer.Option(None, "--address", help="Dask scheduler, tcp://host:port (--engine dask)"),
    json_out: str | None = json_option("the batch report"),
    force: bool = typer.Option(False, "--force", help="overwrite an existing --json report"),
    quiet: bool = typer.Option(False, "-q", "--quiet", help="no progress on stderr"),
):
    """Run many `dtoc optimize` jobs (sequences x scanners x orientations x option sets), cached and resumable.

    Exit 0 when every job succeeded (ran or cached), 1 when any failed, 130/143 when interrupted (finished
    jobs are kept; run again to do the rest)."""
    from dtoc.batch.run import run_batch
    from dtoc.cli.progress import ProgressReporter
    from dtoc.util.jsonout import strict_json

    outp = Output(json_out)
    rep = ProgressReporter("dtoc batch", quiet=quiet, value_label="jobs")
    try:
        report = run_batch(
            plan,
            out,
            engine=engine,
            workers=workers,
            address=address,
            progress=rep.update,
            report_path=json_out,
            force=force,
        )
    except KeyboardInterrupt as e:
        if getattr(e, "report", None) is None:
            raise
        stopped: KeyboardInterrupt | None = e
    else:
        stopped = None
    finally:
        rep.close()
    if stopped is not None:  # outside the except block: the exit carries no interrupt as its context
        _interrupted_exit(stopped, outp, out, force)
    outp.write_json(strict_json(report), force)
    _print_table(report, outp.console())
    for w in report["warnings"]:
        note(f"dtoc: warning: {w}")
    note(
        f"{report['n_jobs']} jobs: {report['n_ran']} ran, {report['n_cached']} cached, {report['n_failed']} failed "
        f"in {report['wall_time_s']:.1f} s ({report['engine']}, {report['workers']} workers); outputs in {out}/<job>"
    )
    if report["n_failed"]:
        raise SystemExit(1)


def _interrupted_exit(e: KeyboardInterrupt, outp: Output, out: Path, force: bool) -> None:
    """The report so far, one line, exit 130 (SIGINT) / 143 (SIGTERM)."""
    from dtoc.util.interrupt import exit_code, signal_name
    from dtoc.util.jsonout import strict_json

    r = e.report  # type: ignore[attr-defined]
    signum = getattr(e, "signum", None)
    outp.write_json(strict_json(r), force)
    note(
        f"dtoc: interrupted by {signal_name(signum)}: {r['n_ran'] + r['n_cached']} of {r['n_jobs']} jobs finished "
        f"and kept in {out}; run the same command again to do the rest"
    )
    raise SystemExit(exit_code(signum))


def _print_table(report: dict, con) -> None:
    from rich.table import Table

    t = Table(title="dtoc batch")
    for c, j in (
        ("job", "left"),
        ("status", "left"),
        ("k max err, dk (before -> after)", "right"),
        ("NRMSE %", "right"),
        ("ghost %", "right"),
        ("violations", "right"),
        ("time s", "right"),
    ):
        t.add_column(c, justify=j)  # type: ignore[arg-type]

    def f(v, fmt=".3g"):
        return "-" if v is None else format(v, fmt)

    for r in report["jobs"]:
        fig = r.get("figures") or {}
        k = fig.get("kspace_max_error_dk") or {}
        t.add_row(
            r["name"],
            r["status"],
            f"{f(k.get('before'))} -> {f(k.get('after'))}" if k else "-",
            f((fig.get("nrmse_percent") or {}).get("after")),
            f((fig.get("ghost_ratio_percent") or {}).get("after")),
            "check FAILED" if fig.get("check_failed") else f(fig.get("limit_violations"), "d"),
            f(r.get("seconds"), ".1f"),
        )
    con.print(t)
    for r in report["jobs"]:
        if r["status"] == "failed":
            con.print(f"{r['name']}: {r.get('error')}", soft_wrap=True, markup=False)
        elif (r.get("figures") or {}).get("check_failed"):
            con.print(f"{r['name']}: dtoc check of the output FAILED: {r['figures']['check_failed']}", markup=False)


def register(app: typer.Typer) -> None:
    """Add this stage's commands to app."""
    app.command("batch")(batch_cmd)
