"""Scanner limits and rasters (:class:`SystemSpec`), shared by the builder, the writer and the validator.

Defaults are those of a Siemens system with the paper's 7 T MAGNETOM Terra gradient limits
(72 mT/m, 180 T/m/s): gradient and block raster 10 us, RF raster 1 us, ADC raster 100 ns,
RF dead time 100 us, RF ring-down 30 us, ADC sample count a multiple of 4 and at most 8192 per ADC.
The ADC dead time defaults to 0 s as in Pulseq (MATLAB ``mr.opts``) and pypulseq; set it for a
scanner that needs it.  Units are in the field names.
"""

from __future__ import annotations

from pathlib import Path

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from dtoc.constants import GAMMA_HZ_PER_T
from dtoc.errors import InputError


class SystemSpec(BaseModel):
    """Hardware limits and timing rules of one scanner (all values > 0 unless stated)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    name: str = "siemens-7T-terra"
    #: upper bounds catch unit mistakes (uT/m or Hz/m given as mT/m); preclinical systems reach ~1-3 T/m
    max_grad_mT_per_m: float = Field(72.0, gt=0, le=5000.0, description="per-axis gradient amplitude limit, mT/m")
    max_slew_T_per_m_per_s: float = Field(180.0, gt=0, le=100000.0, description="per-axis slew-rate limit, T/m/s")
    max_grad_vector_mT_per_m: float | None = Field(
        None, gt=0, description="limit on |g| (vector norm over x, y, z), mT/m; None: sqrt(3) x per-axis limit"
    )
    max_slew_vector_T_per_m_per_s: float | None = Field(
        None, gt=0, description="limit on |dg/dt| (vector norm), T/m/s; None: sqrt(3) x per-axis limit"
    )
    grad_raster_s: float = Field(10e-6, gt=0)
    rf_raster_s: float = Field(1e-6, gt=0)
    adc_raster_s: float = Field(100e-9, gt=0)
    block_raster_s: float = Field(10e-6, gt=0)
    rf_dead_time_s: float = Field(100e-6, ge=0, description="minimum RF delay in its block, s")
    rf_ringdown_time_s: float = Field(30e-6, ge=0, description="minimum time from RF end to block end, s")
    adc_dead_time_s: float = Field(0.0, ge=0, description="minimum ADC delay and time from ADC end to block end, s")
    adc_samples_divisor: int = Field(4, ge=1, description="ADC sample count must be a multiple of this")
    adc_max_samples: int = Field(8192, ge=1, description="most samples in one ADC event")
    continuity_tol_hz_per_m: float = Field(1.0, gt=0, description="allowed gradient jump between blocks, Hz/m")
    required_definitions: tuple[str, ...] = (
        "GradientRasterTime",
        "RadiofrequencyRasterTime",
        "AdcRasterTime",
        "BlockDurationRaster",
    )

    @property
    def vector_grad_limit_mT_per_m(self) -> float:
        return self.max_grad_vector_mT_per_m or 3**0.5 * self.max_grad_mT_per_m

    @property
    def vector_slew_limit_T_per_m_per_s(self) -> float:
        return self.max_slew_vector_T_per_m_per_s or 3**0.5 * self.max_slew_T_per_m_per_s

    def to_pypulseq_opts(self, enforce_limits: bool = True):
        """pypulseq ``Opts`` with these rasters and dead times.

        With ``enforce_limits=False`` the amplitude/slew limits are set 1000x higher, so that pypulseq
        builds over-limit target waveforms; dtoc checks limits itself (:mod:`dtoc.seq.check`).
        """
        from dtoc.seq.pulseq import import_pypulseq

        pp = import_pypulseq()

        scale = 1.0 if enforce_limits else 1000.0
        return pp.Opts(
            max_grad=self.max_grad_mT_per_m * 1e-3 * GAMMA_HZ_PER_T * scale,
            grad_unit="Hz/m",
            max_slew=self.max_slew_T_per_m_per_s * GAMMA_HZ_PER_T * scale,
            slew_unit="Hz/m/s",
            grad_raster_time=self.grad_raster_s,
            rf_raster_time=self.rf_raster_s,
            adc_raster_time=self.adc_raster_s,
            block_duration_raster=self.block_raster_s,
            rf_dead_time=self.rf_dead_time_s,
            rf_ringdown_time=self.rf_ringdown_time_s,
            adc_dead_time=self.adc_dead_time_s,
            gamma=GAMMA_HZ_PER_T,
        )


def load_yaml_model(path, model: type[BaseModel], what: str, mapping_hint: str) -> BaseModel:
    """Read a YAML file into the pydantic ``model``; every problem is one :class:`InputError` line:
    ``<path>: <what> not found``, ``not a YAML <what>``, ``<mapping_hint>`` (not a mapping), or the first
    offending key (:func:`format_validation_error`)."""
    import yaml

    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: {what} not found")
    try:
        data = yaml.safe_load(p.read_text())
    except (yaml.YAMLError, UnicodeDecodeError) as e:
        raise InputError(f"{p}: not a YAML {what} ({type(e).__name__})") from None
    if not isinstance(data, dict):
        raise InputError(f"{p}: {mapping_hint}")
    try:
        return model(**data)
    except ValidationError as e:
        raise InputError(f"{p}: {format_validation_error(e)}") from None


def format_validation_error(e: ValidationError) -> str:
    """One line naming the first offending key of a pydantic error."""
    err = e.errors()[0]
    loc = ".".join(str(x) for x in err.get("loc", ())) or "<root>"
    msg = err.get("msg", "invalid")
    if msg.startswith("Value error, "):  # pydantic's prefix for a validator's own message
        msg = msg[len("Value error, ") :]
    if err.get("type") == "extra_forbidden":
        msg = "unknown key"
    more = f" (and {len(e.errors()) - 1} more)" if len(e.errors()) > 1 else ""
    return f"{loc}: {msg}{more}"
