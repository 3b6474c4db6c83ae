"""CLI commands of the `dtoc.sim` stage (registered by :mod:`dtoc.cli.main`): ``dtoc simulate``."""

from __future__ import annotations

from pathlib import Path

import typer

from dtoc.cli.output import Output, json_option, note, sequence_notes
from dtoc.cli.scanner import ORIENTATION_HELP, reference_option, rf_use_option, scanner_option
from dtoc.constants import DEFAULT_B0_T


def _round(x):
    """Floats to 10 significant digits (stable JSON across BLAS thread counts); recursive."""
    if isinstance(x, float):
        return float(f"{x:.10g}")
    if isinstance(x, dict):
        return {k: _round(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_round(v) for v in x]
    return x


def simulate_cmd(
    seq: Path = typer.Argument(..., help="Base sequence: .seq file or spec .yaml."),
    girf: Path | None = typer.Option(None, "--girf", help="GIRF .npz (hardware model = this GIRF)."),
    model: Path | None = typer.Option(None, "--model", help="Hardware model file (.json)."),
    phantom: str | None = typer.Option(
        None,
        "--phantom",
        help="Phantom .npz, or 'brain' / 'brain:N' / 'brain-noscalp[:N]' (built-in head; noscalp: without fat and skull; default: brain at the image matrix), 'brain3d[:N]' (3D head on a 3D-encoded sequence's grid, its default).",
    ),
    field_T: float | None = typer.Option(
        None,
        "--b0",
        "--field",
        help=f"Field strength of the built-in phantom's tissue values, T (default: the --scanner profile's, else {DEFAULT_B0_T:g}, as optimize; 3 and 7 tabulated).",
    ),
    b0_map: bool = typer.Option(False, "--b0-map", help="Built-in phantom: add its smooth B0 map."),
    b1_map: bool = typer.Option(False, "--b1-map", help="Built-in phantom: add its smooth B1 map."),
    dummies: int | None = typer.Option(
        None,
        "--dummies",
        min=0,
        help="Dummy repetitions before the sequence (steady state); default as optimize: 300 for a GRE (the paper's), 0 otherwise.",
    ),
    json_out: str | None = json_option("the metrics"),
    png_out: Path | None = typer.Option(
        None, "--png", help="Write the figure (ideal, realized, difference, k-space) here."
    ),
    device: str = typer.Option("cpu", "--device", help="cpu or cuda."),
    dtype: str = typer.Option("float64", "--dtype", help="float32 or float64."),
    force: bool = typer.Option(False, "--force", help="Overwrite existing outputs."),
    quiet: bool = typer.Option(False, "-q", "--quiet", help="No progress on stderr."),
    orientation: str | None = typer.Option(None, "--orientation", help=ORIENTATION_HELP),
    scanner: Path | None = scanner_option(),
    rf_use: str | None = rf_use_option(),
    reference: Path | None = reference_option(),
):
    """Simulate ideal versus realized images of SEQ on a phantom; NRMSE, EPI ghost ratio, k-space error.

    With --reference BASE the ideal image, nominal k and grid are the base's: a pre-compensated output
    played through the hardware model, measured against what its base intended.
    """
    from rich.table import Table

    from dtoc.sim.comparison import check_device, compare_ideal_realized, plot_comparison, torch_dtype
    from dtoc.sim.metrics import report_figures
    from dtoc.sim.phantom import check_phantom_matches, phantom_for
    from dtoc.util.atomic import atomic_write_bytes, check_outputs, outputs_together, sha256_file
    from dtoc.util.jsonout import strict_json
    from dtoc.util.validate import check_range
    from dtoc.version import __version__

    check_range("dummies", dummies, "--dummies")
    check_range("b0", field_T, "--b0")
    if phantom is not None:
        from dtoc.sim.phantom import check_phantom_size

        check_phantom_size(phantom)
    tdtype = torch_dtype(dtype)
    dev = check_device(device)
    phantom_file = phantom if phantom and phantom.endswith(".npz") else None
    from dtoc.cli import scanner as sc

    check_outputs(
        {"--png": png_out, "--json": json_out},
        {
            "SEQ": seq,
            "--girf": girf,
            "--model": model,
            "--phantom": phantom_file,
            "--reference": reference,
            **sc.input_paths(scanner),
        },
        force,
    )
    from dtoc.cli.progress import ProgressReporter
    from dtoc.seq.load import load_sequence

    rep = ProgressReporter("dtoc simulate", quiet=quiet)
    ir = load_sequence(seq, rf_use=sc.rf_use(rf_use))
    sequence_notes(ir)
    base, ref_rec = None, None
    if reference is not None:
        from dtoc.sim.reference import load_reference

        base, ref_rec = load_reference(ir, seq, reference)
        note(ref_rec.pop("note"))
    prof = sc.load(scanner)
    hw = sc.resolve(prof, girf, model)
    label = sc.model_label(prof, girf, model)
    if field_T is None:
        field_T = prof.profile.b0_T if prof is not None else DEFAULT_B0_T
    from dtoc.hardware.orientation import RotatedChain, parse_orientation

    R = parse_orientation(orientation)
    if R is not None:
        hw = RotatedChain(hw, R)
    if phantom is None and (ir if base is None else base).meta.get("grid3d") is not None:
        phantom = "brain3d"  # a 3D-encoded sequence images the built-in 3D head
    intent = ir if base is None else base  # the grid and phantom follow what the acquisition intends
    if not check_phantom_matches(intent, phantom):  # one line for a 2D phantom on a 3D file and the reverse
        intent.require_geometry(f"{reference or seq}: simulate")
    from dtoc.util.cost import check_simulation_cost, fine_per_repetition

    default_train = dummies is None
    if dummies is None:  # the same "before" as dtoc optimize (dtoc.constants.default_dummies)
        from dtoc.constants import default_dummies

        dummies = default_dummies(ir.kind)

    def cost(n_vox: int) -> None:  # the dummy train, then the ideal and the realized runs
        est, sec = check_simulation_cost(
            f"{seq}: simulate",
            n_vox,
            ir.n_adc_samples,
            n_runs=2,
            n_dummies=dummies,
            fine_per_rep=fine_per_repetition(ir),
        )
        if not quiet and sec > 30:
            note(f"note: {est}")

    n_vox = _planned_voxels(intent, phantom)
    if n_vox is not None:
        cost(n_vox)
    ph = phantom_for(intent, phantom, field_T=field_T, b0=b0_map, b1=b1_map)
    if n_vox is None:  # a phantom file (its header checked by its loader): its voxels are known once read
        cost(int(ph.pd.size))
    if default_train and dummies:
        note(f"note: {dummies} dummy repetitions before the sequence (steady state of a {ir.kind}, as optimize)")
    res = compare_ideal_realized(
        ir,
        ph,
        hw,
        n_dummies=dummies,
        dtype=tdtype,
        device=dev,
        step=lambda s: rep.step(f"simulating: {s}"),
        reference=base,
    )
    m = res.metrics
    report = {
        "dtoc_version": __version__,
        "sequence": {
            "path": str(seq),
            "sha256": sha256_file(seq),
            "kind": ir.kind,
            "n_adc_samples": m["n_adc_samples"],
            "matrix": m["matrix"],
        },
        "hardware": {
            "girf": str(girf) if girf else None,
            "model": str(model) if model else None,
            "applied": "ideal" if res.identity_hardware else label,
            "identity": res.identity_hardware,
        },
        "phantom": {
            "source": phantom or "brain",
            "shape": list(ph.shape),
            "fov_m": list(ph.fov_m),
            "field_T": field_T if not (phantom and phantom.endswith(".npz")) else None,
        },
        "simulation": {"dtype": dtype, "dummies": dummies},
        **({"reference": ref_rec} if ref_rec is not None else {}),
        **report_figures(
            {
                k: m[k]
                for k in (
                    "nrmse",
                    "ghost_ratio",
                    "ghost_ratio_ideal",
                    "kspace_rmse_rad_per_m",
                    "kspace_max_err_rad_per_m",
                    "kspace_max_err_dk",
                    "image_reason",
                )
                if k in m
            }
        ),
    }
    report = _round(report)
    text = strict_json(report)
    outp = Output(json_out)
    with outputs_together():
        if png_out is not None:
            atomic_write_bytes(png_out, plot_comparison(res, title=f"{Path(seq).name}: ideal vs realized"), force=force)
        outp.write_json(text, force)
    t = Table(title=f"dtoc simulate {Path(seq).name}")
    t.add_column("metric")
    t.add_column("value", justify="right")
    t.add_row("NRMSE", m["image_reason"] if m["nrmse"] is None else f"{100 * m['nrmse']:.4g} %")
    if m["ghost_ratio"] is not None:
        t.add_row("ghost ratio (ideal)", f"{100 * m['ghost_ratio']:.4g} % ({100 * m['ghost_ratio_ideal']:.3g} %)")
    t.add_row("k-space RMSE", f"{m['kspace_rmse_rad_per_m']:.4g} rad/m")
    if m["kspace_max_err_dk"] is not None:
        t.add_row("k-space max error", f"{m['kspace_max_err_dk']:.4g} dk")
    t.add_row("hardware", "ideal (identity)" if res.identity_hardware else label)
    if ref_rec is not None:
        t.add_row("against", f"the base {reference}")
    outp.console().print(t)
    if png_out is not None:
        note(f"wrote {png_out}")


def _planned_voxels(ir, phantom) -> int | None:
    """Voxels of the phantom a simulation of ``ir`` will build (the image matrix for the built-in head, N x N
    for brain:N), before it is built; None when unknown (a .npz: checked by its loader)."""
    spec = "brain" if phantom is None else str(phantom)
    name, _, size = spec.partition(":")
    if name not in ("brain", "brain-noscalp"):
        return None
    if size.isdigit():
        return int(size) ** 2
    geo = getattr(ir, "geometry", None)
    if geo is None:
        return None
    nx, ny = geo.matrix_xy
    return int(nx) * int(ny)


def register(app: typer.Typer) -> None:
    """Add this stage's commands to app."""
    app.command("simulate")(simulate_cmd)
