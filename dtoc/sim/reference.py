"""``--reference BASE``: a played file measured against the base it was compiled from (docs/foreign.md,
"Checking an output against its base").

A pre-compensated output demands a distorted waveform on purpose; its errors only mean something against what
the *base* intended.  ``dtoc predict``, ``dtoc simulate`` and ``dtoc check`` with ``--reference BASE`` take the
realized trajectory of the played file and compare it with the base's nominal (demanded) one.  This module holds
the two preconditions they share:

- :func:`check_same_structure`: the played file and the base must be the same sequence apart from gradient
  waveforms (same blocks, fine grid, RF events and ADC events, to 1 ns), else one line naming the first difference;
- :func:`verify_base_hash`: a ``dtoc optimize`` output records its base's sha256 in ``[DEFINITIONS]``
  (:data:`BASE_HASH_DEFINITION`, beside the manifest's ``inputs.base``); a different hash is refused (the base
  was edited or is another file), no recorded hash is accepted with a note (a file not written by dtoc, or by
  an older version).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dtoc.constants import BASE_HASH_DEFINITION
from dtoc.errors import InputError
from dtoc.seq.ir import SequenceIR

_TOL_S = 1e-9


def check_same_structure(played: SequenceIR, base: SequenceIR, played_name: str, base_name: str) -> None:
    """Raise :class:`InputError` (one line) unless ``played`` has ``base``'s blocks, timing, RF and ADC events."""

    def refuse(what: str, a, b) -> None:
        raise InputError(
            f"{played_name} does not match its reference {base_name}: {what} ({a} vs {b}); "
            "--reference needs the base the file was compiled from"
        )

    nb_p, nb_b = len(played.block_edges_s) - 1, len(base.block_edges_s) - 1
    if nb_p != nb_b:
        refuse("number of blocks", nb_p, nb_b)
    if abs(played.dt_fine_s - base.dt_fine_s) > 1e-12 or played.n_fine != base.n_fine:
        refuse("duration / gradient raster", f"{played.duration_s:.9g} s", f"{base.duration_s:.9g} s")
    if not np.allclose(played.block_edges_s, base.block_edges_s, rtol=0, atol=_TOL_S):
        i = int(np.argmax(np.abs(np.asarray(played.block_edges_s) - np.asarray(base.block_edges_s)) > _TOL_S))
        refuse(f"start of block {i + 1}", f"{played.block_edges_s[i]:.9g} s", f"{base.block_edges_s[i]:.9g} s")
    if len(played.adc) != len(base.adc):
        refuse("number of ADC events", len(played.adc), len(base.adc))
    for i, (a, b) in enumerate(zip(played.adc, base.adc, strict=True)):
        if a.num_samples != b.num_samples:
            refuse(f"samples of ADC event {i + 1}", a.num_samples, b.num_samples)
        if abs(a.t_start_s - b.t_start_s) > _TOL_S or abs(a.dwell_s - b.dwell_s) > 1e-12:
            refuse(f"timing of ADC event {i + 1}", f"{a.t_start_s:.9g} s", f"{b.t_start_s:.9g} s")
    if len(played.rf) != len(base.rf):
        refuse("number of RF pulses", len(played.rf), len(base.rf))
    for i, (p, q) in enumerate(zip(played.rf, base.rf, strict=True)):
        if abs(p.t_center_s - q.t_center_s) > _TOL_S or p.excites != q.excites or p.refocuses != q.refocuses:
            refuse(f"RF pulse {i + 1} (centre, use)", f"{p.t_center_s:.9g} s {p.use}", f"{q.t_center_s:.9g} s {q.use}")


def recorded_base_hash(played_path: str | Path) -> str | None:
    """The base sha256 a ``.seq`` records (:data:`BASE_HASH_DEFINITION`), or None (not a ``.seq``, or none)."""
    p = Path(played_path)
    if p.suffix.lower() != ".seq":
        return None
    from dtoc.seq.seqtext import parse_seq_text

    v = parse_seq_text(p).definitions().get(BASE_HASH_DEFINITION)
    return v.split()[0].lower() if v and v.split() else None


def verify_base_hash(played_path: str | Path, base_path: str | Path, played_name: str, base_name: str) -> dict:
    """Compare the base hash the played file records with ``base_path``'s; refuse a different one.

    Returns the record for reports: ``{"path", "sha256", "verified"}`` (``verified`` False: the played file
    names no base) and, under ``"note"``, one line for the user.
    """
    from dtoc.util.atomic import sha256_file

    sha = sha256_file(base_path)
    rec = recorded_base_hash(played_path)
    if rec is not None and rec != sha:
        raise InputError(
            f"{played_name} was compiled from another base (its {BASE_HASH_DEFINITION} {rec[:12]}... differs from "
            f"{base_name}'s sha256 {sha[:12]}...): give the base it was compiled from (the optimize manifest's "
            "inputs.base)"
        )
    note = (
        f"reference {base_name}: verified (the base {played_name} was compiled from, sha256 {sha[:12]}...)"
        if rec is not None
        else f"reference {base_name}: not verified ({played_name} records no base hash; structure matches)"
    )
    return {"path": str(base_path), "sha256": sha, "verified": rec is not None, "note": note}


def load_reference(played: SequenceIR, played_path: str | Path, base_path: str | Path) -> tuple[SequenceIR, dict]:
    """The base sequence of ``--reference BASE`` for the played file (already read as ``played``): read, its
    structure matched and its hash verified (:func:`check_same_structure`, :func:`verify_base_hash`).
    Returns (base IR, record for reports with a ``note`` line)."""
    from dtoc.seq.load import load_sequence

    pn, bn = Path(played_path).name, Path(base_path).name
    base = load_sequence(Path(base_path))
    check_same_structure(played, base, pn, bn)
    return base, verify_base_hash(played_path, base_path, pn, bn)


def reference_figures(played: SequenceIR, base: SequenceIR, model) -> dict:
    """The compact figures ``dtoc check --reference`` reports: the played file's realized k (through ``model``,
    orientation included; None: ideal hardware, i.e. its demanded k) against the base's nominal k.

    Returns ``{"realized": bool, "k_error_max_dk", "k_error_max_rad_per_m", "epi_odd_minus_even_dk"}``
    (dk: the base's 2 pi / FOV; None where the base has no FOV).
    """
    from dtoc.hardware.model import resolve_model
    from dtoc.sim.predict import predict

    res = predict(played, model if model is not None else resolve_model(), reference=base)
    kmax = [r["max_rad_per_m"] for r in res["k_error"].values()]
    ro = (res.get("epi") or {}).get("readout") or {}
    return {
        "realized": model is not None,
        "k_error_max_dk": res["k_error_max_dk"],
        "k_error_max_rad_per_m": max(kmax) if kmax else None,
        "epi_odd_minus_even_dk": ro.get("odd_minus_even_dk"),
    }
