"""CLI commands of the `dtoc.optimize` stage: ``dtoc optimize`` (registered by :mod:`dtoc.cli.main`)."""

from __future__ import annotations

import sys
from pathlib import Path

import typer

from dtoc.cli.output import Output, json_option, note
from dtoc.cli.scanner import ORIENTATION_HELP, rf_use_option, scanner_option
from dtoc.constants import DEFAULT_B0_T
from dtoc.util.jsonout import strict_json


def optimize_cmd(
    base: Path = typer.Argument(..., help="base sequence: .seq file or spec .yaml"),
    out: Path = typer.Option(..., "-o", "--out", help="pre-compensated .seq to write"),
    girf: Path | None = typer.Option(None, "--girf", help="GIRF .npz (hardware model = this GIRF)"),
    model: Path | None = typer.Option(None, "--model", help="hardware model JSON"),
    ideal: bool = typer.Option(False, "--ideal", help="optimize for ideal hardware (no --girf / --model)"),
    config: Path | None = typer.Option(None, "--config", help="optimizer config YAML (OptimizeConfig fields)"),
    json_out: str | None = json_option("the run manifest"),
    png: Path | None = typer.Option(None, "--png", help="write the PNG report here"),
    force: bool = typer.Option(False, "--force", help="overwrite existing outputs"),
    resume: Path | None = typer.Option(None, "--resume", help="continue from a checkpoint .npz"),
    checkpoint: Path | None = typer.Option(None, "--checkpoint", help="save checkpoints here while running"),
    trajectory: Path | None = typer.Option(
        None,
        "--trajectory",
        help="realized-trajectory side-car (.npz, docs/contracts.md §5; default: beside -o as <name>.traj.npz)",
    ),
    no_trajectory: bool = typer.Option(False, "--no-trajectory", help="do not write the side-car"),
    orientation: str | None = typer.Option(None, "--orientation", help=ORIENTATION_HELP),
    scanner: Path | None = scanner_option(),
    offset: str | None = typer.Option(
        None, "--offset", help="off-centre slice/FOV position x,y,z in m (physical): FOV-shift phase corrected per ADC"
    ),
    method: str | None = typer.Option(None, "--method", help="dto | adam-paper | warmstart | preemphasis"),
    gmax: float | None = typer.Option(None, "--gmax", help="gradient limit per axis, mT/m (default: the sequence's)"),
    smax: float | None = typer.Option(None, "--smax", help="slew limit per axis, T/m/s (default: the sequence's)"),
    iters: int | None = typer.Option(None, "--iters", help="full-loss iterations"),
    warm_iters: int | None = typer.Option(
        None, "--warm-iters", help="warm-start iterations (a fixed count; default: solve to --k-tol)"
    ),
    k_tol: float | None = typer.Option(
        None, "--k-tol", help="warm-start stopping tolerance on every reachable sample's k error, dk (default 0.01)"
    ),
    lr: float | None = typer.Option(None, "--lr", help="Adam learning rate"),
    w_image: float | None = typer.Option(None, "--w-image", help="weight of the image (NRMSE) term"),
    w_k: float | None = typer.Option(None, "--w-k", help="weight of the k-space term (dk^2 per sample)"),
    w_rf: float | None = typer.Option(None, "--w-rf", help="weight of the realized-gradient-during-RF term"),
    augment: int | None = typer.Option(None, "--augment", help="number of rotated phantoms (0 = none)"),
    no_discard: bool = typer.Option(False, "--no-discard", help="keep every sample (no post-hoc skipping)"),
    phantom: str | None = typer.Option(
        None,
        "--phantom",
        help="phantom: brain, brain:N, brain-noscalp[:N] (no fat/skull), brain3d[:N] (3D head: the image term of a 3D-encoded sequence, asked for) or a .npz",
    ),
    b0: float | None = typer.Option(
        None,
        "--b0",
        help=f"field strength of the built-in phantom's tissue values, T (default {DEFAULT_B0_T:g}, as simulate)",
    ),
    seed: int | None = typer.Option(None, "--seed", help="random seed"),
    threads: int | None = typer.Option(None, "--threads", help="torch threads (fixed for reproducibility)"),
    device: str = typer.Option("cpu", "--device", help="torch device (cpu, cuda, ...)"),
    format_version: str | None = typer.Option(
        None,
        "--format-version",
        help="Pulseq format of the output: 1.4.0, 1.4.1, 1.5.0, 1.5.1 or 1.5.2 (default: the base's, or the "
        "--scanner profile's interpreter_version); what it cannot state is refused before any work",
    ),
    quiet: bool = typer.Option(False, "-q", "--quiet", help="no progress on stderr"),
    rf_use: str | None = rf_use_option(),
    allow_worse: bool = typer.Option(
        False,
        "--allow-worse",
        help="optimize even when the base needs more than 10x --gmax or --smax (refused otherwise: no waveform "
        "within such limits follows the base)",
    ),
):
    """Digital-twin optimization: write a pre-compensated .seq that stays within the hardware limits."""
    from dtoc.errors import InputError
    from dtoc.optimize.request import run_request

    if method is not None and method not in ("dto", "adam-paper", "warmstart", "preemphasis"):
        raise InputError(f"--method {method!r}: expected dto, adam-paper, warmstart or preemphasis")
    req = request_from_options(
        base=base, out=out, girf=girf, model=model, ideal=ideal, config=config, json_out=json_out, png=png,
        force=force, resume=resume, checkpoint=checkpoint, trajectory=trajectory, no_trajectory=no_trajectory,
        orientation=orientation, scanner=scanner, offset=offset, method=method, gmax=gmax, smax=smax, iters=iters,
        warm_iters=warm_iters, k_tol=k_tol, lr=lr, w_image=w_image, w_k=w_k, w_rf=w_rf, augment=augment, no_discard=no_discard,
        phantom=phantom, b0=b0, seed=seed, threads=threads, device=device, format_version=format_version,
        rf_use=rf_use, allow_worse=allow_worse,
    )  # fmt: skip
    outp = Output(json_out)
    m = _run_with_progress(quiet, lambda progress: run_request(req, progress, notes=lambda n: note(f"note: {n}")))
    if outp.json_to_stdout:
        outp.write_json(strict_json(m), force)
    _print_summary(m, outp.console())
    for w in m.get("warnings", []):
        sys.stderr.write(f"dtoc: warning: {w}\n")
    if m.get("interrupted"):
        interrupted_exit(m)
    if not (m.get("output") or {}).get("check_ok", True):
        raise typer.Exit(1)  # the written file fails a check the user asked for (docs/cli.md, exit codes)


def request_from_options(**options):
    """The :class:`~dtoc.optimize.request.OptimizeRequest` of the command's options (a validation error of a
    value the option parser let through becomes one InputError line naming the option)."""
    from pydantic import ValidationError

    from dtoc.errors import InputError
    from dtoc.optimize.request import OptimizeRequest

    try:
        return OptimizeRequest(**options)
    except ValidationError as e:
        err = e.errors()[0]
        opt = "--" + str(err["loc"][0]).replace("_", "-") if err["loc"] else "an option"
        raise InputError(f"{opt}: {err['msg']}") from None


def interrupted_exit(m: dict) -> None:
    """After an interrupted run wrote its best-so-far: one line, exit 130 (SIGINT) or 143 (SIGTERM)."""
    from dtoc.util.interrupt import exit_code, signal_name

    out = (m.get("output") or {}).get("path")
    where = (
        f"wrote the best-so-far to {out} (DtocInterrupted 1; manifest interrupted: true)" if out else "no .seq output"
    )
    ck = m.get("checkpoint")
    resume = f"; resume with --resume {ck}" if ck else ""
    sys.stderr.write(f"dtoc: interrupted by {signal_name()}: {where}{resume}\n")
    sys.stderr.flush()
    raise SystemExit(exit_code())


def _run_with_progress(quiet: bool, fn):
    """Run ``fn(progress)`` reporting on stderr (:class:`dtoc.cli.progress.ProgressReporter`: a bar with ETA
    on a terminal, plain lines otherwise; nothing before the first report, so an early error prints only
    its one line)."""
    from dtoc.cli.progress import ProgressReporter

    rep = ProgressReporter("dtoc optimize", quiet=quiet)
    try:
        return fn(rep.update)
    finally:
        rep.close()


def _print_summary(m: dict, con) -> None:
    from rich.table import Table

    t = Table(title="dtoc optimize")
    t.add_column("figure")
    t.add_column("before", justify="right")
    t.add_column("after", justify="right")

    def f(v, pct=False):
        if v is None:
            return "-"
        return f"{v:.3f} %" if pct else f"{v:.4g}"

    for key, pct in (
        ("nrmse_percent", True),
        ("ghost_ratio_percent", True),
        ("ghost_ratio_excess_percent", True),
        ("kspace_rms_error_rad_per_m", False),
        ("kspace_max_error_dk", False),
    ):
        if key == "ghost_ratio_excess_percent" and m["after"].get(key) is None:
            continue  # EPI only: ghost ratio above the ideal image's own (docs/optimize.md)
        t.add_row(key, f(m["before"].get(key), pct), f(m["after"].get(key), pct))
    t.add_row("n_samples_discarded", "0", str(m["n_samples_discarded"]))
    con.print(t)
    out = m.get("output", {})
    lim = m["limits"]
    src = lim.get("source", {})
    from dtoc.cli.output import note

    if m["before"].get("image_reason"):
        note(f"note: image figures '-': {m['before']['image_reason']}")
    at = (
        f"gmax {lim['gmax_mT_per_m']:g} mT/m ({src.get('gmax_mT_per_m', '?')}), "
        f"smax {lim['smax_T_per_m_per_s']:g} T/m/s ({src.get('smax_T_per_m_per_s', '?')})"
    )
    sv = m.get("solver")
    if sv and sv.get("summary"):
        note(sv["summary"])
    n_inh = len(out.get("check_inherited") or [])
    if out.get("check_ok", True) and n_inh:  # the base's own steps, kept (a warning names them)
        note(
            f"wrote {out.get('path')} in {m['run_time_s']:.1f} s; limits verified at {at}; 0 violations introduced, "
            f"{n_inh} inherited from the base"
        )
    elif out.get("check_ok", True):
        note(f"wrote {out.get('path')} in {m['run_time_s']:.1f} s; limits verified, 0 violations at {at}")
    else:  # never "0 violations" for a file dtoc check fails (exit 1 in optimize_cmd)
        note(
            f"wrote {out.get('path')} in {m['run_time_s']:.1f} s; within the limits at {at}, but dtoc check of the "
            f"written file FAILED: {out.get('check_failed') or ', '.join(out.get('check_other_rules', []))}"
        )
    for c in (m.get("output") or {}).get("checks", []):
        note(c)
    oc = m.get("offcentre")
    if oc:
        off = ",".join(f"{x:g}" for x in oc["offset_m"])
        note(
            f"off-centre {off} m: FOV-shift phase at the ADC samples max {oc['output_corrected']['max_rad']:.3g} rad "
            f"(rms {oc['output_corrected']['rms_rad']:.3g}) after the per-ADC phase/frequency corrections; "
            f"{oc['output_uncorrected']['max_rad']:.3g} rad without them, {oc['base']['max_rad']:.3g} rad for the base file"
        )
    tr = m.get("trajectory")
    if tr:
        nd = tr["n_discarded"]
        note(
            f"wrote {tr['path']}: predicted realized k and B0 phase of {tr['n_samples']} ADC samples"
            + (f" ({nd} discarded, flagged there)" if nd else "")
        )


def register(app: typer.Typer) -> None:
    """Add this stage's commands to app."""
    app.command("optimize")(optimize_cmd)
