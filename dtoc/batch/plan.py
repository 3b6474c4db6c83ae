"""A batch plan (docs/batch.md): base sequences x hardware (scanner profiles, GIRFs, models) x orientations x
option sets, as their product or as explicit rows; each job one ``dtoc optimize`` (:class:`OptimizeRequest`).

A job's key is the SHA-256 of everything its outputs depend on: the bytes of every input file (sequence,
GIRF / model, scanner profile and the files it names, config, phantom), the options, the orientation as a
rotation matrix, and the versions of Python, dtoc, torch, numpy, scipy, pypulseq and pydantic.  Paths and names are not in the key:
moving a library or renaming a job keeps its results; changing one GIRF changes exactly the keys of its jobs.
"""

from __future__ import annotations

import hashlib
import json
import re
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from dtoc.errors import InputError
from dtoc.optimize.request import INPUT_FIELDS, OptimizeRequest

#: the options a plan's option set may give (the rest is set by the plan: files, hardware, orientation, outputs)
OPTION_KEYS = (
    "method",
    "iters",
    "warm_iters",
    "k_tol",
    "lr",
    "w_image",
    "w_k",
    "w_rf",
    "augment",
    "no_discard",
    "phantom",
    "seed",
    "threads",
    "config",
    "offset",
    "device",
    "allow_worse",
)
#: the file names of a job's outputs inside its folder (as ``dtoc optimize -o optimized.seq --json
#: manifest.json --png report.png`` run in that folder writes them)
OUT_SEQ, OUT_MANIFEST, OUT_PNG = "optimized.seq", "manifest.json", "report.png"

_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.+-]*$")


class Hardware(BaseModel):
    """One scanner: exactly one of ``girf``, ``model``, ``scanner`` (profile) or ``ideal``, and the limits
    (mT/m, T/m/s; from the profile when it gives them) and the field strength (T)."""

    model_config = ConfigDict(extra="forbid")
    girf: str | None = None
    model: str | None = None
    scanner: str | None = None
    ideal: bool = False
    gmax: float | None = Field(None, gt=0)
    smax: float | None = Field(None, gt=0)
    b0: float | None = Field(None, gt=0)

    @model_validator(mode="after")
    def _one_source(self) -> Hardware:
        given = [k for k in ("girf", "model", "scanner") if getattr(self, k)] + (["ideal"] if self.ideal else [])
        if len(given) != 1:
            raise ValueError(f"give exactly one of girf, model, scanner, ideal (got {', '.join(given) or 'none'})")
        return self


class Row(BaseModel):
    """One explicit job: names of a sequence, a hardware entry, an option set; an orientation."""

    model_config = ConfigDict(extra="forbid")
    sequence: str
    hardware: str
    orientation: str | None = None
    options: str = "default"


def _as_in_file() -> list[str | None]:
    return [None]


def _default_options() -> dict[str, dict[str, Any]]:
    return {"default": {}}


class BatchPlan(BaseModel):
    """The plan file (YAML).  Paths are relative to the plan file's folder."""

    model_config = ConfigDict(extra="forbid")
    sequences: dict[str, str]
    hardware: dict[str, Hardware]
    orientations: list[str | None] = Field(default_factory=_as_in_file)
    options: dict[str, dict[str, Any]] = Field(default_factory=_default_options)
    rows: list[Row] | None = None
    png: bool = True
    trajectory: bool = True

    @field_validator("sequences", mode="before")
    @classmethod
    def _seq_list(cls, v):
        if isinstance(v, list):  # a list of paths: named by their stems
            names = [Path(str(p)).stem for p in v]
            if len(set(names)) != len(names):
                raise ValueError("two sequences share a file stem: name them (sequences: {name: path})")
            return dict(zip(names, v))
        return v

    @field_validator("sequences", "hardware", "options")
    @classmethod
    def _names(cls, v: dict) -> dict:
        if not v:
            raise ValueError("must not be empty")
        for name in v:
            if not _NAME.match(str(name)):
                raise ValueError(f"name {name!r}: letters, digits and _ . + - only (it names the job's folder)")
        return v

    @field_validator("options")
    @classmethod
    def _option_keys(cls, v: dict) -> dict:
        for name, opts in v.items():
            bad = sorted(set(opts or {}) - set(OPTION_KEYS))
            if bad:
                raise ValueError(
                    f"option set {name!r}: {', '.join(bad)} not allowed here (allowed: {', '.join(OPTION_KEYS)})"
                )
        return v


class Job(BaseModel):
    """One expanded job: its name (folder link), the request run in the job's folder, and its cache key."""

    model_config = ConfigDict(frozen=True)
    name: str
    request: OptimizeRequest
    key: str


def load_plan(path: str | Path) -> BatchPlan:
    """Read and validate a plan YAML (one-line InputError naming the key on any problem)."""
    from dtoc.seq.system import load_yaml_model

    plan = load_yaml_model(
        path,
        BatchPlan,
        "batch plan",
        "a batch plan is a mapping with sequences, hardware, orientations, options (docs/batch.md)",
    )
    assert isinstance(plan, BatchPlan)
    return plan


def _orient_label(o: str | None) -> str:
    if o is None:
        return "file"
    s = o.strip().lower()
    if re.fullmatch(r"[a-z]+", s):
        return s
    return "R" + hashlib.sha256(s.encode()).hexdigest()[:8]


def expand(plan: BatchPlan, root: Path) -> list[Job]:
    """The jobs of ``plan`` (paths resolved against ``root``), in plan order; each checked as ``dtoc optimize``
    would check its options before any job runs."""
    from dtoc.util.validate import check_range

    rows = plan.rows
    n = (
        len(rows)
        if rows is not None
        else (len(plan.sequences) * len(plan.hardware) * len(plan.orientations) * len(plan.options))
    )
    check_range("jobs", n, "the plan's job count")
    if rows is None:
        rows = [
            Row(sequence=s, hardware=h, orientation=o, options=op)
            for s in plan.sequences
            for h in plan.hardware
            for o in plan.orientations
            for op in plan.options
        ]
    jobs, names = [], set()
    for i, r in enumerate(rows):
        for what, table, name in (
            ("sequence", plan.sequences, r.sequence),
            ("hardware", plan.hardware, r.hardware),
            ("options", plan.options, r.options),
        ):
            if name not in table:
                raise InputError(f"rows[{i}]: {what} {name!r} is not defined in the plan's {what}")
        name = f"{r.sequence}__{r.hardware}__{_orient_label(r.orientation)}__{r.options}"
        if name in names:
            raise InputError(f"job {name} appears twice in the plan")
        names.add(name)
        jobs.append(_job(plan, root, name, r))
    return jobs


def _abs(root: Path, p: str | None) -> Path | None:
    if p is None:
        return None
    q = Path(p).expanduser()
    return (q if q.is_absolute() else root / q).resolve()


def _job(plan: BatchPlan, root: Path, name: str, r: Row) -> Job:
    hw = plan.hardware[r.hardware]
    opts = dict(plan.options[r.options] or {})
    if opts.get("config") is not None:
        opts["config"] = _abs(root, opts["config"])
    ph = opts.get("phantom")
    if isinstance(ph, str) and ph.lower().endswith(".npz"):
        opts["phantom"] = str(_abs(root, ph))
    try:
        req = OptimizeRequest(
            base=_abs(root, plan.sequences[r.sequence]),
            out=Path(OUT_SEQ),
            json_out=OUT_MANIFEST,
            png=Path(OUT_PNG) if plan.png else None,
            no_trajectory=not plan.trajectory,
            girf=_abs(root, hw.girf),
            model=_abs(root, hw.model),
            scanner=_abs(root, hw.scanner),
            ideal=hw.ideal,
            gmax=hw.gmax,
            smax=hw.smax,
            b0=hw.b0,
            orientation=r.orientation,
            **opts,
        )
    except ValidationError as e:
        err = e.errors()[0]
        raise InputError(f"job {name}: option {'.'.join(map(str, err['loc']))}: {err['msg']}") from None
    try:
        req.validate_options()
    except InputError as e:
        raise InputError(f"job {name}: {e}") from None
    for f in ("base", "girf", "model", "scanner", "config"):
        p = getattr(req, f)
        if p is not None and not p.is_file():
            raise InputError(f"job {name}: {f} {p} not found")
    return Job(name=name, request=req, key=job_key(req))


def job_key(req: OptimizeRequest) -> str:
    """SHA-256 (hex) of everything the job's outputs depend on (module docstring)."""
    from dtoc.hardware.orientation import parse_orientation
    from dtoc.util.atomic import sha256_file
    from dtoc.version import package_versions

    files = {label: sha256_file(p) for label, p in req.input_files().items()}
    R = parse_orientation(req.orientation)
    opts = req.model_dump(mode="json", exclude={*INPUT_FIELDS, "checkpoint", "force", "orientation"})
    if not opts.get("allow_worse"):
        opts.pop("allow_worse", None)  # keys of jobs that do not ask for it stay as before the option existed
    if "--phantom" in files:
        opts["phantom"] = "<file>"  # its bytes are in files
    record = {
        "versions": package_versions(),
        "files": files,
        "options": opts,
        "orientation_R": None if R is None else [[round(float(x), 12) for x in row] for row in R.tolist()],
    }
    return hashlib.sha256(json.dumps(record, sort_keys=True).encode()).hexdigest()
