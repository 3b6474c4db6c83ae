"""Typed base-sequence specs (pydantic v2), loaded from YAML.

A spec is a small, validated description of a base sequence; :mod:`dtoc.seq.build` turns it into a
pypulseq ``Sequence``.  Spec files are user-facing text, so their fields use the units people type
(ms, us, mm, deg), always spelled out in the field name; they are converted to SI at the builder's
boundary.  Unknown keys are errors (``extra='forbid'``).  The ``system`` block is the scanner the
sequence is designed for (its limits are recorded in the file's definitions; a spec whose ideal
waveforms exceed them still builds, with a warning, because it is an optimization target).

Kinds: ``gre`` (:class:`GreSpec`, the paper's 2D spoiled GRE) and ``epi`` (:class:`EpiSpec`,
single-shot 2D EPI).  Readout is on x, phase encoding on y, slice on z.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, TypeAdapter, ValidationError, model_validator

from dtoc.errors import InputError
from dtoc.seq.system import SystemSpec, format_validation_error


class BaseSpec(BaseModel):
    """Fields shared by every spec."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    name: str = Field(
        ...,
        min_length=1,
        max_length=128,
        pattern=r"^[A-Za-z0-9._+-]+$",
        description="written as the 'Name' definition: letters, digits, . _ + - (no spaces or control characters)",
    )
    fov_mm: float = Field(..., gt=0, le=1000, description="in-plane field of view (readout = phase), mm")
    matrix: int = Field(..., ge=2, le=1024, description="image matrix (readout = phase lines)")
    slice_thickness_mm: float = Field(5.0, gt=0, le=500, description="slice thickness, mm (FOV z in the definitions)")
    dwell_us: float = Field(..., gt=0, le=1e5, description="ADC dwell time, us")
    flip_angle_deg: float = Field(..., gt=0, le=180)
    system: SystemSpec = SystemSpec()

    @model_validator(mode="before")
    @classmethod
    def _merge_system(cls, data):
        """A partial ``system`` mapping overrides only the fields it names of the kind's default."""
        if isinstance(data, dict) and isinstance(data.get("system"), dict):
            default = cls.model_fields["system"].default.model_dump()
            data = {**data, "system": {**default, **data["system"]}}
        return data

    @model_validator(mode="after")
    def _even_matrix(self):
        if self.matrix % 2:
            raise ValueError(f"matrix must be even, got {self.matrix}")
        return self


class GreSpec(BaseSpec):
    """2D spoiled gradient echo as in the paper (Section 3.2, Figure 2B).

    Per TR: an RF period (non-selective block pulse, no gradients), a prewinder block (readout
    prewinder + phase encoding, ending at the readout amplitude), the ADC block (constant readout),
    and a spoiler block (readout spoiler + phase rewinder, then zero until the end of the TR).
    TE is counted from the RF centre to ADC sample ``matrix/2`` (where k = 0).
    """

    kind: Literal["gre"] = "gre"
    fov_mm: float = Field(32.0, gt=0, le=1000)
    matrix: int = Field(32, ge=2, le=1024)
    dwell_us: float = Field(100.0, gt=0, le=1e5)
    flip_angle_deg: float = Field(15.0, gt=0, le=180)
    tr_ms: float = Field(10.0, gt=0, le=10_000)
    te_ms: float = Field(3.15, gt=0, le=10_000, description="RF centre to the k = 0 ADC sample, ms")
    rf_period_ms: float = Field(2.0, gt=0, le=1000, description="RF block at the start of each TR (no gradients), ms")
    rf_duration_ms: float | None = Field(
        None, gt=0, le=1000, description="block pulse length; default centred in the RF period"
    )
    rf_spoiling_inc_deg: float = Field(117.0, ge=0, lt=360)
    repetitions: int = Field(32, ge=1, le=4096, description="number of TRs (phase-encode lines, sequential order)")
    spoiler_mT_per_m: float = Field(17.6, ge=0, le=5000, description="readout spoiler amplitude, mT/m")
    spoiler_duration_ms: float = Field(2.0, ge=0, le=1000, description="spoiler lobe duration from the ADC end, ms")
    rewind_phase: bool = Field(True, description="phase-encode rewinder in the spoiler block")
    system: SystemSpec = SystemSpec(
        max_grad_mT_per_m=50.0, max_slew_T_per_m_per_s=500.0, name="paper-gre-unconstrained"
    )


class EpiSpec(BaseSpec):
    """Single-shot 2D EPI (paper Section 3.3): slice-selective sinc excitation on z, prephasers,
    ``matrix`` readout lines of constant gradient with the ADC on their flat part (no ramp sampling),
    and between lines a transition block (readout reversal at the design slew rate, phase blip on y).
    """

    kind: Literal["epi"] = "epi"
    fov_mm: float = Field(250.0, gt=0, le=1000)
    matrix: int = Field(64, ge=2, le=1024)
    dwell_us: float = Field(10.0, gt=0, le=1e5)
    flip_angle_deg: float = Field(90.0, gt=0, le=180)
    echo_spacing_ms: float = Field(
        ..., gt=0, le=1000, description="time between the starts of consecutive readout lines, ms"
    )
    te_ms: float | None = Field(
        None, gt=0, le=10_000, description="RF centre to the k = 0 sample; None: shortest possible"
    )
    slice_thickness_mm: float = Field(3.0, gt=0, le=500)
    rf_duration_ms: float = Field(2.0, gt=0, le=1000, description="sinc excitation length, ms")
    rf_time_bw_product: float = Field(4.0, gt=0, le=100)
    system: SystemSpec = SystemSpec()


Spec = Annotated[GreSpec | EpiSpec, Field(discriminator="kind")]
_ADAPTER = TypeAdapter(Spec)


def parse_spec(data: dict, source: str = "<spec>") -> BaseSpec:
    """Validate a mapping as a spec (``kind`` selects the type)."""
    if not isinstance(data, dict):
        raise InputError(f"{source}: a spec must be a mapping with a 'kind' key")
    if "kind" not in data:
        raise InputError(f"{source}: missing key 'kind' (one of: gre, epi)")
    if data["kind"] not in ("gre", "epi"):
        raise InputError(f"{source}: kind {data['kind']!r} is not known (one of: gre, epi)")
    try:
        return _ADAPTER.validate_python(data)
    except ValidationError as e:
        errs = e.errors()
        # an unknown key is usually a typo of the missing one: name it first
        err = next((x for x in errs if x.get("type") == "extra_forbidden"), errs[0])
        loc = [str(x) for x in err.get("loc", ())]
        if loc and loc[0] in ("gre", "epi"):
            loc = loc[1:]
        where = ".".join(loc) or "<root>"
        msg = "unknown key" if err.get("type") == "extra_forbidden" else err.get("msg", "invalid")
        if err.get("type") == "value_error":
            msg = msg.removeprefix("Value error, ")
        more = f" (and {len(e.errors()) - 1} more)" if len(e.errors()) > 1 else ""
        return _raise(f"{source}: {where}: {msg}{more}")


def _raise(msg):
    raise InputError(msg)


def load_spec(path: str | Path) -> BaseSpec:
    """Read and validate a spec YAML file (one-line :class:`InputError` on any problem)."""
    import yaml

    p = Path(path)
    if p.is_dir():
        raise InputError(f"{p}: is a directory, expected a spec .yaml file")
    if not p.is_file():
        raise InputError(f"{p}: spec file not found")
    if p.suffix.lower() == ".seq":
        raise InputError(f"{p}: a Pulseq .seq file, not a spec: 'dtoc build' takes a spec .yaml (sequences/*.yaml)")
    try:
        data = yaml.safe_load(p.read_text(encoding="utf-8"))
    except UnicodeDecodeError:
        raise InputError(f"{p}: not a text file") from None
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f" at line {mark.line + 1}" if mark is not None else ""
        raise InputError(f"{p}: not valid YAML{where}") from None
    return parse_spec(data, str(p))


__all__ = ["BaseSpec", "GreSpec", "EpiSpec", "SystemSpec", "load_spec", "parse_spec"]


def load_system(path: str | Path) -> SystemSpec:
    """Read a :class:`SystemSpec` from YAML: a mapping of its fields (unknown keys are errors), a
    mapping ``{system: {...}}``, or a sequence spec (its ``system`` block)."""
    import yaml

    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: system spec not found")
    try:
        data = yaml.safe_load(p.read_text())
    except (yaml.YAMLError, UnicodeDecodeError) as e:
        raise InputError(f"{p}: not valid YAML ({type(e).__name__})") from None
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise InputError(f"{p}: expected a mapping of SystemSpec fields")
    if "kind" in data:  # a sequence spec: use the system it is designed for
        return parse_spec(data, str(p)).system
    if "system" in data and isinstance(data["system"], dict) and len(data) == 1:
        data = data["system"]
    try:
        return SystemSpec(**data)
    except ValidationError as e:
        raise InputError(f"{p}: {format_validation_error(e)}") from None
