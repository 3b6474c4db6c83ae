"""``--reference BASE``: a pre-compensated output measured against what its base intended, at any orientation."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from cli_helpers import run_cli

REPO = Path(__file__).resolve().parents[1]
BASE = REPO / "sequences" / "epi_small.seq"  # 16x16 EPI, FOV 250 mm
GIRF = REPO / "girf" / "example_7T.npz"  # per-axis GIRF: the orientation matters


@pytest.fixture(scope="module")
def sag_output(tmp_path_factory):
    """epi_small optimized for the sagittal orientation: (base copy, output, manifest)."""
    d = tmp_path_factory.mktemp("ref")
    base = d / "base.seq"
    shutil.copyfile(BASE, base)
    out, man = d / "sag.seq", d / "sag.json"
    from dtoc.cli.main import run  # a module fixture has no capsys: the CLI entry point directly

    try:
        run(
            [str(a) for a in ("optimize", base, "--girf", GIRF, "--orientation", "sag", "-o", out, "--json", man, "-q")]
        )
    except SystemExit as e:
        assert not e.code, e.code
    return base, out, json.loads(man.read_text())


def _predict(capsys, out, *argv) -> dict:
    code, stdout, err = run_cli(capsys, "predict", out, "--girf", GIRF, "--json", "-", "-q", *argv)
    assert code == 0, err
    return json.loads(stdout)


def test_predict_reference_reproduces_the_manifest_at_its_orientation_and_not_elsewhere(capsys, sag_output):
    base, out, m = sag_output
    after = m["after"]["kspace_max_error_dk"]
    assert m["inputs"]["base"]["sha256"] and after < 0.05  # the optimized figure the user was given
    at_sag = _predict(capsys, out, "--orientation", "sag", "--reference", base)
    # the same figure as the manifest, within the writer's stated precision (the output is re-read: its amplitudes
    # are the file's decimals; docs/sequences.md "Precision bound": <= 2e-5 dk at every ADC sample)
    assert at_sag["k_error_max_dk"] == pytest.approx(after, abs=2e-5)
    assert at_sag["reference"]["verified"] is True
    assert at_sag["reference"]["sha256"] == m["inputs"]["base"]["sha256"]
    # another orientation: the pre-compensation does not hold there
    at_tra = _predict(capsys, out, "--orientation", "tra", "--reference", base)
    assert at_tra["k_error_max_dk"] > 10 * after
    # without the reference the output is measured against its own (pre-compensated) demand: meaningless
    own = _predict(capsys, out, "--orientation", "sag")
    assert own["k_error_max_dk"] > 0.5 and "reference" not in own
    # EPI odd-even offset: against the base it is tiny at sag
    assert abs(at_sag["epi"]["readout"]["odd_minus_even_dk"]) < 0.01 < abs(own["epi"]["readout"]["odd_minus_even_dk"])


def test_simulate_reference_reproduces_the_manifest_nrmse(capsys, sag_output):
    base, out, m = sag_output
    res = {}
    for o in ("sag", "tra"):
        argv = ("simulate", out, "--girf", GIRF, "--orientation", o, "--reference", base, "--json", "-", "-q")
        code, stdout, err = run_cli(capsys, *argv)
        assert code == 0, err
        res[o] = json.loads(stdout)
    assert res["sag"]["nrmse_percent"] == pytest.approx(m["after"]["nrmse_percent"], rel=1e-3)
    assert res["tra"]["nrmse_percent"] > 5 * res["sag"]["nrmse_percent"]
    assert res["sag"]["reference"]["verified"] is True


def test_reference_refusals_and_an_unverified_base(capsys, sag_output, tmp_path):
    base, out, _ = sag_output
    # another sequence: refused in one line before any work
    other = REPO / "sequences" / "gre_small.seq"
    code, _, err = run_cli(capsys, "predict", out, "--girf", GIRF, "--reference", other, "-q")
    assert code == 2 and "does not match its reference" in err and "number of blocks" in err
    assert len([ln for ln in err.splitlines() if ln.startswith("dtoc: error")]) == 1
    # the same structure but a different file than the one it was compiled from: refused (hash)
    edited = tmp_path / "edited.seq"
    edited.write_bytes(base.read_bytes() + b"# edited\n")
    code, _, err = run_cli(capsys, "check", out, "--reference", edited)
    assert code == 2 and "compiled from another base" in err
    # a file that names no base (the base itself, played as is): accepted, said to be unverified, zero error
    code, stdout, err = run_cli(capsys, "check", base, "--reference", base, "--json", "-")
    assert code == 0 and "not verified" in err
    rep = json.loads(stdout)["reference"]
    assert rep["verified"] is False and rep["realized"] is False and rep["k_error_max_dk"] == pytest.approx(0, abs=1e-9)


def test_check_reference_reports_the_demanded_departure_without_a_model(capsys, sag_output):
    base, out, _ = sag_output
    code, stdout, err = run_cli(capsys, "check", out, "--reference", base, "--json", "-")
    assert code == 0, err
    rep = json.loads(stdout)["reference"]
    # the output's demand departs from the base's nominal k on purpose (the pre-compensation)
    assert rep["verified"] is True and rep["realized"] is False and rep["k_error_max_dk"] > 0.5


def test_diff_ignores_the_provenance_definition(capsys, sag_output):
    base, out, _ = sag_output
    code, stdout, _ = run_cli(capsys, "diff", base, out, "--json", "-")
    whats = {(d["what"], d["where"]) for d in json.loads(stdout)["differences"]}
    assert ("definition", "DtocBaseSha256") not in whats and code == 1  # gradients differ, the hash is not listed
