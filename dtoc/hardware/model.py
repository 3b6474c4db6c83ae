"""The hardware model: an ordered chain of effects, and its JSON model file.

Model file (JSON, validated with pydantic)::

    {"effects": [
        {"kind": "girf", "file": "h.npz"},                       # path relative to the model file
        {"kind": "delay", "axis": "x", "params": {"seconds": 2e-6}},
        {"kind": "exp_eddy", "axis": null, "params": {"alpha": [0.1, 0.1], "tau_s": [1e-3, 0.1]}},
        {"kind": "b0_eddy", "input_axis": "z", "params": {"alpha_uT_per_mT_per_m": 0.01, "tau_s": 5e-3}}
    ]}

Effects act in the listed order, each on the output of the previous one (see
:mod:`dtoc.hardware.effects`), except that the eddy-current kinds ``exp_eddy``, ``cross_eddy`` and ``b0_eddy``
are driven by the slew of the *demanded* waveform (the chain's input, as docs/contracts.md §3 defines them)
and subtract their field from the output of the effects before them; their ``*_chain`` variants are driven by
that output instead.  An empty list is ideal hardware.  ``--girf h.npz`` is the shortcut for a
model with the single effect ``girf``.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
from pydantic import BaseModel, ConfigDict, ValidationError
from torch import nn

from dtoc.errors import InputError
from dtoc.hardware.effects import EFFECTS, Effect, Girf
from dtoc.util.atomic import atomic_write_text

Axis = Literal["x", "y", "z"] | None


class EffectSpec(BaseModel):
    """One entry of the model file's ``effects`` list."""

    model_config = ConfigDict(extra="forbid")
    kind: str
    axis: Axis = None
    input_axis: Axis = None
    params: dict[str, Any] = {}
    file: str | None = None


class ModelSpec(BaseModel):
    """The model file: an ordered list of effects (plus an optional free-text description)."""

    model_config = ConfigDict(extra="forbid")
    effects: list[EffectSpec] = []
    description: str | None = None


def build_effect(
    kind: str,
    params: dict[str, Any] | None = None,
    axis: str | None = None,
    input_axis: str | None = None,
    file: str | os.PathLike | None = None,
    base_dir: str | os.PathLike | None = None,
) -> Effect:
    """Construct one effect from its kind, parameters and axes (InputError on anything wrong).

    For ``girf``, ``file`` is the GIRF ``.npz`` (relative paths are taken from ``base_dir``).
    """
    params = dict(params or {})
    if kind not in EFFECTS:
        raise InputError(f"unknown effect kind {kind!r}; known: {', '.join(sorted(EFFECTS))}")
    cls = EFFECTS[kind]
    if kind == "girf":
        if file is None:
            raise InputError("effect 'girf' needs 'file' (a GIRF .npz)")
        from dtoc.hardware.girf_io import load_girf

        p = Path(file)
        if not p.is_absolute() and base_dir is not None:
            p = Path(base_dir) / p
        eff = girf_effect(load_girf(p))
        eff.file = str(p.resolve())
        return eff
    if file is not None:
        raise InputError(f"effect {kind!r} takes no 'file'")
    kwargs: dict[str, Any] = dict(params)
    if kind == "lti":
        missing = {"taps", "dt_s"} - set(params)
        if missing:
            raise InputError(f"effect 'lti': missing parameter(s) {sorted(missing)}")
        unknown = set(params) - {"taps", "dt_s", "t0_s"}
    else:
        missing = set(cls.param_names) - set(params)
        if missing:
            raise InputError(f"effect {kind!r}: missing parameter(s) {sorted(missing)}")
        unknown = set(params) - set(cls.param_names)
    if unknown:
        raise InputError(f"effect {kind!r}: unknown parameter(s) {sorted(unknown)}")
    if kind in ("cross_eddy", "b0_eddy", "cross_eddy_chain", "b0_eddy_chain"):
        kwargs.update(axis=axis, input_axis=input_axis)
    else:
        if input_axis is not None:
            raise InputError(f"effect {kind!r} takes no 'input_axis'")
        kwargs.update(axis=axis)
    return cls(**kwargs)


def girf_effect(girf) -> Girf:
    """A :class:`Girf` effect from a :class:`dtoc.hardware.girf_io.GirfData` (time domain)."""
    td = girf.to_time_domain()
    return Girf(td.h, td.dt_s, td.t0_s, td.h0, file=td.source)


class HardwareModel(nn.Module):
    """Ordered chain of effects: demanded gradient -> realized gradient and B0 offset.

    ``forward(g, dt_s, b0=None)``: ``g`` (B, 3, T) or (3, T) in mT/m on a uniform grid ``dt_s`` (s),
    samples at ``t_n = n*dt_s``; returns ``(G, b0_uT)`` with ``G`` the shape of ``g`` (mT/m) and ``b0_uT``
    (B, T) or (T,) (uT).  Differentiable w.r.t. ``g`` and every effect parameter; works in float32 and
    float64 on any device (parameters are cast to the waveform's dtype/device).
    """

    def __init__(self, effects: list[Effect] | None = None, description: str | None = None):
        super().__init__()
        self.effects = nn.ModuleList(effects or [])
        self.description = description

    def forward(self, g: torch.Tensor, dt_s: float, b0: torch.Tensor | None = None, demand: torch.Tensor | None = None):
        """``demand``: the demanded waveform that drives the eddy-current effects when ``g`` is not it
        (e.g. ``g`` is the output of an earlier part of the chain that was evaluated separately); default
        ``g``."""
        if not isinstance(g, torch.Tensor):
            g = torch.as_tensor(np.asarray(g, dtype=np.float64))
        squeeze = g.ndim == 2
        if squeeze:
            g = g.unsqueeze(0)
        if g.ndim != 3 or g.shape[1] != 3:
            raise InputError(f"hardware model: gradient must have shape (B, 3, T) or (3, T), got {tuple(g.shape)}")
        if b0 is None:
            b0 = torch.zeros(g.shape[0], g.shape[2], dtype=g.dtype, device=g.device)
        elif squeeze and b0.ndim == 1:
            b0 = b0.unsqueeze(0)
        if demand is None:
            demand = g
        elif squeeze and demand.ndim == 2:
            demand = demand.unsqueeze(0)
        G = g
        for eff in self.effects:
            if getattr(eff, "driven_by_demand", False):
                G, b0 = eff(G, b0, dt_s, demand=demand)
            else:
                G, b0 = eff(G, b0, dt_s)
        if squeeze:
            return G[0], b0[0]
        return G, b0

    def frozen(self) -> HardwareModel:
        """Stop gradients w.r.t. the model's parameters (in place; returns self).

        Use when optimizing the waveform through a fixed model: no parameter gradients are computed and
        GIRF effects reuse their resampled kernel spectrum across calls.
        """
        self.requires_grad_(False)
        return self

    @property
    def is_identity(self) -> bool:
        return len(self.effects) == 0

    def to_spec(self) -> dict[str, Any]:
        """Model-file content as a dict (GIRF effects reference their ``file``)."""
        out: dict[str, Any] = {"effects": [e.spec() for e in self.effects]}
        if self.description:
            out["description"] = self.description
        return out

    def to_json(self) -> str:
        """Model file text (sorted, indented JSON; deterministic)."""
        return json.dumps(self.to_spec(), indent=2, sort_keys=True) + "\n"


def model_from_spec(
    spec: dict[str, Any] | ModelSpec, base_dir: str | os.PathLike | None = None, where: str = "model"
) -> HardwareModel:
    """Build a model from a parsed model-file dict."""
    try:
        ms = spec if isinstance(spec, ModelSpec) else ModelSpec.model_validate(spec)
    except ValidationError as e:
        err = e.errors()[0]
        loc = ".".join(str(x) for x in err["loc"])
        raise InputError(f"{where}: key {loc!r}: {err['msg']}") from None
    effects = []
    for i, es in enumerate(ms.effects):
        try:
            effects.append(build_effect(es.kind, es.params, es.axis, es.input_axis, es.file, base_dir))
        except InputError as e:
            raise InputError(f"{where}: effects[{i}]: {e}") from None
    return HardwareModel(effects, ms.description)


#: Plausible ranges of scalar parameters in a model *file* (outside: a unit mistake, e.g. us given as s).
PLAUSIBLE = {
    ("gain", "factor"): (0.1, 10.0, "dimensionless"),
    ("delay", "seconds"): (-1e-3, 1e-3, "s"),
    ("delay_bandlimited", "seconds"): (-1e-3, 1e-3, "s"),
    ("offset", "mT_per_m"): (-100.0, 100.0, "mT/m"),
    ("exp_eddy", "alpha"): (-1.0, 1.0, "dimensionless"),
    ("exp_eddy", "tau_s"): (1e-7, 10.0, "s"),
    ("cross_eddy", "alpha"): (-1.0, 1.0, "dimensionless"),
    ("cross_eddy", "tau_s"): (1e-7, 10.0, "s"),
    ("b0_eddy", "alpha_uT_per_mT_per_m"): (-100.0, 100.0, "uT per mT/m"),
    ("b0_eddy", "tau_s"): (1e-7, 10.0, "s"),
    ("slew_limit", "max_slew_T_per_m_per_s"): (1.0, 1e5, "T/m/s"),
    ("resonance", "f0_hz"): (0.1, 1e6, "Hz"),
    ("resonance", "q"): (0.5, 1e6, "dimensionless"),
    ("resonance", "amplitude"): (-10.0, 10.0, "dimensionless"),
}
PLAUSIBLE.update({(k + "_chain", n): v for (k, n), v in list(PLAUSIBLE.items()) if k.endswith("eddy")})


#: Kinds that describe the measuring device, not the gradient chain: refused in a model file.
MEASUREMENT_KINDS = ("time_base",)


def check_plausible_spec(ms: ModelSpec, where: str = "model") -> None:
    """Reject model-file parameters outside :data:`PLAUSIBLE` and measurement-side kinds (one line naming
    ``effects[i]``)."""
    for i, es in enumerate(ms.effects):
        if es.kind in MEASUREMENT_KINDS:
            raise InputError(
                f"{where}: effects[{i}] ({es.kind}): describes the measuring device's clock, not the gradient "
                "chain; it cannot be part of a hardware model (dtoc identify applies it to the measurement only)"
            )
        for name, value in es.params.items():
            rng = PLAUSIBLE.get((es.kind, name))
            if rng is None:
                continue
            vals = value if isinstance(value, (list, tuple)) else [value]
            for v in vals:
                if (
                    isinstance(v, (int, float))
                    and not isinstance(v, bool)
                    and np.isfinite(v)
                    and not rng[0] <= v <= rng[1]
                ):  # NaN/inf: the effect's own check names them
                    raise InputError(
                        f"{where}: effects[{i}] ({es.kind}): {name} = {v:g} is implausible (expected "
                        f"{rng[0]:g} to {rng[1]:g} {rng[2]}; units off?)"
                    )


def load_model(path: str | os.PathLike) -> HardwareModel:
    """Read a JSON model file (GIRF files relative to it); implausible parameters are rejected
    (:func:`check_plausible_spec`)."""
    p = Path(path)
    if p.is_dir():
        raise InputError(f"{p}: is a directory, expected a model .json file")
    if not p.is_file():
        raise InputError(f"{p}: model file not found")
    try:
        spec = json.loads(p.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise InputError(f"{p}: not valid JSON ({e.msg if hasattr(e, 'msg') else e})") from None
    if not isinstance(spec, dict):
        raise InputError(f"{p}: model file must be a JSON object with key 'effects'")
    if "effects" not in spec:  # `{}` is not "ideal hardware": an ideal model says so with "effects": []
        raise InputError(f"{p}: model file has no key 'effects' (ideal hardware is an explicit \"effects\": [])")
    try:
        ms = ModelSpec.model_validate(spec)
    except ValidationError as e:
        err = e.errors()[0]
        loc = ".".join(str(x) for x in err["loc"])
        raise InputError(f"{p}: key {loc!r}: {err['msg']}") from None
    check_plausible_spec(ms, str(p))
    return model_from_spec(ms, base_dir=p.parent, where=str(p))


def save_model(model: HardwareModel, path: str | os.PathLike, force: bool = False) -> Path:
    """Write the model file; GIRF effects without a file get one beside it (``<stem>_girf<i>.npz``).

    GIRF ``file`` entries are written relative to the model file's folder when possible.
    """
    from dtoc.hardware.girf_io import GirfData, save_girf

    p = Path(path)
    spec = model.to_spec()
    for i, (eff, es) in enumerate(zip(model.effects, spec["effects"])):
        if not isinstance(eff, Girf):
            continue
        src = Path(eff.file) if eff.file else None
        if src is None or not src.is_file():
            target = p.parent / f"{p.stem}_girf{i}.npz"
            gd = GirfData(
                dt_s=eff.dt_s,
                t0_s=eff.t0_s,
                h=eff.h.detach().cpu().double().numpy(),
                h0=None if eff.h0 is None else eff.h0.detach().cpu().double().numpy(),
            )
            save_girf(gd, target, force=force)
            es["file"] = target.name
        else:
            try:
                es["file"] = os.path.relpath(src.resolve(), p.parent.resolve())
            except ValueError:  # another drive
                es["file"] = str(src.resolve())
    return atomic_write_text(p, json.dumps(spec, indent=2, sort_keys=True) + "\n", force=force)


def model_from_girf(path: str | os.PathLike) -> HardwareModel:
    """The ``--girf h.npz`` shortcut: a model with the single effect ``girf``."""
    from dtoc.hardware.girf_io import load_girf

    eff = girf_effect(load_girf(path))
    eff.file = str(Path(path).resolve())
    return HardwareModel([eff], description=f"GIRF {Path(path).name}")


def resolve_model(girf: str | os.PathLike | None = None, model: str | os.PathLike | None = None) -> HardwareModel:
    """``--girf`` / ``--model`` CLI options -> model (neither: ideal hardware; both: error)."""
    if girf is not None and model is not None:
        raise InputError("give either --girf or --model, not both")
    if girf is not None:
        return model_from_girf(girf)
    if model is not None:
        return load_model(model)
    return HardwareModel([])
