"""The library behind every ``dtoc`` command, one function per command (docs/api.md).

``optimize_sequence`` and ``identify_effects`` carry longer names than their commands because
``dtoc.optimize`` and ``dtoc.identify`` are the sub-packages that implement them.

Each function takes what the command takes (paths or in-memory objects) and returns typed results
instead of printing; the CLI (:mod:`dtoc.cli`) is a thin layer over the same calls.  Units: mT/m, uT,
rad/m, s (docs/conventions.md).  Import it as ``import dtoc`` (the names below are re-exported there,
loaded on first use so that ``import dtoc`` stays light).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

from dtoc.constants import DEFAULT_B0_T
from dtoc.seq.ir import SequenceIR

if TYPE_CHECKING:
    from dtoc.hardware.model import HardwareModel
    from dtoc.identify.search import IdentifyResult
    from dtoc.optimize.config import OptimizeConfig
    from dtoc.optimize.run import RunOutputs
    from dtoc.seq.check import CheckResult
    from dtoc.seq.diff import DiffResult
    from dtoc.seq.spec import BaseSpec
    from dtoc.seq.system import SystemSpec
    from dtoc.sim.comparison import ComparisonResult
    from dtoc.sim.phantom import Phantom
    from dtoc.sim.twin import HardwareChain

PathLike = str | Path


def load_sequence(path_or_spec: PathLike | BaseSpec) -> SequenceIR:
    """A base sequence from a ``.seq`` file, a spec ``.yaml`` file or a spec object (docs/sequences.md)."""
    from dtoc.seq.load import load_sequence as _load

    return _load(path_or_spec)


def build_sequence(spec: PathLike | BaseSpec, out: PathLike | None = None, force: bool = False) -> SequenceIR:
    """Build a spec (object or ``.yaml``) into a sequence; with ``out``, also write the signed ``.seq`` (``dtoc build``)."""
    from dtoc.seq.build import build_ir, build_to_file
    from dtoc.seq.spec import BaseSpec, load_spec

    s = spec if isinstance(spec, BaseSpec) else load_spec(Path(spec))
    if out is not None:
        build_to_file(s, out, force=force)
    return build_ir(s)


def load_model(girf: PathLike | None = None, model: PathLike | None = None, trainable: bool = False) -> HardwareModel:
    """The hardware model of a GIRF file (``--girf``) or a model file (``--model``); neither: ideal hardware.

    The model is fixed (no gradients with respect to its parameters, what simulate / predict / optimize
    need) unless ``trainable`` (to fit its parameters, as ``identify`` does).
    """
    from dtoc.hardware.model import resolve_model

    m = resolve_model(girf=girf, model=model)
    return m if trainable else m.frozen()


def simulate(
    sequence: PathLike | SequenceIR,
    model: HardwareChain | None = None,
    *,
    phantom: Phantom | str | None = None,
    field_T: float = DEFAULT_B0_T,
    n_dummies: int | None = None,
    device: str = "cpu",
    reference: PathLike | SequenceIR | None = None,
) -> ComparisonResult:
    """Ideal versus realized images of a Cartesian sequence on a phantom (``dtoc simulate``).

    Args:
        sequence: base sequence (path, spec or :class:`~dtoc.seq.ir.SequenceIR`).
        model: hardware chain (:func:`load_model`); None: ideal hardware.
        phantom: a :class:`~dtoc.sim.phantom.Phantom` or a spec ('brain', 'brain-noscalp:64', a ``.npz``).
        field_T: field strength of the built-in phantom's tissue values, T.
        n_dummies: dummy repetitions before the sequence (steady state); None: as ``dtoc optimize`` for the kind
            (:func:`dtoc.constants.default_dummies`).
        reference: the base ``sequence`` was compiled from (``--reference``): ideal image and nominal k are the
            base's (same structure required; a base hash the file records is verified when both are paths).
    Returns:
        :class:`~dtoc.sim.comparison.ComparisonResult` (images, k-space, ``metrics`` dict).
    """
    from dtoc.sim.comparison import compare_ideal_realized
    from dtoc.sim.phantom import Phantom, phantom_for

    ir = sequence if isinstance(sequence, SequenceIR) else load_sequence(sequence)
    base = _reference(sequence, ir, reference)
    ph = phantom if isinstance(phantom, Phantom) else phantom_for(base or ir, phantom, field_T=field_T)
    if n_dummies is None:
        from dtoc.constants import default_dummies

        n_dummies = default_dummies(ir.kind)
    return compare_ideal_realized(ir, ph, model, n_dummies=n_dummies, device=device, reference=base)


def _reference(sequence, ir: SequenceIR, reference) -> SequenceIR | None:
    """The base of ``reference=`` (None: none), structure matched; hash verified when both are paths."""
    from dtoc.sim.reference import check_same_structure, load_reference

    if reference is None:
        return None
    if isinstance(reference, SequenceIR):
        check_same_structure(ir, reference, "the sequence", "the reference")
        return reference
    if isinstance(sequence, SequenceIR):
        base = load_sequence(reference)
        check_same_structure(ir, base, "the sequence", Path(reference).name)
        return base
    return load_reference(ir, sequence, reference)[0]


def predict(
    sequence: PathLike | SequenceIR, model: HardwareModel, reference: PathLike | SequenceIR | None = None
) -> dict[str, Any]:
    """Realized versus demanded gradients, k-space error and B0 phase of a sequence (``dtoc predict``);
    ``reference``: against the base it was compiled from instead of its own demand (``--reference``)."""
    from dtoc.sim.predict import predict as _predict

    ir = sequence if isinstance(sequence, SequenceIR) else load_sequence(sequence)
    out = _predict(ir, model, reference=_reference(sequence, ir, reference))
    out.pop("_arrays", None)
    return out


def optimize_sequence(
    base: PathLike | SequenceIR,
    *,
    girf: PathLike | None = None,
    model: PathLike | None = None,
    out: PathLike | None = None,
    config: OptimizeConfig | None = None,
    manifest_path: PathLike | None = None,
    png_path: PathLike | None = None,
    force: bool = False,
    phantom: Phantom | str | None = None,
    device: str = "cpu",
    ideal: bool = False,
) -> RunOutputs:
    """Pre-compensate ``base`` for a hardware model within the hard limits (``dtoc optimize``).

    Returns:
        :class:`~dtoc.optimize.run.RunOutputs`: ``manifest`` (figures before/after, limits, hashes),
        ``ir_out`` (the pre-compensated sequence) and arrays for plots.
    """
    from dtoc.optimize.run import optimize_sequence as _optimize

    return _optimize(
        base,
        out=out,
        girf=girf,
        model=model,
        config=config,
        manifest_path=manifest_path,
        png_path=png_path,
        force=force,
        phantom=phantom,
        device=device,
        ideal=ideal,
    )


def identify_effects(
    measured: PathLike,
    *,
    girf: PathLike | None = None,
    model: PathLike | None = None,
    out_model: PathLike | None = None,
    json_out: PathLike | None = None,
    force: bool = False,
) -> IdentifyResult:
    """Compare a measurement with the declared model, add the missing effects, report before/after (``dtoc identify``)."""
    from dtoc.identify.api import run_identify

    return run_identify(measured, girf=girf, model=model, out_model=out_model, json_out=json_out, force=force)


def check(path: PathLike, system: SystemSpec | None = None) -> CheckResult:
    """Validate a ``.seq`` file (``dtoc check``): the format's rules and the limits, and the vendor conventions of
    ``system`` (dead times, ADC samples, rasters) when one is given (each violation's ``kind`` and ``source``)."""
    from dtoc.seq.check import check_file

    return check_file(path, system)


def diff(path_a: PathLike, path_b: PathLike, rtol: float = 1e-6, atol: float = 1e-9) -> DiffResult:
    """Semantic comparison of two ``.seq`` files within tolerances (``dtoc diff``)."""
    from dtoc.seq.diff import diff_files

    return diff_files(path_a, path_b, rtol=rtol, atol=atol)


def run_batch(
    plan: PathLike,
    out: PathLike,
    engine: str = "local",
    workers: int | None = None,
    address: str | None = None,
) -> dict[str, Any]:
    """Run a batch plan into the folder ``out``, each job one ``dtoc optimize``, cached by content
    (``dtoc batch``, docs/batch.md).  Returns the report (one record per job: status, figures, folder)."""
    from dtoc.batch.run import run_batch as _run

    return _run(plan, out, engine=engine, workers=workers, address=address)
