"""``--scanner PROFILE.yaml`` (docs/scanner.md): the option and how its values yield to explicit options."""

from __future__ import annotations

from pathlib import Path

import typer

ORIENTATION_HELP = (
    "slice orientation the file is played at: tra, sag, cor or 9 numbers (row-major rotation logical -> physical; "
    "docs/conventions.md); the hardware model acts on the physical axes"
)

SCANNER_HELP = "scanner profile YAML (docs/scanner.md): limits, rasters, dead times, hardware model, B0; explicit options override it"


RF_USE_HELP = (
    "RF use by the file's [RF] event number, e.g. 2=refocusing,3=inversion (or initials e/r/i/s/p/o/u): over the "
    "file's use and over the use detected for files before format 1.5 (docs/foreign.md)"
)


def rf_use_option():
    return typer.Option(None, "--rf-use", help=RF_USE_HELP)


def rf_use(text: str | None) -> dict:
    """``--rf-use`` parsed (:func:`dtoc.seq.rfuse.parse_rf_use_overrides`)."""
    from dtoc.seq.rfuse import parse_rf_use_overrides

    return parse_rf_use_overrides(text)


def scanner_option():
    return typer.Option(None, "--scanner", help=SCANNER_HELP)


def load(scanner: Path | None):
    """The :class:`dtoc.hardware.profile.LoadedProfile`, or None: loaded and validated whole, its hardware
    section included (every command that takes ``--scanner`` refuses a profile whose GIRF or model is missing,
    NaN, pickled or not a GIRF, whether or not it plays the model)."""
    if scanner is None:
        return None
    from dtoc.hardware.profile import load_profile

    prof = load_profile(scanner)
    prof.hardware_model()
    return prof


def model_label(prof, girf, model) -> str:
    """The hardware model a report names: the one actually applied (--girf / --model, else the profile's,
    else ideal hardware)."""
    if girf is not None or model is not None:
        return str(girf or model)
    if prof is not None and prof.hardware_label() is not None:
        return str(prof.hardware_label())
    return "ideal"


def input_paths(scanner: Path | None) -> dict:
    """The profile and the hardware files it points at: inputs that no output may overwrite."""
    from dtoc.hardware.profile import input_files

    return input_files(scanner)


def resolve(prof, girf, model):
    """The model a command plays: --girf / --model, else the profile's, else ideal hardware."""
    from dtoc.hardware.profile import profile_hardware

    hw = profile_hardware(prof, girf, model)
    if hw is not None:
        return hw
    from dtoc.hardware.model import resolve_model

    return resolve_model(girf=girf, model=model)


REFERENCE_HELP = (
    "the base this file was compiled from (.seq or spec): errors against the base's intended trajectory "
    "(k, image) instead of this file's own pre-compensated demand; same structure required, a recorded "
    "base hash verified (docs/foreign.md)"
)


def reference_option():
    return typer.Option(None, "--reference", help=REFERENCE_HELP)
