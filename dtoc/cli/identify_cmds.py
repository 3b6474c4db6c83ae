"""CLI commands of the `dtoc.identify` stage (registered by :mod:`dtoc.cli.main`).

``dtoc identify MEASURED.npz [--girf H.npz | --model M.json] [--json REPORT.json] -o UPDATED.json
[--png RESIDUALS.png] [--force]``: thin layer over :func:`dtoc.identify.api.run_identify`; the result
tables go to stdout, progress lines to stderr.
"""

from __future__ import annotations

import sys
from pathlib import Path

import typer

from dtoc.cli.scanner import scanner_option
from dtoc.identify.kinds import CANDIDATE_KINDS as KINDS


def identify_cmd(
    measured: Path = typer.Argument(
        ..., help="measurement .npz (docs/contracts.md §1: dt, g, G and/or k, optional b0)"
    ),
    girf: Path | None = typer.Option(None, "--girf", help="declared model: a GIRF .npz"),
    model: Path | None = typer.Option(None, "--model", help="declared model: a model JSON file"),
    out: Path = typer.Option(
        ...,
        "-o",
        "--out",
        help="updated model JSON (declared model + effects adopted); not written when nothing is adopted",
    ),
    json_out: str | None = typer.Option(
        None,
        "--json",
        help="write the report JSON (docs/contracts.md §3) here ('-' = stdout; tables then go to stderr)",
    ),
    png: Path | None = typer.Option(None, "--png", help="write a PNG of residuals before/after (time and frequency)"),
    force: bool = typer.Option(False, "--force", help="overwrite existing outputs"),
    max_effects: int = typer.Option(6, "--max-effects", min=0, help="cap on the number of effects added"),
    threshold: float = typer.Option(
        10.0, "--threshold", min=0.0, help="minimum held-out score (chi-square units) to add an effect"
    ),
    kinds: str | None = typer.Option(
        None, "--kinds", help="comma-separated candidate kinds (default: all: " + ",".join(KINDS) + ")"
    ),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="no progress lines on stderr"),
    scanner: Path | None = scanner_option(),
):
    """Compare a measurement with the declared model, trace the residual to missing effects, write the updated model."""
    from dtoc.errors import InputError
    from dtoc.identify.api import run_identify
    from dtoc.identify.report import print_table
    from dtoc.util.validate import check_range, escape

    check_range("max_effects", max_effects, "--max-effects")
    kind_list = None
    if kinds is not None:
        kind_list = [k.strip() for k in kinds.split(",") if k.strip()]
        if not kind_list:
            raise InputError(f"--kinds {escape(kinds)}: names no kind (leave --kinds out for all: {', '.join(KINDS)})")
        bad = [escape(k, 40) for k in kind_list if k not in KINDS]
        if bad:
            raise InputError(f"--kinds: unknown kind(s) {', '.join(bad)}; known: {', '.join(KINDS)}")

    def progress(msg: str) -> None:
        if not quiet:
            sys.stderr.write(f"identify: {msg}\n")
            sys.stderr.flush()

    from dtoc.cli import scanner as sc
    from dtoc.util.atomic import check_outputs

    check_outputs(
        {"-o": out, "--json": json_out, "--png": png},
        {"MEASURED": measured, "--girf": girf, "--model": model, **sc.input_paths(scanner)},
        force,
    )
    from dtoc.util.validate import check_npz_archive

    for key, shape in check_npz_archive(measured, "MEASURED").items():
        if key in ("g", "G", "k") and len(shape) >= 1 and shape[-1] < 32:
            raise InputError(
                f"{measured}: '{key}' has {shape[-1]} samples per waveform; identify needs at least 32 (as girf fit)"
            )
    from dtoc.hardware.profile import profile_hardware

    declared = profile_hardware(sc.load(scanner), girf, model)
    res = run_identify(
        measured,
        girf=girf,
        model=model,
        out_model=out,
        json_out=json_out,
        png_out=png,
        force=force,
        max_effects=max_effects,
        threshold=threshold,
        kinds=kind_list,
        progress=progress,
        declared_model=declared,
    )
    from dtoc.cli.output import Output

    outp = Output(json_out)
    if outp.json_to_stdout:
        from dtoc.identify.report import report_json

        outp.write_json(report_json(res), force)
    print_table(res, console=outp.console())
    written = [str(p) for p in (out if res.adopted else None, json_out, png) if p is not None and str(p) != "-"]
    if written:
        progress("wrote " + ", ".join(written))
    if not res.adopted:
        progress(f"no model written to {out}: no effect beyond the declared model was adopted")


def register(app: typer.Typer) -> None:
    """Add this stage's commands to app."""
    app.command("identify")(identify_cmd)
