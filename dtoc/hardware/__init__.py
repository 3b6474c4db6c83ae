"""The hardware twin: demanded gradients -> realized gradients and B0 (see docs/hardware.md).

Public API::

    HardwareModel, build_effect, load_model, save_model, model_from_girf, resolve_model, model_from_spec
    effects: Delay, Gain, Offset, ExpEddy, CrossEddy, B0Eddy, Girf, Lti, SlewLimit, EFFECTS
    GIRF files: GirfData, load_girf, save_girf
    measurements: Measurement, load_measurement, save_measurement, k_from_G, G_from_k
"""

# Lazy: ``import dtoc.hardware.<module>`` (e.g. the torch-free ``orientation``) must not import torch; the
# names below load their module on first use.
_LAZY = {
    "EFFECTS": "dtoc.hardware.effects",
    "B0Eddy": "dtoc.hardware.effects",
    "CrossEddy": "dtoc.hardware.effects",
    "Delay": "dtoc.hardware.effects",
    "Effect": "dtoc.hardware.effects",
    "ExpEddy": "dtoc.hardware.effects",
    "Gain": "dtoc.hardware.effects",
    "Girf": "dtoc.hardware.effects",
    "Lti": "dtoc.hardware.effects",
    "Offset": "dtoc.hardware.effects",
    "SlewLimit": "dtoc.hardware.effects",
    "GirfData": "dtoc.hardware.girf_io",
    "load_girf": "dtoc.hardware.girf_io",
    "save_girf": "dtoc.hardware.girf_io",
    "Measurement": "dtoc.hardware.measurement",
    "load_measurement": "dtoc.hardware.measurement",
    "save_measurement": "dtoc.hardware.measurement",
    "k_from_G": "dtoc.hardware.measurement",
    "G_from_k": "dtoc.hardware.measurement",
    "HardwareModel": "dtoc.hardware.model",
    "build_effect": "dtoc.hardware.model",
    "load_model": "dtoc.hardware.model",
    "save_model": "dtoc.hardware.model",
    "model_from_girf": "dtoc.hardware.model",
    "model_from_spec": "dtoc.hardware.model",
    "resolve_model": "dtoc.hardware.model",
}


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'dtoc.hardware' has no attribute {name!r}")


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
