"""Regression tests for defects found in the audit of `dtoc build/check/diff` (bad options, messages)."""

import json

import pytest
from cli_helpers import run_cli as _run  # noqa: E402


def _one_line_error(code, err, match):
    assert code == 2, err
    assert err.startswith("dtoc: error: ") and err.count("\n") == 1 and "Traceback" not in err
    assert match in err, err


@pytest.fixture()
def small_seq(repo_root):
    return repo_root / "sequences" / "epi_small.seq"


@pytest.mark.parametrize("opt,val", [("--gmax", "nan"), ("--gmax", "inf"), ("--gmax", "0"), ("--smax", "-5")])
def test_check_rejects_non_finite_or_non_positive_limits(capsys, small_seq, opt, val):
    # defect: --gmax nan / inf used to be accepted and the file passed ("nan mT/m ... OK")
    code, out, err = _run(capsys, "check", small_seq, opt, val)
    _one_line_error(code, err, f"{opt} {val} ")
    assert "outside the accepted range: (0, " in err  # one ranges table (dtoc.util.validate, docs/cli.md)
    assert out == ""


def test_check_names_where_the_limits_come_from(capsys, small_seq):
    # defect: a file-recorded limit overridden by --gmax was reported as "given + command line"
    code, out, err = _run(capsys, "check", small_seq, "--gmax", "5", "--json", "-")
    res = json.loads(out)
    assert code == 1 and res["limits_source"] == "file definitions + --gmax 5"
    assert res["system"]["max_grad_mT_per_m"] == 5.0 and res["system"]["max_slew_T_per_m_per_s"] == 180.0
    assert {v["rule"] for v in res["violations"]} >= {"grad_amplitude"}
    code, _, err = _run(capsys, "check", small_seq, "--max-rows", "-1")
    _one_line_error(code, err, "--max-rows must be >= 0")


@pytest.mark.parametrize("opt,val", [("--rtol", "-1"), ("--atol", "nan"), ("--atol", "-1e-9")])
def test_diff_rejects_bad_tolerances(capsys, small_seq, opt, val):
    # defect: a negative rtol made a file differ from itself (exit 1 with 50 "differences")
    code, _, err = _run(capsys, "diff", small_seq, small_seq, opt, val)
    _one_line_error(code, err, f"{opt} must be a finite number >= 0")


def test_diff_counts_every_difference(capsys, repo_root):
    # defect: n_differences was capped at the 50 listed rows
    a, b = repo_root / "sequences" / "epi_esp081.seq", repo_root / "sequences" / "epi_esp073.seq"
    code, out, _ = _run(capsys, "diff", a, b, "--json", "-")
    res = json.loads(out)
    assert code == 1 and res["n_listed"] == 50 and res["n_differences"] > 50
    # 63 transition blocks are 80 us longer, plus definitions and gradients
    assert sum(d["what"] == "block_duration" for d in res["differences"]) >= 40
    code, out, err = _run(capsys, "diff", a, b)
    assert f"{res['n_differences']} difference(s), first 50 listed" in out  # the table is on stdout


def test_build_input_and_output_messages(capsys, repo_root, tmp_path):
    spec = repo_root / "sequences" / "epi_small.yaml"
    code, _, err = _run(capsys, "build", spec, "-o", tmp_path / "x.txt")
    _one_line_error(code, err, "the output must be a .seq file")
    assert not (tmp_path / "x.txt").exists()
    code, _, err = _run(capsys, "build", repo_root / "sequences" / "epi_small.seq", "-o", tmp_path / "x.seq")
    _one_line_error(code, err, "a Pulseq .seq file, not a spec")
    code, _, err = _run(capsys, "build", tmp_path, "-o", tmp_path / "x.seq")
    _one_line_error(code, err, "is a directory")
    code, _, err = _run(capsys, "check", spec)
    _one_line_error(code, err, "a spec YAML, not a Pulseq .seq file")
    assert not list(tmp_path.iterdir())


def _edited(tmp_path, repo_root, old, new, name="e.seq"):
    """epi_small.seq with one text edit, unsigned (check reports the signature, nothing else should break)."""
    b = (repo_root / "sequences" / "epi_small.seq").read_text()
    b = b[: b.find("\n[SIGNATURE]")] + "\n"
    assert old in b
    (tmp_path / name).write_text(b.replace(old, new, 1))
    return tmp_path / name


@pytest.mark.parametrize("value", ["0", "-1e-05", "abc"])
def test_bad_raster_definition_is_one_line(capsys, tmp_path, repo_root, value):
    # defect: GradientRasterTime 0 / negative / text ended in "unexpected ValidationError" (exit 3)
    f = _edited(tmp_path, repo_root, "GradientRasterTime 1e-05", f"GradientRasterTime {value}")
    code, _, err = _run(capsys, "check", f)
    _one_line_error(code, err, "definition GradientRasterTime must be one positive time in s")


@pytest.mark.parametrize("value", ["-72", "nan"])
def test_bad_recorded_limits(capsys, tmp_path, repo_root, value):
    # defect: an invalid MaxGrad_mT_per_m definition ended in "unexpected ValidationError"
    f = _edited(tmp_path, repo_root, "MaxGrad_mT_per_m 72", f"MaxGrad_mT_per_m {value}")
    code, _, err = _run(capsys, "check", f)
    _one_line_error(code, err, "limits recorded in the file's definitions are invalid")
    code, out, err = _run(capsys, "check", f, "--gmax", "72", "--smax", "180", "--json", "-")
    res = json.loads(out)
    # an unsigned file is valid (the signature is optional in the specification): a warning, not a violation
    assert code == 0 and res["violations"] == [] and any("unsigned" in w for w in res["warnings"])
    assert res["limits_source"] == "--gmax 72 --smax 180"


@pytest.mark.parametrize("opt,val", [("--gmax", "72000"), ("--smax", "1e9")])
def test_implausible_cli_limits(capsys, small_seq, opt, val):
    # defect: --gmax 72000 (uT/m typed as mT/m) was accepted and every file passed
    code, _, err = _run(capsys, "check", small_seq, opt, val)
    _one_line_error(code, err, "outside the accepted range")


def test_system_spec_rejects_inf(tmp_path, capsys, small_seq):
    (tmp_path / "s.yaml").write_text("max_grad_mT_per_m: .inf\n")
    code, _, err = _run(capsys, "check", small_seq, "--system", tmp_path / "s.yaml")
    _one_line_error(code, err, "max_grad_mT_per_m: Input should be a finite number")


@pytest.mark.parametrize(
    "data,match",
    [
        # a typo'd key is named first (it used to say only "echo_spacing_ms: Field required (and 1 more)")
        ({"kind": "epi", "name": "a", "echospacing_ms": 0.8}, "echospacing_ms: unknown key"),
        # a typo of 100 000 repetitions used to build for minutes; 250 m FOV (um typed as mm) built silently
        (
            {"kind": "gre", "name": "a", "repetitions": 100000},
            "repetitions: Input should be less than or equal to 4096",
        ),
        ({"kind": "epi", "name": "a", "echo_spacing_ms": 0.8, "fov_mm": 250000}, "fov_mm: Input should be less than"),
        (
            {"kind": "epi", "name": "a", "echo_spacing_ms": float("nan")},
            "echo_spacing_ms: Input should be a finite number",
        ),
    ],
)
def test_spec_messages_and_plausible_ranges(data, match):
    from dtoc.errors import InputError
    from dtoc.seq.spec import parse_spec

    with pytest.raises(InputError, match=match):
        parse_spec(data, "s.yaml")
