"""The hardware twin: demanded gradients -> realized gradients and B0 (see docs/hardware.md).

Public API::

    HardwareModel, build_effect, load_model, save_model, model_from_girf, resolve_model, model_from_spec
    effects: Delay, Gain, Offset, ExpEddy, CrossEddy, B0Eddy, Girf, Lti, SlewLimit, EFFECTS
    GIRF files: GirfData, load_girf, save_girf
    measurements: Measurement, load_measurement, save_measurement, k_from_G, G_from_k
"""

from dtoc.hardware.effects import (
    EFFECTS,
    B0Eddy,
    CrossEddy,
    Delay,
    Effect,
    ExpEddy,
    Gain,
    Girf,
    Lti,
    Offset,
    SlewLimit,
)
from dtoc.hardware.girf_io import GirfData, load_girf, save_girf
from dtoc.hardware.measurement import G_from_k, Measurement, k_from_G, load_measurement, save_measurement
from dtoc.hardware.model import (
    HardwareModel,
    build_effect,
    load_model,
    model_from_girf,
    model_from_spec,
    resolve_model,
    save_model,
)

__all__ = [
    "EFFECTS",
    "B0Eddy",
    "CrossEddy",
    "Delay",
    "Effect",
    "ExpEddy",
    "Gain",
    "Girf",
    "Lti",
    "Offset",
    "SlewLimit",
    "GirfData",
    "load_girf",
    "save_girf",
    "Measurement",
    "load_measurement",
    "save_measurement",
    "k_from_G",
    "G_from_k",
    "HardwareModel",
    "build_effect",
    "load_model",
    "save_model",
    "model_from_girf",
    "model_from_spec",
    "resolve_model",
]
