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


def identify_plan_cmd(
    out: Path | None = typer.Option(
        None, "-o", "--out", help="write the proposed waveforms here (.npz: dt, g, labels)"
    ),
    kinds: str | None = typer.Option(
        None, "--kinds", help="candidate kinds to identify (default: all parametric: delay,gain,offset,exp_eddy,...)"
    ),
    dt_us: float = typer.Option(10.0, "--dt-us", min=0.1, help="sample interval of the waveforms, us"),
    gmax: float = typer.Option(30.0, "--gmax", min=0.1, help="largest amplitude to play, mT/m"),
    smax: float = typer.Option(150.0, "--smax", min=1.0, help="largest slew rate to play, T/m/s"),
    record_ms: float = typer.Option(50.0, "--record-ms", min=1.0, help="length of each waveform, ms"),
    sigma_g: float = typer.Option(0.01, "--sigma-g", min=1e-9, help="expected G noise per sample, mT/m"),
    json_out: str | None = typer.Option(None, "--json", help="write the check as JSON here ('-' = stdout)"),
    force: bool = typer.Option(False, "--force", help="overwrite existing outputs"),
):
    """Propose a short set of test waveforms (one axis at a time) that identifies a candidate set, and check it
    with the identifiability test identify uses (docs/identify.md, "Planning a measurement")."""
    import json

    import numpy as np

    from dtoc.errors import InputError
    from dtoc.identify.plan import NOMINAL, check, propose
    from dtoc.util.atomic import atomic_write_bytes, check_outputs

    kind_list = None
    if kinds is not None:
        kind_list = [k.strip() for k in kinds.split(",") if k.strip()]
        bad = [k for k in kind_list if k not in NOMINAL]
        if not kind_list or bad:
            raise InputError(f"--kinds: unknown or no kind(s) {bad}; plannable: {', '.join(NOMINAL)}")
    check_outputs({"-o": out, "--json": json_out}, {}, force)
    dt_s = dt_us / 1e6
    g, labels = propose(dt_s, gmax, smax, record_ms * 1e-3)
    verdicts = check(g, dt_s, kind_list, sigma_g)
    report = {
        "dt_s": dt_s,
        "waveforms": labels,
        "candidates": [
            {
                "name": v.name,
                "identifiable": v.identifiable,
                "relative_stderr": None if not np.isfinite(v.rel_se) else float(v.rel_se),
                "most_correlated_with": v.partner,
                "correlation": float(v.corr),
                "reason": v.reason,
            }
            for v in verdicts
        ],
        "all_identifiable": all(v.identifiable for v in verdicts),
    }
    from dtoc.cli.output import Output

    outp = Output(json_out)
    con = outp.console()
    con.print(f"{len(labels)} test waveforms of {record_ms:g} ms at {dt_us:g} us (one axis at a time):", markup=False)
    for lab in labels:
        con.print(f"  - {lab}", markup=False)
    con.print(f"identifiability on these waveforms (G measured, noise {sigma_g:g} mT/m):", markup=False)
    for v in verdicts:
        con.print(f"  {v.name}: {v.reason}", markup=False)
    if out is not None:
        import io

        buf = io.BytesIO()
        np.savez(buf, dt=np.float64(dt_s), g=g, labels=np.asarray(labels))
        atomic_write_bytes(out, buf.getvalue(), force=force)
    outp.write_json(json.dumps(report, indent=2) + "\n", force)


def register(app: typer.Typer) -> None:
    """Add this stage's commands to app."""
    app.command("identify")(identify_cmd)
    app.command("identify-plan")(identify_plan_cmd)
