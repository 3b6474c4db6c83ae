"""Scanner profile: one typed YAML file that describes a scanner as dtoc needs it (docs/scanner.md).

``--scanner PROFILE.yaml`` on every command that takes limits or a hardware model (optimize, simulate,
predict, check, identify); an explicit option (``--gmax``, ``--smax``, ``--system``, ``--girf``, ``--model``,
``--b0``) overrides the profile's value.  Paths in the profile are relative to the profile file; a GIRF may
be a dtoc ``.npz`` or a published MATLAB file, imported on the fly (the profile points at it, nothing is
copied).  Sections the checks need but the profile lacks (PNS, acoustics) are reported as "not checked",
never as passed.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from dtoc.errors import InputError
from dtoc.seq.pns import SafeModel

PerAxis = float | Annotated[list[float], Field(min_length=3, max_length=3)]


class Rasters(BaseModel):
    model_config = ConfigDict(extra="forbid")
    grad_s: float = Field(gt=0, lt=1e-3)
    rf_s: float = Field(gt=0, lt=1e-3)
    adc_s: float = Field(gt=0, lt=1e-3)
    block_s: float = Field(gt=0, lt=1e-3)


class DeadTimes(BaseModel):
    model_config = ConfigDict(extra="forbid")
    rf_dead_time_s: float = Field(ge=0, lt=1e-2)
    rf_ringdown_time_s: float = Field(ge=0, lt=1e-2)
    adc_dead_time_s: float = Field(ge=0, lt=1e-2)


class HardwareRef(BaseModel):
    """The hardware model: a GIRF file (``.npz``, or a published ``.mat`` imported as ``dtoc girf import``
    would) or a model JSON; exactly one."""

    model_config = ConfigDict(extra="forbid")
    girf: str | list[str] | None = None  # one file, or the per-axis files of one GIRF (GIRF_X/Y/Z.mat)
    girf_partial: bool = False  # the GIRF lacks an axis and may be imported with it ideal (girf import --partial)
    model: str | None = None

    @model_validator(mode="after")
    def _one(self) -> HardwareRef:
        if self.girf and self.model:
            raise ValueError("give girf or model, not both (a model JSON may hold a GIRF effect)")
        return self


class ScannerProfile(BaseModel):
    """A scanner as dtoc needs it.  Units in the names; per-axis values as one number or [x, y, z]."""

    model_config = ConfigDict(extra="forbid")
    name: str = Field(min_length=1, max_length=200)
    b0_T: float = Field(gt=0, le=21.1)
    gamma_hz_per_T: float = Field(42.577478e6, gt=0)
    gmax_mT_per_m: PerAxis
    smax_T_per_m_per_s: PerAxis
    rasters: Rasters
    dead_times: DeadTimes
    hardware: HardwareRef | None = None
    pns: SafeModel | None = None  # SAFE model parameters per physical axis (dtoc.seq.pns)
    acoustic_forbidden_bands_hz: list[Annotated[list[float], Field(min_length=2, max_length=2)]] = Field(
        default_factory=list
    )
    acoustic_max_power_fraction: float = Field(0.1, gt=0, le=1)  # dtoc's criterion (dtoc.seq.acoustics)
    #: ADC conventions (optional; dtoc check checks only those named): sample count a multiple of, most per ADC
    #: (segment, when the file declares MaxAdcSegmentLength)
    adc_samples_divisor: int | None = Field(None, ge=1)
    adc_max_samples: int | None = Field(None, ge=1)
    source: str | None = None  # where the numbers come from
    interpreter_version: str | None = Field(None, pattern=r"^\d+\.\d+(\.\d+)?$")  # Pulseq format it reads

    @field_validator("acoustic_forbidden_bands_hz")
    @classmethod
    def _bands(cls, v):
        for lo, hi in v:
            if not (0 <= lo < hi):
                raise ValueError("each forbidden band is [f_lo, f_hi] in Hz with 0 <= f_lo < f_hi")
        return v

    @field_validator("name")
    @classmethod
    def _printable(cls, v):
        from dtoc.util.validate import check_name

        try:
            check_name(v, "")
        except InputError as e:
            raise ValueError(str(e).strip()) from None
        return v

    @field_validator("source")
    @classmethod
    def _one_line(cls, v):
        if v is not None and (len(v) > 2000 or any(ord(c) < 32 or ord(c) == 127 for c in v)):
            raise ValueError("one line of at most 2000 characters, no control characters")
        return v

    @field_validator("gmax_mT_per_m", "smax_T_per_m_per_s")
    @classmethod
    def _positive(cls, v, info):
        from dtoc.util.validate import RANGES

        r = RANGES["gmax" if info.field_name == "gmax_mT_per_m" else "smax"]
        vals = v if isinstance(v, list) else [v]
        if not all(math.isfinite(x) and r.lo < x <= r.hi for x in vals):
            raise ValueError(f"limits must be within the accepted range {r.text()} (docs/cli.md)")
        return v

    # -------------------------------------------------------------------------------------------
    @property
    def gmax_min_mT_per_m(self) -> float:
        """The smallest per-axis amplitude limit (the optimizer's limits are one number for all axes)."""
        v = self.gmax_mT_per_m
        return float(min(v) if isinstance(v, list) else v)

    @property
    def smax_min_T_per_m_per_s(self) -> float:
        v = self.smax_T_per_m_per_s
        return float(min(v) if isinstance(v, list) else v)

    def not_checked(self) -> list[str]:
        """The pre-upload checks this profile cannot support (said as "not checked", never as passed)."""
        out = []
        if self.pns is None:
            out.append("PNS: not checked (the profile has no SAFE model parameters)")
        if not self.acoustic_forbidden_bands_hz:
            out.append("acoustic bands: not checked (the profile lists no forbidden bands)")
        if self.adc_samples_divisor is None or self.adc_max_samples is None:
            out.append(
                "ADC sample count and segmenting: not checked (the profile names no adc_samples_divisor / "
                "adc_max_samples)"
            )
        return out

    def safety_checks(self, rotation=None):
        """The profile's PNS and acoustic checks (:class:`dtoc.seq.check.SafetyChecks`) at orientation ``rotation``."""
        from dtoc.seq.check import SafetyChecks

        return SafetyChecks(
            pns=self.pns,
            acoustic_bands_hz=tuple(tuple(b) for b in self.acoustic_forbidden_bands_hz),
            acoustic_max_power_fraction=self.acoustic_max_power_fraction,
            rotation=rotation,
        )

    def system_spec(self):
        """The :class:`dtoc.seq.system.SystemSpec` of ``dtoc check`` (limits, rasters, dead times)."""
        from dtoc.seq.system import SystemSpec

        return SystemSpec(
            name=self.name,
            max_grad_mT_per_m=self.gmax_min_mT_per_m,
            max_slew_T_per_m_per_s=self.smax_min_T_per_m_per_s,
            grad_raster_s=self.rasters.grad_s,
            rf_raster_s=self.rasters.rf_s,
            adc_raster_s=self.rasters.adc_s,
            block_raster_s=self.rasters.block_s,
            rf_dead_time_s=self.dead_times.rf_dead_time_s,
            rf_ringdown_time_s=self.dead_times.rf_ringdown_time_s,
            adc_dead_time_s=self.dead_times.adc_dead_time_s,
            # not named: nothing to check against (1 divides every count; no count reaches 2^31)
            adc_samples_divisor=self.adc_samples_divisor or 1,
            adc_max_samples=self.adc_max_samples or 2**31,
        )


class LoadedProfile:
    """A validated profile and the folder its relative paths start from."""

    def __init__(self, profile: ScannerProfile, path: Path) -> None:
        self.profile = profile
        self.path = path
        self._hw: object = None
        self._hw_loaded = False

    def _resolve(self, p: str) -> Path:
        q = Path(os.path.expanduser(p))
        return q if q.is_absolute() else (self.path.parent / q)

    def hardware_files(self) -> tuple[list[Path] | None, Path | None]:
        """(girf files, model) paths of the profile (None where absent)."""
        h = self.profile.hardware
        if h is None:
            return None, None
        g = None if not h.girf else [self._resolve(x) for x in ([h.girf] if isinstance(h.girf, str) else h.girf)]
        return g, (self._resolve(h.model) if h.model else None)

    def hardware_model(self):
        """The profile's :class:`dtoc.hardware.model.HardwareModel` (None when it declares none); loaded and
        validated once (a missing, NaN, pickled or non-GIRF file is one InputError line)."""
        if not self._hw_loaded:
            self._hw = self._load_hardware()
            self._hw_loaded = True
        return self._hw

    def _load_hardware(self):
        girf, model = self.hardware_files()
        if girf is None and model is None:
            return None
        where = f"{self.path}: hardware"
        for f in girf or []:
            if not f.exists():
                raise InputError(f"{where}: GIRF file {f} not found (paths are relative to the profile)")
        if model is not None and not model.exists():
            raise InputError(f"{where}: model file {model} not found (paths are relative to the profile)")
        from dtoc.hardware.model import HardwareModel, girf_effect, load_model, model_from_girf
        from dtoc.util.validate import check_npz_archive

        for f in [*(girf or []), *([model] if model is not None else [])]:
            if not f.is_file():
                raise InputError(f"{where}: {f} is not a regular file")
            if f.suffix.lower() == ".npz":
                check_npz_archive(f, "--scanner GIRF")
        if model is not None:
            return load_model(model)
        if not girf:
            raise InputError(f"{where}: names no GIRF or model file")
        if len(girf) == 1 and girf[0].suffix.lower() == ".npz":
            return model_from_girf(girf[0])
        from dtoc.hardware.girf_import import import_girf

        h = self.profile.hardware
        gd = import_girf(girf, allow_partial=bool(h and h.girf_partial))
        return HardwareModel([girf_effect(gd)], description=f"{self.profile.name}: {', '.join(f.name for f in girf)}")

    def hardware_label(self) -> str | None:
        """What the reports name as the model the profile applied: ``--scanner NAME: FILE(S)`` (None: none)."""
        girf, model = self.hardware_files()
        files = [*(girf or []), *([model] if model is not None else [])]
        if not files:
            return None
        return f"--scanner {self.profile.name}: {', '.join(str(f) for f in files)}"


def load_profile(path: str | os.PathLike) -> LoadedProfile:
    """Read and validate a scanner profile YAML (one-line InputError naming the key on any problem)."""
    from dtoc.seq.system import load_yaml_model

    prof = load_yaml_model(
        path, ScannerProfile, "scanner profile", "a scanner profile is a mapping (name, b0_T, gmax_mT_per_m, ...)"
    )
    if not isinstance(prof, ScannerProfile):
        raise InputError(f"{path}: not a scanner profile")
    return LoadedProfile(prof, Path(path))


def profile_hardware(prof: LoadedProfile | None, girf, model):
    """The profile's hardware model when neither ``--girf`` nor ``--model`` is given (None otherwise, or for no
    profile or a profile without one): explicit options override the profile."""
    if girf is not None or model is not None or prof is None:
        return None
    return prof.hardware_model()


def input_files(path: str | os.PathLike | None) -> dict[str, Path]:
    """{option label: path} of the profile and the hardware files it names: inputs that no output may overwrite
    (and that a batch job's key hashes).  Empty for no profile."""
    if path is None:
        return {}
    out: dict[str, Path] = {"--scanner": Path(path)}
    girfs, model = load_profile(path).hardware_files()
    for i, g in enumerate(girfs or []):
        out[f"--scanner GIRF[{i}]"] = g
    if model is not None:
        out["--scanner model"] = model
    return out
