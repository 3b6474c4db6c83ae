"""CLI commands of the `dtoc.seq` stage: ``build``, ``check``, ``diff`` (registered by :mod:`dtoc.cli.main`)."""

from __future__ import annotations

import sys
import warnings
from pathlib import Path

import typer

from dtoc.cli.output import Output, json_option, note
from dtoc.cli.scanner import reference_option, scanner_option
from dtoc.util.jsonout import strict_json


def build_cmd(
    spec: Path = typer.Argument(..., help="spec YAML (kind gre or epi; examples in sequences/*.yaml)"),
    out: Path = typer.Option(..., "-o", "--out", help="output .seq (its folder must exist)"),
    force: bool = typer.Option(False, "--force", help="overwrite an existing output"),
    format_version: str | None = typer.Option(
        None, "--format-version", help="Pulseq format of the output: 1.4.0, 1.4.1, 1.5.0 (default), 1.5.1 or 1.5.2"
    ),
):
    """Build a base sequence from a spec and write a signed Pulseq .seq (format 1.5.0 unless --format-version; deterministic).

    Spec fields carry their units in the name (fov_mm, dwell_us, te_ms, ...; docs/sequences.md). A spec
    whose ideal waveforms exceed its system limits still builds (an optimization target) with a warning
    giving the worst violation; 'dtoc check' then rejects the file.
    """
    from dtoc.errors import InputError
    from dtoc.seq.build import SpecLimitWarning, build_to_file
    from dtoc.seq.spec import load_spec
    from dtoc.util.atomic import check_outputs

    if out.suffix.lower() != ".seq":
        raise InputError(f"{out}: the output must be a .seq file (Pulseq interpreters expect the .seq extension)")
    check_outputs({"-o": out}, {"SPEC": spec}, force)
    s = load_spec(spec)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", SpecLimitWarning)
        try:
            p = build_to_file(s, out, force=force, version=format_version)
        except InputError as e:
            msg = str(e)
            raise InputError(
                msg if msg.startswith(str(spec)) or msg.startswith(str(out)) else f"{spec}: {msg}"
            ) from None
    for w in caught:
        if issubclass(w.category, SpecLimitWarning):
            sys.stderr.write(f"dtoc: warning: {w.message}\n")
    sys.stderr.write(f"wrote {p}\n")


def check_cmd(
    seq: Path = typer.Argument(..., help=".seq file to validate"),
    system: Path | None = typer.Option(None, "--system", help="SystemSpec YAML (limits, rasters, dead times)"),
    gmax: float | None = typer.Option(None, "--gmax", help="per-axis gradient limit, mT/m (overrides)"),
    smax: float | None = typer.Option(None, "--smax", help="per-axis slew limit, T/m/s (overrides)"),
    json_out: str | None = json_option("the check result"),
    force: bool = typer.Option(False, "--force", help="overwrite an existing --json file"),
    max_rows: int = typer.Option(20, "--max-rows", help="violations shown in the table (all are in --json)"),
    orientation: str | None = typer.Option(
        None, "--orientation", help="the orientation it will be played at: warn if the file was compiled for another"
    ),
    scanner: Path | None = scanner_option(),
    reference: Path | None = reference_option(),
):
    """Validate a .seq before upload; exit 1 on any violation, 0 when clean.

    --reference BASE: the file must have the base's structure (else exit 2) and, where it records one, the
    base's hash; its k error against the base's nominal k is reported, realized through the --scanner
    profile's hardware model at --orientation when the profile has one, else of its demanded waveform.

    Limits: --gmax/--smax override --system, which overrides the limits a dtoc-built file records; a file
    without recorded limits needs --gmax and --smax (or --system): limits are never assumed.
    """

    from dtoc.errors import InputError
    from dtoc.seq.check import check_file, system_from_definitions
    from dtoc.seq.seqtext import parse_seq_text
    from dtoc.seq.spec import load_system
    from dtoc.seq.system import SystemSpec
    from dtoc.util.validate import check_range

    check_range("gmax", gmax, "--gmax")
    check_range("smax", smax, "--smax")
    if max_rows < 0:
        raise InputError(f"--max-rows must be >= 0, got {max_rows}")
    from dtoc.cli import scanner as sc
    from dtoc.util.atomic import check_outputs

    check_outputs(
        {"--json": json_out},
        {"SEQ": seq, "--system": system, "--reference": reference, **sc.input_paths(scanner)},
        force,
    )

    prof = sc.load(scanner)
    rotation = None
    if orientation is not None:
        from dtoc.hardware.orientation import parse_orientation

        rotation = parse_orientation(orientation)
    sysspec = load_system(system) if system else None
    base = f"--system {system}" if system else None
    if sysspec is None and prof is not None:
        sysspec, base = prof.profile.system_spec(), f"--scanner {prof.profile.name}"
    if prof is not None:
        for line in prof.profile.not_checked():
            note(line)
    if gmax is not None or smax is not None:
        if sysspec is None:
            st = parse_seq_text(seq)
            defs = {k: (v.split()[0] if v.split() else v) for k, v in st.definitions().items()}
            try:
                sysspec = system_from_definitions(defs)
            except InputError as e:
                if gmax is None or smax is None:  # the file's other limit is needed but invalid
                    raise InputError(f"{seq}: {e}") from None
                sysspec = None
            if sysspec is None and (gmax is None or smax is None):
                missing = "--smax" if smax is None else "--gmax"
                raise InputError(
                    f"{seq}: the file records no gradient limits: give {missing} too, or --system (limits are never assumed)"
                )
            base = "file definitions" if sysspec is not None else None
            sysspec = sysspec or SystemSpec()  # its conventions are not checked (conventions=None below)
        upd = {}
        if gmax is not None:
            upd["max_grad_mT_per_m"] = gmax
        if smax is not None:
            upd["max_slew_T_per_m_per_s"] = smax
        from pydantic import ValidationError

        from dtoc.seq.system import format_validation_error

        try:
            sysspec = SystemSpec(**{**sysspec.model_dump(), **upd})
        except ValidationError as e:
            raise InputError(f"--gmax/--smax: {format_validation_error(e)} (mT/m and T/m/s)") from None
    safety = prof.profile.safety_checks(rotation) if prof is not None else None
    given = " ".join(f"{n} {v:g}" for n, v in (("--gmax", gmax), ("--smax", smax)) if v is not None)
    limits_source = " + ".join(x for x in (base, given) if x) or None
    # vendor conventions (dead times, ring-down, ADC samples, rasters): only those a profile or system file names
    conventions = f"--system {system}" if system else (f"--scanner {prof.profile.name}" if prof is not None else None)
    res = check_file(seq, sysspec, safety, limits_source=limits_source, conventions=conventions)
    bad_orientation = _recorded_orientation_problem(res.definitions)
    if bad_orientation is not None:
        res.warnings.append(bad_orientation)
    elif rotation is not None:
        res.warnings.extend(_orientation_warnings(res.definitions, rotation))
    report = res.to_dict()
    ref_line = None
    if reference is not None:
        report["reference"], ref_line = _reference_check(seq, reference, prof, rotation)
    outp = Output(json_out)
    outp.write_json(strict_json(report), force)
    _print_check(res, max_rows, outp.console())
    if ref_line is not None:
        outp.console().print(ref_line)
    for w in res.warnings:
        note(f"dtoc: warning: {w}")
    for c in res.checks:
        note(c)
    for c in res.not_checked:
        note(c)
    if not res.ok:
        raise typer.Exit(1)


def _reference_check(seq: Path, reference: Path, prof, rotation) -> tuple[dict, str]:
    """``check --reference``: structure and hash (refused in one line otherwise), then the k error against the
    base (realized through the profile's model at the orientation where there is one)."""
    from dtoc.hardware.profile import profile_hardware
    from dtoc.seq.load import load_sequence
    from dtoc.sim.reference import load_reference, reference_figures

    ir = load_sequence(seq)
    base, rec = load_reference(ir, seq, reference)
    note(rec.pop("note"))
    hw = profile_hardware(prof, None, None)
    if hw is not None and rotation is not None:
        from dtoc.hardware.orientation import RotatedChain

        hw = RotatedChain(hw, rotation)
    fig = reference_figures(ir, base, hw)
    rec.update(fig)
    what = "realized k (the profile's hardware model)" if fig["realized"] else "demanded k (no hardware model)"
    k = fig["k_error_max_dk"]
    ks = f"{k:.4g} dk" if k is not None else f"{fig['k_error_max_rad_per_m']:.4g} rad/m (the base has no FOV)"
    oe = fig["epi_odd_minus_even_dk"]
    line = f"against the base {reference}: {what} off the base's nominal k by at most {ks}" + (
        f", EPI odd-even {oe:.4g} dk" if oe is not None else ""
    )
    return rec, line


def _recorded_orientation_problem(definitions: dict) -> str | None:
    """A ``DtocOrientation`` definition that is not 9 numbers of a rotation: one warning naming it (None: absent
    or valid)."""
    from dtoc.errors import InputError
    from dtoc.hardware.orientation import parse_orientation
    from dtoc.util.validate import escape

    v = (definitions or {}).get("DtocOrientation")
    if v is None:
        return None
    text = " ".join(str(x) for x in v) if isinstance(v, (list, tuple)) else str(v)
    try:
        if len(text.split()) != 9:
            raise InputError("not 9 numbers")
        parse_orientation(text)
    except InputError:
        return (
            f"the file's DtocOrientation {escape(text, 60)} is not 9 numbers of a rotation matrix: the orientation it "
            "was compiled for is unknown (its pre-compensation holds only at that orientation)"
        )
    return None


def _orientation_warnings(definitions: dict, want) -> list[str]:
    """A file compiled (pre-compensated) for one orientation and checked for another (``want``, R): one warning."""
    import numpy as np

    from dtoc.hardware.orientation import file_orientation, orientation_name

    got = file_orientation(definitions)
    if got is None:
        if not np.allclose(want, np.eye(3)):
            return [
                f"the file records no orientation (DtocOrientation): if it was pre-compensated, it was for the "
                f"file's own axes (tra), not {orientation_name(want)}"
            ]
        return []
    if not np.allclose(got, want, atol=1e-6):
        return [
            f"the file was compiled for orientation {orientation_name(got)}, checked for {orientation_name(want)}: "
            "its pre-compensation does not hold at this orientation; re-optimize with --orientation"
        ]
    return []


def _print_check(res, max_rows: int, con) -> None:
    from rich.table import Table

    s = res.system
    con.print(
        f"{res.path}: limits from {res.limits_source}: {s.max_grad_mT_per_m:g} mT/m, {s.max_slew_T_per_m_per_s:g} T/m/s; "
        f"rules of {res.sources.get('format', 'the file')}; vendor conventions "
        + (f"from {res.sources['convention']}" if "convention" in res.sources else "not checked")
    )
    if res.ok:
        con.print("[green]OK[/green]: no violations")
        return
    t = Table(title=f"{len(res.violations)} violation(s)")
    for c in ("kind", "rule", "block", "axis", "value", "limit", "from", "detail"):
        t.add_column(c)
    for v in res.violations[:max_rows]:
        t.add_row(
            v.kind,
            v.rule,
            "" if v.block is None else str(v.block),
            v.axis or "",
            "" if v.value is None else f"{v.value:.5g} {v.unit}".strip(),
            "" if v.limit is None else f"{v.limit:.5g} {v.unit}".strip(),
            v.source,
            v.message,
        )
    con.print(t)
    if len(res.violations) > max_rows:
        con.print(f"... {len(res.violations) - max_rows} more (use --json for all)")
    con.print("[red]FAILED[/red]: " + res.summary())


def diff_cmd(
    a: Path = typer.Argument(..., help="first .seq"),
    b: Path = typer.Argument(..., help="second .seq"),
    rtol: float = typer.Option(1e-6, "--rtol", help="relative tolerance"),
    atol: float = typer.Option(1e-9, "--atol", help="absolute tolerance (mT/m, s, rad, Hz)"),
    json_out: str | None = json_option("the differences"),
    force: bool = typer.Option(False, "--force", help="overwrite an existing --json file"),
):
    """Semantic comparison of two .seq files; exit 0 same, 1 different.

    Numbers match when |a - b| <= atol + rtol * |b| (gradients: rtol x the largest |g| of the axis);
    atol is in each quantity's own unit (mT/m, s, rad, Hz).
    """
    import math

    from dtoc.errors import InputError
    from dtoc.seq.diff import diff_files

    for name, v in (("--rtol", rtol), ("--atol", atol)):
        if not (math.isfinite(v) and v >= 0):
            raise InputError(f"{name} must be a finite number >= 0, got {v}")

    from dtoc.util.atomic import check_outputs

    check_outputs({"--json": json_out}, {"A": a, "B": b}, force)
    res = diff_files(a, b, rtol=rtol, atol=atol)
    outp = Output(json_out)
    outp.write_json(strict_json(res.to_dict()), force)
    from rich.table import Table

    con = outp.console()
    if res.same:
        con.print(f"[green]same[/green] within rtol {rtol:g}, atol {atol:g}")
    else:
        shown = len(res.differences)
        total = res.n_differences
        t = Table(title=f"{total} difference(s)" + (f", first {shown} listed" if total > shown else ""))
        for c in ("what", "where", "A", "B"):
            t.add_column(c)
        for d in res.differences:
            t.add_row(d["what"], d["where"], str(d["a"]), str(d["b"]))
        con.print(t)
    if not res.same:
        raise typer.Exit(1)


def register(app: typer.Typer) -> None:
    """Add this stage's commands to app."""
    app.command("build")(build_cmd)
    app.command("check")(check_cmd)
    app.command("diff")(diff_cmd)
