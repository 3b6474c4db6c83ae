"""Hostile inputs and paths across every command (docs/cli.md, "Bad input"): each case exits 2 (1 for a
``check`` that finds violations), prints at most one stderr line and no traceback or "unexpected", and
leaves every file in its folder as it was (sha256 before and after)."""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import run_cli

from dtoc.seq.seqtext import sign_text

REPO = Path(__file__).resolve().parents[1]
GRE = REPO / "sequences" / "gre_small.seq"
EPI = REPO / "sequences" / "epi_small.seq"
SPEC = REPO / "sequences" / "epi_small.yaml"
GIRF = REPO / "girf" / "example_7T.npz"
RAW = GRE.read_bytes()
BODY = RAW[: RAW.find(b"\n[SIGNATURE]")]


def _seq(old: bytes, new: bytes) -> bytes:
    """The GRE with one edit, re-signed (so that only the edit is wrong)."""
    assert old in BODY, old
    return sign_text(BODY.replace(old, new, 1))


#: name -> file content of a malformed .seq (every one is refused by the reader: exit 2)
BAD_SEQ: dict[str, bytes] = {
    "empty": b"",
    "binary": b"\x89PNG\r\n\x1a\n\x00\x00",
    "not_pulseq": b"hello\n",
    "yaml_given_as_seq": SPEC.read_bytes(),
    "no_blocks": sign_text(BODY[: BODY.find(b"[BLOCKS]")]),
    "truncated": RAW[: len(RAW) // 2],
    "nan_duration": _seq(b" 2  30   0", b" 2  nan   0"),
    "negative_duration": _seq(b" 2  30   0", b" 2  -30   0"),
    "fractional_duration": _seq(b" 2  30   0", b" 2  30.5   0"),
    "negative_adc_delay": _seq(b"1 16 100000 0 0 0 0 0 0", b"1 16 100000 -20 0 0 0 0 0"),
    "negative_adc_samples": _seq(b"1 16 100000 0 0 0 0 0 0", b"1 -16 100000 0 0 0 0 0 0"),
    "negative_rf_delay": _seq(b"1      23.1481 1 2 3 900 100", b"1      23.1481 1 2 3 900 -100"),
    "inf_gradient": _seq(b"2       -1e+06", b"2       inf"),
    "overflow_gradient": _seq(b"2       -1e+06", b"2       -1e+306"),
    "rf_amplitude_1e12": _seq(b"1      23.1481", b"1      2.3e12"),
    "nan_shape_count": _seq(b"num_samples 2\n", b"num_samples nan\n"),
    "shape_count_1e12": _seq(b"num_samples 2\n", b"num_samples 1000000000000\n"),
    "block_duration_2e11_rasters": _seq(b" 1 200   1", b" 1 200000000000   1"),
    "adc_1e9_samples": _seq(b"1 16 100000 0 0 0 0 0 0", b"1 1000000000 100 0 0 0 0 0 0"),
    "missing_extension_list": _seq(b" 1 200   1   0   0   0  0  0", b" 1 200   1   0   0   0  0  5"),
    "missing_gradient": _seq(b" 2  30   0   1   2", b" 2  30   0  99   2"),
    "missing_shape": _seq(b"2       -1e+06            0            0 6 7 0", b"2 -1e+06 0 0 66 7 0"),
    "raster_zero": _seq(b"GradientRasterTime 1e-05", b"GradientRasterTime 0"),
    "raster_in_us": _seq(b"GradientRasterTime 1e-05", b"GradientRasterTime 10"),
    "version_1_3": _seq(b"minor 5", b"minor 3"),
    "unknown_rf_use": _seq(b"0 0 0 0 e\n2 ", b"0 0 0 0 q\n2 "),
    "bad_signature": RAW.replace(b"Kind gre", b"Kind grf"),
    "sha1_signature": RAW.replace(b"Type md5", b"Type sha1"),
    "crlf_resigned": sign_text(BODY.replace(b"\n", b"\r\n")),
}


def _with_rotation_extension() -> bytes:
    i = BODY.find(b"# Sequence Shapes")
    body = BODY[:i] + b"[EXTENSIONS]\n1 1 1 0\n\nextension ROTATIONS 1\n1 1 2 0 0\n\n" + BODY[i:]  # |q| != 1
    return sign_text(body.replace(b" 1 200   1   0   0   0  0  0", b" 1 200   1   0   0   0  0  1", 1))


BAD_SEQ["rotation_not_normalised"] = _with_rotation_extension()
#: check reads these without failing to parse and reports them as violations (exit 1)
CHECK_VIOLATION = {"bad_signature", "sha1_signature", "crlf_resigned"}


def _digest(folder: Path) -> dict[str, str]:
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


def _assert_clean_failure(capsys, tmp_path: Path, argv: list, code_expected: int = 2) -> str:
    before = _digest(tmp_path)
    code, out, err = run_cli(capsys, *argv)
    assert code == code_expected, (code, out[-500:], err)
    assert "Traceback" not in err and "unexpected" not in err, err
    lines = err.strip().splitlines()
    if code_expected == 2:
        assert len(lines) == 1 and lines[0].startswith("dtoc: error: "), err
    else:
        assert len(lines) <= 1, err
    assert _digest(tmp_path) == before, "a file was written or changed"
    return err


@pytest.mark.parametrize("name", sorted(BAD_SEQ))
def test_bad_seq_check(capsys, tmp_path, name):
    p = tmp_path / "in.seq"
    p.write_bytes(BAD_SEQ[name])
    _assert_clean_failure(capsys, tmp_path, ["check", p], 1 if name in CHECK_VIOLATION else 2)


@pytest.mark.parametrize("name", sorted(BAD_SEQ))
def test_bad_seq_predict(capsys, tmp_path, name):
    p = tmp_path / "in.seq"
    p.write_bytes(BAD_SEQ[name])
    _assert_clean_failure(capsys, tmp_path, ["predict", p, "--girf", GIRF, "--png", tmp_path / "p.png"])


@pytest.mark.parametrize("name", ["nan_duration", "block_duration_2e11_rasters", "adc_1e9_samples", "crlf_resigned"])
def test_bad_seq_simulate_and_optimize(capsys, tmp_path, name):
    p = tmp_path / "in.seq"
    p.write_bytes(BAD_SEQ[name])
    _assert_clean_failure(capsys, tmp_path, ["simulate", p, "--json", tmp_path / "s.json"])
    _assert_clean_failure(capsys, tmp_path, ["optimize", p, "--girf", GIRF, "-o", tmp_path / "o.seq"])


def _girf_file(tmp_path: Path, **change) -> Path:
    d = dict(np.load(GIRF))
    for k, v in change.items():
        if v is None:
            d.pop(k)
        else:
            d[k] = v
    p = tmp_path / "h.npz"
    np.savez(p, **d)
    return p


def _h_nan():
    h = np.load(GIRF)["h"].copy()
    h[0, 0, 5] = np.nan
    return h


BAD_GIRF: dict[str, Callable[[], dict]] = {
    "girf_nan": lambda: {"h": _h_nan()},
    "girf_wrong_shape": lambda: {"h": np.ones((2, 3, 16))},
    "girf_no_dt": lambda: {"dt": None},
    "girf_dt_negative": lambda: {"dt": np.array([-1e-5])},
    "girf_dt_in_us": lambda: {"dt": np.array([10.0])},
    "girf_h0_wrong_shape": lambda: {"h0": np.ones((2, 7))},
}


@pytest.mark.parametrize("name", sorted(BAD_GIRF))
def test_bad_girf_every_command(capsys, tmp_path, name):
    g = _girf_file(tmp_path, **BAD_GIRF[name]())
    _assert_clean_failure(capsys, tmp_path, ["girf", "show", g])
    _assert_clean_failure(capsys, tmp_path, ["predict", EPI, "--girf", g])
    _assert_clean_failure(capsys, tmp_path, ["optimize", EPI, "--girf", g, "-o", tmp_path / "o.seq"])


def _model(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "m.json"
    p.write_text(text)
    return p


BAD_MODEL = {
    "model_not_json": "{effects: [",
    "model_deep_nesting": "[" * 100000 + "]" * 100000,
    "model_unknown_kind": json.dumps({"effects": [{"kind": "wormhole", "params": {}}]}),
    "model_alpha_2": json.dumps(
        {"effects": [{"kind": "exp_eddy", "axis": "x", "params": {"alpha": 2, "tau_s": 1e-3}}]}
    ),
    "model_tau_nan": json.dumps(
        {"effects": [{"kind": "exp_eddy", "axis": "x", "params": {"alpha": 0.1, "tau_s": float("nan")}}]}
    ),
    "model_delay_in_us": json.dumps({"effects": [{"kind": "delay", "axis": "x", "params": {"seconds": 3.0}}]}),
}


@pytest.mark.parametrize("name", sorted(BAD_MODEL))
def test_bad_model(capsys, tmp_path, name):
    m = _model(tmp_path, BAD_MODEL[name])
    _assert_clean_failure(capsys, tmp_path, ["predict", EPI, "--model", m])
    _assert_clean_failure(capsys, tmp_path, ["simulate", EPI, "--model", m])


BAD_SPEC = {
    "spec_deep_nesting": "a: " + "[" * 100000 + "]" * 100000 + "\n",
    "spec_name_newline": SPEC.read_text().replace("name: epi_small", 'name: "epi\\n[BLOCKS]"'),
    "spec_negative_fov": SPEC.read_text().replace("fov_mm: 250", "fov_mm: -250"),
    "spec_unknown_key": SPEC.read_text() + "wormhole: 1\n",
    "spec_not_yaml": "kind: [epi\n",
}


@pytest.mark.parametrize("name", sorted(BAD_SPEC))
def test_bad_spec(capsys, tmp_path, name):
    s = tmp_path / "s.yaml"
    s.write_text(BAD_SPEC[name])
    _assert_clean_failure(capsys, tmp_path, ["build", s, "-o", tmp_path / "o.seq"])


def _measurement(tmp_path: Path, n: int = 2, m: int = 1, bad: str | None = None) -> Path:
    g = np.zeros((m, 3, n))
    g[:, 0, n // 2 :] = 1.0
    G = g.copy()
    if bad == "nan":
        G[0, 0, 0] = np.nan
    p = tmp_path / "meas.npz"
    np.savez(p, dt=np.array(1e-5), g=g, G=G)
    return p


@pytest.mark.parametrize("case", ["two_samples", "nan"])
def test_bad_measurement_girf_fit(capsys, tmp_path, case):
    meas = _measurement(tmp_path, bad="nan" if case == "nan" else None, n=2 if case == "two_samples" else 400)
    _assert_clean_failure(capsys, tmp_path, ["girf", "fit", meas, "-o", tmp_path / "h.npz"])


OPTION_CASES = {
    "gmax_nan": ["--gmax", "nan"],
    "smax_negative": ["--smax", "-130"],
    "b0_zero": ["--b0", "0"],
    "iters_negative": ["--iters", "-1"],
    "device_unknown": ["--device", "tpu"],
    "method_unknown": ["--method", "magic"],
    "no_hardware_model": None,
    "girf_and_ideal": ["--ideal"],
}


@pytest.mark.parametrize("name", sorted(OPTION_CASES))
def test_bad_optimize_options(capsys, tmp_path, name):
    extra = OPTION_CASES[name]
    hw = [] if extra is None else ["--girf", GIRF]
    _assert_clean_failure(capsys, tmp_path, ["optimize", EPI, *hw, *(extra or []), "-o", tmp_path / "o.seq"])


def test_outputs_that_would_destroy_an_input(capsys, tmp_path):
    base = tmp_path / "base.seq"
    base.write_bytes(EPI.read_bytes())
    g = tmp_path / "h.npz"
    g.write_bytes(GIRF.read_bytes())
    prof = tmp_path / "p.yaml"
    prof.write_text(
        (REPO / "scanners" / "kcl_terra_7T.yaml")
        .read_text()
        .replace("../../shared/data/girf/kcl_7T_terra_2024/7T_GIRF.mat", "h.npz")
    )
    for argv in (
        ["optimize", base, "--girf", g, "-o", tmp_path / "o.seq", "--json", base, "--force"],
        ["optimize", base, "--girf", g, "-o", tmp_path / "o.seq", "--png", tmp_path / "o.seq", "--force"],
        ["optimize", base, "--girf", g, "-o", base, "--force"],
        ["simulate", base, "--json", base, "--force"],
        ["predict", base, "--girf", g, "--png", g, "--force"],
        ["girf", "show", g, "--png", g, "--force"],
        ["girf", "show", g, "--json", g, "--force"],
        ["girf", "import", g, "-o", g, "--force"],
        ["check", base, "--json", base, "--force"],
        ["diff", base, base, "--json", base, "--force"],
        # a scanner profile and the GIRF it points at are inputs too
        ["check", base, "--scanner", prof, "--json", prof, "--force"],
        ["simulate", base, "--scanner", prof, "--json", g, "--force"],
        ["predict", base, "--scanner", prof, "--png", prof, "--force"],
        ["optimize", base, "--scanner", prof, "-o", tmp_path / "o.seq", "--json", g, "--force"],
        ["identify", base, "--scanner", prof, "-o", prof, "--force"],
    ):
        err = _assert_clean_failure(capsys, tmp_path, argv)
        assert "would overwrite" in err or "given for both" in err, err


def test_paths_that_are_not_files(capsys, tmp_path):
    _assert_clean_failure(capsys, tmp_path, ["check", "/dev/zero"])
    _assert_clean_failure(capsys, tmp_path, ["check", tmp_path])
    _assert_clean_failure(capsys, tmp_path, ["check", tmp_path / "missing.seq"])
    _assert_clean_failure(capsys, tmp_path, ["predict", EPI, "--girf", tmp_path / "missing.npz"])
    _assert_clean_failure(capsys, tmp_path, ["simulate", EPI, "--png", tmp_path / "no" / "dir" / "x.png"])
    _assert_clean_failure(capsys, tmp_path, ["build", SPEC, "-o", tmp_path])


def test_existing_output_is_not_overwritten(capsys, tmp_path):
    out = tmp_path / "o.seq"
    out.write_bytes(b"keep me")
    _assert_clean_failure(capsys, tmp_path, ["build", SPEC, "-o", out])
    _assert_clean_failure(capsys, tmp_path, ["optimize", EPI, "--girf", GIRF, "-o", out])


def test_the_corpus_is_large_enough():
    n = (
        2 * len(BAD_SEQ)
        + 2 * 4
        + 3 * len(BAD_GIRF)
        + 2 * len(BAD_MODEL)
        + len(BAD_SPEC)
        + 2
        + len(OPTION_CASES)
        + 10
        + 6
        + 2
    )
    assert n >= 60, n


def test_partial_vendor_girf_needs_an_explicit_flag(capsys, tmp_path, shared_data):
    mat = shared_data / "girf" / "kcl_7T_terra_2023" / "7T_1pcterms.mat"
    if not mat.exists():
        pytest.skip("../shared/data absent")
    err = _assert_clean_failure(capsys, tmp_path, ["girf", "import", mat, "-o", tmp_path / "h.npz"])
    assert "axis z is not in the GIRF" in err and "--partial" in err
    code, _, err = run_cli(capsys, "girf", "import", mat, "-o", tmp_path / "h.npz", "--partial")
    assert code == 0 and "axis z not in the file: ideal response" in err


def test_full_disk_is_one_line_and_leaves_nothing(capsys, tmp_path, monkeypatch):
    import errno
    import os

    import dtoc.util.atomic as atomic

    def full(fd):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(tmp_path))

    monkeypatch.setattr(atomic.os, "fsync", full)
    err = _assert_clean_failure(capsys, tmp_path, ["build", SPEC, "-o", tmp_path / "o.seq"])
    assert "No space left on device" in err
    err = _assert_clean_failure(
        capsys, tmp_path, ["girf", "show", GIRF, "--png", tmp_path / "g.png", "--json", tmp_path / "g.json"]
    )
    assert list(tmp_path.iterdir()) == []  # no temporary left behind either
