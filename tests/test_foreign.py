"""Sequences dtoc did not write (tests/foreign/writers.py: pypulseq scripts in the users' style, no FOV/matrix or
limit definitions, RF with the writers' default use 'undefined'): read, checked, simulated, predicted and
optimized like dtoc's own, with the limits given and never assumed."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import run_cli
from foreign.writers import epi, gre

from bench.foreign import pypulseq_checks
from dtoc.seq.geometry import infer_cartesian_grid

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("foreign")
    (d / "gre.seq").write_bytes(gre())
    (d / "epi.seq").write_bytes(epi())
    return d


@pytest.fixture(scope="module")
def kcl_girf(tmp_path_factory, shared_data):
    mat = shared_data / "girf" / "kcl_7T_terra_2024" / "7T_GIRF.mat"
    if not mat.exists():
        pytest.skip("the KCL 2024 GIRF is absent")
    from dtoc.hardware.girf_import import import_girf
    from dtoc.hardware.girf_io import save_girf

    p = tmp_path_factory.mktemp("girf") / "kcl2024.npz"
    save_girf(import_girf([mat]), p)
    return p


def test_reader_notes_the_undefined_rf_use_and_infers_the_grid(files, capsys):
    from dtoc.seq.load import load_sequence

    ir = load_sequence(files / "gre.seq")
    assert all(r.use == "undefined" and r.excites for r in ir.rf)
    # as pypulseq's calculate_kspace: k = 0 right after every (undefined-use) excitation
    k_ref = _pypulseq_kspace_at_adc(files / "gre.seq")
    np.testing.assert_allclose(ir.nominal_kspace_rad_per_m(), k_ref, atol=1e-6 * np.abs(k_ref).max())
    geo = ir.geometry
    assert geo is not None and geo.matrix_readout_phase == (32, 32) and (geo.readout_axis, geo.phase_axis) == (0, 1)
    assert geo.fov_m[0] == pytest.approx(0.22, rel=1e-5) and geo.fov_m[1] == pytest.approx(0.22, rel=1e-5)
    assert ir.kind == "gre" and abs(ir.meta["grid_offset_dk"][0]) == pytest.approx(0.5, abs=1e-4)
    assert 2 not in np.flatnonzero(ir.free_mask.any(axis=1))  # the slice axis is held
    notes = " ".join(ir.meta["notes"])
    assert "use 'undefined': 32, taken as excitations" in notes and "grid inferred" in notes
    assert load_sequence(files / "epi.seq").kind == "epi"


def _pypulseq_kspace_at_adc(path: Path) -> np.ndarray:
    import pypulseq as pp

    from dtoc.seq.pulseq import quiet

    s = pp.Sequence()
    with quiet():
        s.read(str(path))
        k_adc = s.calculate_kspace()[0]  # (3, N_adc) in 1/m
    return 2 * math.pi * np.asarray(k_adc)


def test_check_refuses_to_assume_limits(files, capsys):
    code, out, err = run_cli(capsys, "check", files / "gre.seq")
    assert code == 2 and err.count("\n") == 1 and "limits are never assumed" in err and out == ""
    code, out, err = run_cli(capsys, "check", files / "gre.seq", "--gmax", "32")
    assert code == 2 and "give --smax too" in err
    code, out, _ = run_cli(capsys, "check", files / "gre.seq", "--gmax", "32", "--smax", "130")
    assert code == 0 and "32 mT/m, 130 T/m/s" in out


def test_optimize_refuses_to_assume_limits(files, capsys, tmp_path):
    code, _, err = run_cli(capsys, "optimize", files / "epi.seq", "--ideal", "-o", tmp_path / "o.seq")
    assert code == 2 and "limits are never assumed" in err and not (tmp_path / "o.seq").exists()


@pytest.mark.parametrize("name", ["gre", "epi"])
def test_optimize_foreign_file_with_a_real_girf(files, kcl_girf, tmp_path, capsys, name):
    out, man = tmp_path / "o.seq", tmp_path / "o.json"
    argv = ["optimize", files / f"{name}.seq", "--girf", kcl_girf, "--gmax", "32", "--smax", "130"]
    code, _, err = run_cli(capsys, *argv, "-o", out, "--json", man, "-q")
    assert code == 0, err
    m = json.loads(man.read_text())
    b, a = m["before"], m["after"]
    assert a["kspace_max_error_dk"] < 0.05 < b["kspace_max_error_dk"]
    assert a["nrmse_percent"] < 0.5 * b["nrmse_percent"]
    if name == "epi":
        assert a["ghost_ratio_excess_percent"] < 0.05 < b["ghost_ratio_excess_percent"]
    assert any("grid inferred" in n for n in m["sequence"]["notes"])
    assert m["limits"]["source"] == {"gmax_mT_per_m": "--gmax", "smax_T_per_m_per_s": "--smax"}
    code, out_txt, _ = run_cli(capsys, "check", out, "--gmax", "32", "--smax", "130")
    assert code == 0 and "OK: no violations" in out_txt
    timing_ok, slew = pypulseq_checks(out)  # pypulseq decodes the shapes, numpy differentiates
    assert timing_ok and slew <= 130 * (1 + 1e-6)
    # only gradients changed: RF, ADC and block durations are the base's
    code, d_out, _ = run_cli(capsys, "diff", files / f"{name}.seq", out, "--json", "-")
    whats = {d["what"] for d in json.loads(d_out)["differences"]}
    assert whats and all(w.startswith(("grad", "definition", "shape")) for w in whats), whats


def _grid(k_lines: list[np.ndarray]):
    k = np.concatenate(k_lines, axis=1)
    return infer_cartesian_grid(k, [x.shape[1] for x in k_lines])


def _cartesian(nro, npe, dk, ro_offset=0.0, pe_index=None):
    pe_index = np.arange(npe) - npe // 2 if pe_index is None else pe_index
    lines = []
    for j in pe_index:
        kx = (np.arange(nro) - nro // 2 + ro_offset) * dk
        lines.append(np.stack([kx, np.full(nro, j * dk), np.zeros(nro)]))
    return lines


@pytest.mark.parametrize(
    "nro, npe, offset, want",
    [(64, 64, 0.0, (64, 64)), (64, 48, 0.5, (64, 48)), (63, 63, 0.0, (63, 63)), (64, 64, -0.5, (64, 64))],
)
def test_grid_inference_layouts(nro, npe, offset, want):
    dk = 2 * math.pi / 0.24
    g = _grid(_cartesian(nro, npe, dk, offset, None if npe % 2 == 0 else np.arange(npe) - npe // 2))
    assert g is not None and g.matrix_readout_phase == want
    assert g.fov_m[0] == pytest.approx(0.24, rel=1e-9) and g.fov_m[1] == pytest.approx(0.24, rel=1e-9)
    assert abs(abs(g.offset_dk[0]) - abs(offset)) < 1e-9


def test_grid_inference_partial_fourier_and_non_cartesian():
    dk = 2 * math.pi / 0.2
    g = _grid(_cartesian(64, 40, dk, 0.0, np.arange(-32, 8)))  # 5/8 partial Fourier along phase
    assert g is not None and g.matrix_readout_phase == (64, 64)
    # radial spokes: k moves on two axes within a readout
    spokes = []
    for th in np.linspace(0, np.pi, 16, endpoint=False):
        r = (np.arange(64) - 32) * dk
        spokes.append(np.stack([r * np.cos(th), r * np.sin(th), np.zeros(64)]))
    assert _grid(spokes) is None
    # ramp sampling: a non-uniform readout is not a grid
    ramp = _cartesian(64, 8, dk)
    for line in ramp:
        line[0] = np.sinh(line[0] / (40 * dk)) * 40 * dk
    assert _grid(ramp) is None
