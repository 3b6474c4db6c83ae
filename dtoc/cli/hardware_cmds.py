"""CLI commands of the hardware twin: ``girf import``, ``girf fit``, ``girf show``, ``predict``.

Thin layer: parse options -> call :mod:`dtoc.hardware` / :mod:`dtoc.identify.girf_fit` -> print a table on
stderr (rich) or JSON on stdout (``--json``).
"""

from __future__ import annotations

from pathlib import Path

import typer

from dtoc.cli.output import Output, json_option, note, sequence_notes
from dtoc.cli.scanner import ORIENTATION_HELP, reference_option, rf_use_option, scanner_option
from dtoc.util.jsonout import strict_json

girf_app = typer.Typer(
    help="GIRF files: import published ones, fit from measurements, show figures.", no_args_is_help=True
)


def _finite(name: str, v: float | None, positive: bool = False) -> None:
    """Reject NaN/inf (and <= 0 when ``positive``) option values with one line."""
    import math

    from dtoc.errors import InputError

    if v is None:
        return
    if not math.isfinite(v) or (positive and v <= 0):
        raise InputError(f"{name} must be a finite number{' > 0' if positive else ''}, got {v}")


def _check_device(device: str) -> None:
    import torch

    from dtoc.errors import InputError

    try:
        dev = torch.device(device)
    except (RuntimeError, ValueError):
        raise InputError(f"--device {device!r} is not a torch device (use cpu or cuda)") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise InputError(f"--device {device}: CUDA is not available on this machine")
    if dev.type not in ("cpu", "cuda"):
        raise InputError(f"--device {device!r}: only cpu and cuda are supported")


def _fmt(v, scale=1.0, digits=4):
    if v is None:
        return "-"
    return f"{v * scale:.{digits}g}"


def _summary_table(rows, title):
    from rich.table import Table

    t = Table(title=title)
    for c in ("term", "DC gain", "-3 dB BW (kHz)", "group delay (us)", "peak |H|", "at (kHz)"):
        t.add_column(c, justify="right")
    for r in rows:
        t.add_row(
            r["term"],
            _fmt(r["dc_gain"]),
            _fmt(r["bandwidth_3db_hz"], 1e-3),
            _fmt(r["group_delay_s"], 1e6, 3),
            _fmt(r["peak_gain"]),
            _fmt(r["peak_hz"], 1e-3),
        )
    return t


def _emit_girf(gd, out: Path, force: bool, json_out: str | None):
    from dtoc.errors import InputError
    from dtoc.hardware.girf_analysis import girf_summary
    from dtoc.hardware.girf_io import save_girf, validate_girf_arrays
    from dtoc.util.atomic import outputs_together

    try:  # what is written must load back with dtoc's own loader
        validate_girf_arrays(gd.arrays(), f"{out}")
    except InputError as e:
        raise InputError(f"the result would not load back, nothing written: {e}") from None
    rows = girf_summary(gd)
    outp = Output(json_out)
    with outputs_together():
        p = save_girf(gd, out, force=force)
        outp.write_json(strict_json({"output": str(p), "notes": gd.notes, "terms": rows}), force)
    outp.console().print(_summary_table(rows, f"{p}"))
    for n in gd.notes:
        note(f"note: {n}")
    note(f"wrote {p}")


@girf_app.command("import")
def import_cmd(
    files: list[Path] = typer.Argument(..., help="published GIRF file(s): one .mat, or the per-axis X/Y/Z .mat files"),
    out: Path = typer.Option(..., "-o", "--out", help="output GIRF .npz (contract format)"),
    b0: bool = typer.Option(
        False, "--b0", help="also import the B0 (zeroth-order) term (unit undocumented in the published files)"
    ),
    shift_us: float = typer.Option(0.0, "--shift-us", help="add a pure delay to every term, us (positive = later)"),
    as_published: bool = typer.Option(
        False, "--as-published", help="keep a GMTF's declared ADC/gradient convention shift (default: undo it)"
    ),
    partial: bool = typer.Option(
        False, "--partial", help="accept a GIRF that lacks an axis, giving it an ideal response (refused otherwise)"
    ),
    force: bool = typer.Option(False, "--force", help="overwrite an existing output"),
    json_out: str | None = json_option("the figures"),
):
    """Convert a published GIRF (MATLAB v5 or v7.3) into the dtoc GIRF .npz (conventions: docs/hardware.md).

    Reads per-term kernels h<in><out> + t (s), a GMTF struct (freq in Hz) or GIRFReco-style per-axis
    GIRF_X/Y/Z.mat (freq in kHz); prints DC gain, -3 dB bandwidth (kHz) and group delay (us) per term.
    """
    from dtoc.hardware.girf_import import import_girf
    from dtoc.util.atomic import check_outputs

    _finite("--shift-us", shift_us)
    check_outputs({"-o": out, "--json": json_out}, {f"FILES[{i}]": p for i, p in enumerate(files)}, force)
    gd = import_girf(files, include_b0=b0, shift_s=shift_us * 1e-6, as_published=as_published, allow_partial=partial)
    _emit_girf(gd, out, force, json_out)


@girf_app.command("fit")
def fit_cmd(
    measured: Path = typer.Argument(..., help="measurement .npz (g and G or k, optional b0)"),
    out: Path = typer.Option(..., "-o", "--out", help="output GIRF .npz"),
    reg: float = typer.Option(
        1e-6, "--reg", help="Tikhonov weight relative to the peak input power (dimensionless, > 0)"
    ),
    fmax_khz: float | None = typer.Option(
        None, "--fmax-khz", help="frequency window: taper to zero at this frequency, kHz"
    ),
    tmin_ms: float | None = typer.Option(
        None,
        "--tmin-ms",
        help="time window start: taps kept from this time after the impulse, ms (give with --tmax-ms)",
    ),
    tmax_ms: float | None = typer.Option(
        None, "--tmax-ms", help="time window end: taps kept up to this time after the impulse, ms"
    ),
    no_b0: bool = typer.Option(False, "--no-b0", help="do not fit the B0 row even when b0 was measured"),
    force: bool = typer.Option(False, "--force", help="overwrite an existing output"),
    json_out: str | None = json_option("the figures"),
):
    """Estimate a 3x3 GIRF (+ B0 row) from measured input/output pairs by regularised least squares.

    Input: measurement .npz with dt (s), g and G (mT/m, (M, 3, N)) or k (rad/m), optional b0 (uT).
    Output: time-domain GIRF .npz on the measurement's dt; the notes say up to which frequency the
    inputs support the fit.
    """
    from dtoc.errors import InputError
    from dtoc.hardware.measurement import load_measurement
    from dtoc.identify.girf_fit import fit_girf
    from dtoc.util.atomic import check_outputs

    _finite("--reg", reg, positive=True)
    _finite("--fmax-khz", fmax_khz, positive=True)
    _finite("--tmin-ms", tmin_ms)
    _finite("--tmax-ms", tmax_ms)
    check_outputs({"-o": out, "--json": json_out}, {"measurement": measured}, force)
    m = load_measurement(measured)
    tw = None
    if tmin_ms is not None or tmax_ms is not None:
        if tmin_ms is None or tmax_ms is None:
            raise InputError("give both --tmin-ms and --tmax-ms")
        tw = (tmin_ms * 1e-3, tmax_ms * 1e-3)
    if fmax_khz is not None and fmax_khz <= 0:
        raise InputError("--fmax-khz must be > 0")
    gd = fit_girf(m, reg=reg, fmax_hz=None if fmax_khz is None else fmax_khz * 1e3, time_window_s=tw, fit_b0=not no_b0)
    _emit_girf(gd, out, force, json_out)


@girf_app.command("show")
def show_cmd(
    girf: Path = typer.Argument(..., help="GIRF .npz"),
    png: Path | None = typer.Option(
        None, "--png", help="write a PNG: self-term magnitude and phase, cross/B0 terms, impulse responses"
    ),
    force: bool = typer.Option(False, "--force", help="overwrite an existing PNG or --json file"),
    json_out: str | None = json_option("the figures"),
):
    """Print DC gain, -3 dB bandwidth and group delay per term; optionally plot the GIRF.

    DC gain is dimensionless (uT per mT/m for B0 terms); bandwidth in kHz and group delay (phase slope over
    0-4 kHz, positive = output lags) in us in the table; --json gives SI units (Hz, s).
    """
    from dtoc.hardware.girf_analysis import girf_summary
    from dtoc.hardware.girf_io import load_girf
    from dtoc.hardware.girf_plot import plot_girf
    from dtoc.util.atomic import check_outputs, outputs_together

    check_outputs({"--png": png, "--json": json_out}, {"GIRF": girf}, force)
    gd = load_girf(girf)
    rows = girf_summary(gd)
    outp = Output(json_out)
    with outputs_together():
        if png is not None:
            plot_girf(gd, png, title=girf.name, force=force)
        outp.write_json(strict_json({"file": str(girf), "notes": gd.notes, "terms": rows}), force)
    outp.console().print(_summary_table(rows, str(girf)))
    for n in gd.notes:
        note(f"note: {n}")
    if png is not None:
        note(f"wrote {png}")


def predict_cmd(
    seq: Path = typer.Argument(..., help="base sequence: .seq file or spec .yaml"),
    girf: Path | None = typer.Option(None, "--girf", help="GIRF .npz (shortcut for a one-effect model)"),
    model: Path | None = typer.Option(None, "--model", help="hardware model JSON (effects chain, docs/hardware.md)"),
    json_out: str | None = json_option("the figures"),
    png: Path | None = typer.Option(
        None,
        "--png",
        help="write a PNG: demanded vs realized gradients (whole and zoomed), gradient error, k error in dk",
    ),
    force: bool = typer.Option(False, "--force", help="overwrite an existing PNG or --json file"),
    device: str = typer.Option("cpu", "--device", help="torch device (cpu, cuda)"),
    orientation: str | None = typer.Option(None, "--orientation", help=ORIENTATION_HELP),
    scanner: Path | None = scanner_option(),
    rf_use: str | None = rf_use_option(),
    reference: Path | None = reference_option(),
    quiet: bool = typer.Option(False, "-q", "--quiet", help="No progress on stderr."),
):
    """Realized vs demanded: gradient error, k error at ADC samples, B0 phase, EPI odd/even offsets.

    Per axis: max and RMS of realized - demanded gradient (mT/m); k-space error at the ADC samples
    (rad/m and in dk = 2 pi / FOV); peak B0 (uT) and accrued B0 phase at the ADC samples (rad); for EPI
    the mean k offset of odd and even readout lines and their difference (rad/m, dk).
    Without --girf/--model the hardware is ideal (all errors 0). With --reference BASE every error is
    against the base's demanded gradient and nominal k (a pre-compensated output at any orientation/scanner).
    """
    from dtoc.seq.load import load_sequence
    from dtoc.sim.predict import plot_prediction, predict

    _check_device(device)
    from dtoc.cli import scanner as sc
    from dtoc.util.atomic import check_outputs, outputs_together

    check_outputs(
        {"--png": png, "--json": json_out},
        {"SEQ": seq, "--girf": girf, "--model": model, "--reference": reference, **sc.input_paths(scanner)},
        force,
    )
    from dtoc.cli.progress import ProgressReporter

    rep = ProgressReporter("dtoc predict", quiet=quiet)
    prof = sc.load(scanner)
    m = sc.resolve(prof, girf, model)
    label = sc.model_label(prof, girf, model)
    from dtoc.hardware.orientation import RotatedChain, parse_orientation

    R = parse_orientation(orientation)
    if R is not None:
        m = RotatedChain(m, R)
    ir = load_sequence(seq, rf_use=sc.rf_use(rf_use))
    sequence_notes(ir)
    base, ref_rec = None, None
    if reference is not None:
        from dtoc.sim.reference import load_reference

        base, ref_rec = load_reference(ir, seq, reference)
    rep.step("realizing (hardware model, k at the ADC samples)")
    res = predict(ir, m, device=device, reference=base)
    if ref_rec is not None:
        note(ref_rec.pop("note"))
        res["reference"] = ref_rec
    outp = Output(json_out)
    with outputs_together():
        if png is not None:
            shown = "ideal hardware" if label == "ideal" else label
            plot_prediction(ir, res, png, title=f"{seq.name} with {shown}", force=force)
        res.pop("_arrays")
        res["sequence"] = str(seq)
        res["model"] = label
        outp.write_json(strict_json(res), force)
    _print_prediction(res, outp.console())
    if png is not None:
        note(f"wrote {png}")


def _print_prediction(res, con):
    from rich.table import Table

    ref = res.get("reference")
    t = Table(title=f"{res['sequence']} with {res['model']}" + (f", against the base {ref['path']}" if ref else ""))
    for c in ("axis", "max |G-g| (mT/m)", "RMS (mT/m)", "max |k-k0| (rad/m)", "RMS (rad/m)", "max (dk)", "RMS (dk)"):
        t.add_column(c, justify="right")
    for a in ("x", "y", "z"):
        ge = res["grad_error"][a]
        ke = res["k_error"].get(a, {})
        t.add_row(
            a,
            _fmt(ge["max_mT_per_m"]),
            _fmt(ge["rms_mT_per_m"]),
            _fmt(ke.get("max_rad_per_m")),
            _fmt(ke.get("rms_rad_per_m")),
            _fmt(ke.get("max_dk")),
            _fmt(ke.get("rms_dk")),
        )
    con.print(t)
    con.print(f"max B0: {_fmt(res['b0_max_uT'])} uT; accrued B0 phase at ADC: max {_fmt(res['b0_phase_max_rad'])} rad")
    epi = res.get("epi")
    if epi:
        for key in ("readout", "phase"):
            e = epi.get(key)
            if e:
                con.print(
                    f"EPI {key} ({epi[key + '_axis']}) line k offsets: even {_fmt(e['even_mean_rad_per_m'])}, "
                    f"odd {_fmt(e['odd_mean_rad_per_m'])} rad/m; odd-even {_fmt(e['odd_minus_even_rad_per_m'])} rad/m "
                    f"= {_fmt(e['odd_minus_even_dk'])} dk"
                )


def register(app: typer.Typer) -> None:
    """Add this stage's commands to app."""
    app.add_typer(girf_app, name="girf")
    app.command("predict")(predict_cmd)
