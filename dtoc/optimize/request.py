"""One ``dtoc optimize`` as a typed request: the command line's options, validated once, and the library call
that resolves them (scanner profile, limits and where they came from, orientation, off-centre, config) and runs
:func:`dtoc.optimize.run.optimize_sequence`.

``dtoc optimize`` builds an :class:`OptimizeRequest` from its options and calls :func:`run_request`;
``dtoc batch`` builds one per job and calls the same function in its workers, so a batch job is exactly the
``dtoc optimize`` with the same options (docs/batch.md).
"""

from __future__ import annotations

import os
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
    format_version: str | None = None
    rf_use: str | None = None  # RF use by [RF] event id, "ID=use,..." (dtoc.seq.rfuse)
    allow_worse: bool = False

    def validate_options(self) -> None:
        """Every option value against its accepted range (:data:`dtoc.util.validate.RANGES`, docs/cli.md), the
        phantom's size and the checkpoint rules: one InputError line before any file is read or any work."""
        from dtoc.util.validate import check_range

        for key, opt, v in (
            ("gmax", "--gmax", self.gmax),
            ("smax", "--smax", self.smax),
            ("b0", "--b0", self.b0),
            ("seed", "--seed", self.seed),
            ("weight", "--w-image", self.w_image),
            ("weight", "--w-k", self.w_k),
            ("weight", "--w-rf", self.w_rf),
            ("lr", "--lr", self.lr),
            ("iters", "--iters", self.iters),
            ("iters", "--warm-iters", self.warm_iters),
            ("k_tol", "--k-tol", self.k_tol),
            ("augment", "--augment", self.augment),
            ("threads", "--threads", self.threads),
        ):
            check_range(key, v, opt)
        if self.phantom is not None:
            from dtoc.sim.phantom import check_phantom_size

            check_phantom_size(self.phantom)

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
    from dtoc.hardware.profile import load_profile, profile_hardware
    from dtoc.optimize.config import load_config
    from dtoc.optimize.offcentre import parse_offset
    from dtoc.optimize.run import check_run_paths, optimize_sequence, require_hardware
    from dtoc.seq.load import load_sequence
    from dtoc.sim.comparison import check_device

    req.validate_options()
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
        {k: v for k, v in req.input_files().items() if k not in ("BASE", "--girf", "--model", "--config", "--resume")},
    )
    _check_checkpoint(req)
    _check_resume(req.resume)
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
    from dtoc.seq.rfuse import parse_rf_use_overrides

    ir = load_sequence(req.base, rf_use=parse_rf_use_overrides(req.rf_use))
    if notes is not None:
        for n in ir.meta.get("notes", []):
            notes(n)
    stale = [d.pop("DtocInterrupted", None) for d in (ir.definitions, getattr(ir.source, "definitions", None))
             if isinstance(d, dict)]  # fmt: skip
    if any(v is not None for v in stale) and notes is not None:  # the writer copies the source's definitions
        notes(f"{req.base} is an interrupted run's best-so-far (DtocInterrupted): the flag is not copied to the output")
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
    _check_config(cfg, req, ir, prof, notes)
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
        format_version=req.format_version or (None if prof is None else prof.profile.interpreter_version),
        notes=notes,
    )
    return res.manifest


def _check_checkpoint(req: OptimizeRequest) -> None:
    """``--checkpoint`` is an output like the others: an existing file is replaced only with ``--force`` (or
    when it is the checkpoint resumed from)."""
    from dtoc.errors import InputError

    ck = req.checkpoint
    if ck is None or req.force or not os.path.lexists(ck):
        return
    if req.resume is not None and os.path.realpath(req.resume) == os.path.realpath(ck):
        return
    raise InputError(f"{ck}: --checkpoint exists; pass --force to overwrite it (or --resume it)")


def _check_resume(resume: Path | None) -> None:
    """A checkpoint to resume from: a dtoc checkpoint archive (no pickles, sizes within memory) whose edges are
    all finite (a NaN would resume silently into a NaN waveform)."""
    if resume is None:
        return
    import numpy as np

    from dtoc.errors import InputError
    from dtoc.util.validate import check_npz_archive

    if not Path(resume).is_file():
        raise InputError(f"{resume}: --resume checkpoint not found (or not a regular file)")
    check_npz_archive(resume, "--resume")
    try:
        with np.load(resume, allow_pickle=False) as z:
            edges = np.asarray(z["edges_mT_per_m"], dtype=np.float64)
            it = int(z["it"])
    except Exception as e:  # noqa: BLE001 - any unreadable archive: one line
        raise InputError(f"{resume}: not a dtoc optimize checkpoint ({type(e).__name__})") from None
    if not np.isfinite(edges).all():
        raise InputError(f"{resume}: checkpoint 'edges_mT_per_m' holds NaN or infinity: not resumed")
    if not 0 <= it <= 10_000_000:
        raise InputError(f"{resume}: checkpoint iteration {it} out of range")


#: the base may need up to this factor above a limit before ``optimize`` refuses without ``--allow-worse``
WORSE_FACTOR = 10.0


def _check_config(cfg, req: OptimizeRequest, ir, prof, notes) -> None:
    """The resolved run (options, config file, the file's own limits) against the accepted ranges; the limits
    against what the base needs (refused without ``--allow-worse`` when no waveform within them can follow
    it); threads against the cores.  One InputError line, before any work."""
    from dtoc.errors import InputError
    from dtoc.optimize.limits import waveform_extremes
    from dtoc.optimize.run import limits_and_sources
    from dtoc.util.validate import check_range, cores

    src = f"{req.config} " if req.config is not None else ""
    for key, field, v in (
        ("seed", "seed", cfg.seed),
        ("iters", "iters", cfg.iters),
        ("iters", "warm_iters", cfg.warm_iters),
        ("augment", "augment_rotations", cfg.augment_rotations),
        ("dummies", "n_dummies", cfg.n_dummies),
        ("threads", "threads", cfg.threads),
        ("b0", "b0_T", cfg.b0_T),
        ("lr", "lr", cfg.lr),
        ("phantom_n", "phantom_size", cfg.phantom_size),
        *(("weight", f"weights.{k}", w) for k, w in cfg.weights.model_dump().items()),
    ):
        check_range(key, v, f"{src}config {field}")
    geo = getattr(ir, "geometry", None)
    name, _, size = str(req.phantom or "brain").partition(":")
    if cfg.weights.image > 0 and geo is not None and name in ("brain", "brain-noscalp"):
        from dtoc.util.cost import check_simulation_cost, fine_per_repetition

        n = cfg.phantom_size or (int(size) if size.isdigit() else None)
        vox = n * n if n else int(geo.matrix_xy[0]) * int(geo.matrix_xy[1])
        check_simulation_cost(
            f"{req.base}: optimize", vox, ir.n_adc_samples, n_phantoms=1 + cfg.augment_rotations,
            n_dummies=cfg.n_dummies, fine_per_rep=fine_per_repetition(ir), dummies_option="n_dummies in --config",
        )  # fmt: skip
    limits, sources = limits_and_sources(ir, cfg)
    for key, v, name in (
        ("gmax", limits.gmax_mT_per_m, "gmax_mT_per_m"),
        ("smax", limits.smax_T_per_m_per_s, "smax_T_per_m_per_s"),
    ):
        where = sources.get(name, key)
        label = (
            f"{req.base}: {where}"
            if where.startswith("file")
            else (where if where.startswith("--") else f"{where} {key}")
        )
        check_range(key, v, label)
    n = cores()
    if cfg.threads > n:
        raise InputError(
            f"--threads {cfg.threads}: more than the {n} cores this process may use (oversubscribed threads spin-wait: "
            "many times slower); give at most {n}".replace("{n}", str(n))
        )
    if cfg.threads > 1 and notes is not None:
        try:
            load = os.getloadavg()[0]
        except OSError:
            load = 0.0
        if load + cfg.threads > n + 0.5:
            notes(
                f"--threads {cfg.threads} on {n} cores with load {load:.1f}: the threads will compete with other "
                "processes (spin-waiting can make the run many times slower; --threads 1 is safer here)"
            )
    if req.allow_worse or not ir.n_adc_samples:
        return
    ext = waveform_extremes(ir.grad_mT_per_m, ir.dt_fine_s)
    g, sl = max(ext["gmax_mT_per_m"]), max(ext["smax_T_per_m_per_s"])
    for need, lim, unit, opt in (
        (g, limits.gmax_mT_per_m, "mT/m", "gmax"),
        (sl, limits.smax_T_per_m_per_s, "T/m/s", "smax"),
    ):
        if need > WORSE_FACTOR * lim:
            raise InputError(
                f"{opt} {lim:g} {unit}: the base sequence needs {need:.4g} {unit} ({need / lim:.3g}x): no waveform "
                f"within the limits can follow its k-space (the output would be worse than the base); refused "
                f"before work; pass --allow-worse to optimize anyway"
            )
