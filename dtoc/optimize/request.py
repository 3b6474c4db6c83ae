"""One ``dtoc optimize`` as a typed request: the command line's options, validated once, and the library call
that resolves them (scanner profile, limits and where they came from, orientation, off-centre, config) and runs
:func:`dtoc.optimize.run.optimize_sequence`.

``dtoc optimize`` builds an :class:`OptimizeRequest` from its options and calls :func:`run_request`;
``dtoc batch`` builds one per job and calls the same function in its workers, so a batch job is exactly the
``dtoc optimize`` with the same options (docs/batch.md).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict

#: options of :class:`OptimizeRequest` that name input files
INPUT_FIELDS = ("base", "girf", "model", "config", "scanner", "resume")


class OptimizeRequest(BaseModel):
    """The options of ``dtoc optimize`` (``dtoc optimize --help`` describes each; units as there: mT/m, T/m/s, T).

    Types are checked here; ranges and consistency where the values are used (:class:`~dtoc.optimize.config.OptimizeConfig`, the
    loaders), with the same one-line errors as the command.  Paths are taken as given (relative to the working directory).  ``json_out`` '-' means the manifest is
    not written to a file (the command prints it on stdout).  ``trajectory`` None with ``no_trajectory``
    False writes the side-car beside ``out`` as ``<stem>.traj.npz``.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)
    base: Path
    out: Path
    girf: Path | None = None
    model: Path | None = None
    ideal: bool = False
    config: Path | None = None
    json_out: str | None = None
    png: Path | None = None
    force: bool = False
    resume: Path | None = None
    checkpoint: Path | None = None
    trajectory: Path | None = None
    no_trajectory: bool = False
    orientation: str | None = None
    scanner: Path | None = None
    offset: str | None = None
    method: Literal["dto", "adam-paper", "warmstart", "preemphasis"] | None = None
    gmax: float | None = None
    smax: float | None = None
    iters: int | None = None
    warm_iters: int | None = None
    k_tol: float | None = None
    lr: float | None = None
    w_image: float | None = None
    w_k: float | None = None
    w_rf: float | None = None
    augment: int | None = None
    no_discard: bool = False
    phantom: str | None = None
    b0: float | None = None
    seed: int | None = None
    threads: int | None = None
    device: str = "cpu"

    def trajectory_path(self) -> Path | None:
        """Where the side-car goes (None: not written)."""
        if self.no_trajectory:
            return None
        return self.trajectory if self.trajectory is not None else self.out.with_name(self.out.stem + ".traj.npz")

    def input_files(self) -> dict[str, Path]:
        """{label: path} of every file the run reads: the base, GIRF, model, config, checkpoint resumed from,
        the scanner profile and each file it names, a phantom ``.npz`` (labels as the options)."""
        from dtoc.hardware.profile import input_files

        out = {f"--{f}" if f != "base" else "BASE": getattr(self, f) for f in INPUT_FIELDS if f != "scanner"}
        out = {k: v for k, v in out.items() if v is not None}
        out.update(input_files(self.scanner))
        if self.phantom is not None and self.phantom.lower().endswith(".npz"):
            out["--phantom"] = Path(self.phantom)
        return out

    def manifest_path(self) -> str | None:
        """The manifest file (None: not written to a file)."""
        return None if self.json_out in (None, "-") else self.json_out


def run_request(
    req: OptimizeRequest, progress: Callable | None = None, notes: Callable[[str], None] | None = None
) -> dict:
    """Resolve the request and run the optimization; returns the manifest (docs/contracts.md).

    Bad input is a one-line :class:`~dtoc.errors.InputError` raised before any work or output; an interrupt
    (SIGINT/SIGTERM) during the optimization returns a manifest with ``interrupted: true`` after the
    best-so-far was written (docs/cli.md).  ``progress(stage, it, total, value)`` receives the iterations;
    ``notes(line)`` the reader's notes on the sequence (e.g. how an undefined RF use was taken) before the run.
    """
    from dtoc.errors import InputError
    from dtoc.hardware.orientation import parse_orientation
    from dtoc.hardware.profile import input_files, load_profile, profile_hardware
    from dtoc.optimize.config import load_config
    from dtoc.optimize.offcentre import parse_offset
    from dtoc.optimize.run import check_run_paths, optimize_sequence, require_hardware
    from dtoc.seq.load import load_sequence
    from dtoc.sim.comparison import check_device

    check_device(req.device)
    R = parse_orientation(req.orientation)
    r0 = parse_offset(req.offset)
    trajectory = req.trajectory_path()
    manifest_path = req.manifest_path()
    check_run_paths(
        req.base,
        req.out,
        manifest_path,
        req.png,
        req.force,
        req.girf,
        req.model,
        req.config,
        req.resume,
        req.checkpoint,
        trajectory,
        input_files(req.scanner),
    )
    prof = None if req.scanner is None else load_profile(req.scanner)
    hw = profile_hardware(prof, req.girf, req.model)
    if hw is None:
        require_hardware(req.girf, req.model, req.ideal)
    elif req.ideal:
        raise InputError("give --ideal or a hardware model (--girf / --model / the --scanner profile's), not both")
    gmax, smax, b0 = req.gmax, req.smax, req.b0
    limit_from = {}
    if prof is not None:
        p = prof.profile
        if gmax is None:
            gmax, limit_from["gmax_mT_per_m"] = p.gmax_min_mT_per_m, f"--scanner {p.name}"
        if smax is None:
            smax, limit_from["smax_T_per_m_per_s"] = p.smax_min_T_per_m_per_s, f"--scanner {p.name}"
        if b0 is None:
            b0 = p.b0_T
    if not req.base.exists():
        raise InputError(f"{req.base}: base sequence not found")
    ir = load_sequence(req.base)
    if notes is not None:
        for n in ir.meta.get("notes", []):
            notes(n)
    weights = {k: v for k, v in (("image", req.w_image), ("kspace", req.w_k), ("rf", req.w_rf)) if v is not None}
    overrides = {
        "method": req.method,
        "gmax_mT_per_m": gmax,
        "smax_T_per_m_per_s": smax,
        "iters": req.iters,
        "warm_iters": req.warm_iters,
        "k_tol_dk": req.k_tol,
        "lr": req.lr,
        "augment_rotations": req.augment,
        "seed": req.seed,
        "b0_T": b0,
        "threads": req.threads,
        "discard": False if req.no_discard else None,
        "weights": weights or None,
    }
    cfg = load_config(ir.kind, req.config, overrides)
    ir.meta.setdefault("spec_path", str(req.base) if req.base.suffix.lower() in (".yaml", ".yml") else None)
    res = optimize_sequence(
        ir,
        out=req.out,
        girf=req.girf,
        model=req.model,
        config=cfg,
        config_path=req.config,
        manifest_path=manifest_path,
        png_path=req.png,
        force=req.force,
        resume=req.resume,
        checkpoint_path=req.checkpoint,
        device=req.device,
        phantom=req.phantom,
        progress=progress,
        base_path=req.base,
        ideal=req.ideal,
        trajectory_path=trajectory,
        orientation=R,
        hardware=hw,
        limit_sources=limit_from or None,
        scanner_path=req.scanner,
        safety=None if prof is None else prof.profile.safety_checks(),
        offset_m=r0,
    )
    return res.manifest
