"""Slice orientation: the hardware model acts on the physical axes the prescription rotates the file's axes onto."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from cli_helpers import run_cli
from foreign.writers import epi

from dtoc.errors import InputError
from dtoc.hardware.model import HardwareModel, build_effect
from dtoc.hardware.orientation import NAMED, RotatedChain, logical_limit_scale, parse_orientation

REPO = Path(__file__).resolve().parents[1]


def _rot(ax: str, deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return {"x": np.array([[1, 0, 0], [0, c, -s], [0, s, c]]), "z": np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])}[ax]


OBLIQUE = _rot("z", 10) @ _rot("x", 15)
OBLIQUE_TEXT = " ".join(f"{x:.12g}" for x in OBLIQUE.ravel())


def test_parse_names_numbers_and_refusals():
    for name, R in NAMED.items():
        assert np.allclose(parse_orientation(name), R) and np.isclose(np.linalg.det(R), 1.0)
        assert logical_limit_scale(R) == 1.0  # a permutation with signs: limits unchanged
    assert np.allclose(parse_orientation(OBLIQUE_TEXT), OBLIQUE)
    assert logical_limit_scale(OBLIQUE) == pytest.approx(1 / np.abs(OBLIQUE).sum(1).max())
    for bad in ("axial", "1 2 3", "1 0 0 0 1 0 0 0 -1", "2 0 0 0 1 0 0 0 1", "nan 0 0 0 1 0 0 0 1"):
        with pytest.raises(InputError):
            parse_orientation(bad)


def test_a_delay_on_one_physical_axis_moves_to_the_logical_axis_played_there():
    # physical x delayed by 20 us; at 'sag' (logical z -> physical x) the logical z waveform is the delayed one
    model = HardwareModel([build_effect("delay", {"seconds": 20e-6}, axis="x")])
    dt = 5e-6
    g = torch.zeros(3, 200, dtype=torch.float64)
    g[:, 50:120] = torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)[:, None]
    G_tra, _ = model(g, dt)
    G_sag, _ = RotatedChain(model, NAMED["sag"])(g, dt)
    shift = lambda x: torch.roll(x, 4)  # noqa: E731  (20 us = 4 samples; zero-padded ends)
    assert torch.allclose(G_tra[0], shift(g[0])) and torch.allclose(G_tra[2], g[2])
    assert torch.allclose(G_sag[2], shift(g[2])) and torch.allclose(G_sag[0], g[0]) and torch.allclose(G_sag[1], g[1])
    # identity rotation: the model itself
    G_id, _ = RotatedChain(model, np.eye(3))(g, dt)
    assert torch.allclose(G_id, G_tra)


def test_optimized_for_an_oblique_slice_holds_there_not_elsewhere(tmp_path, capsys, shared_data):
    mat = shared_data / "girf" / "kcl_7T_terra_2024" / "7T_GIRF.mat"
    if not mat.exists():
        pytest.skip("the KCL 2024 GIRF is absent")
    import dtoc
    from dtoc.hardware.girf_import import import_girf
    from dtoc.hardware.girf_io import save_girf
    from dtoc.seq.load import load_sequence

    girf = tmp_path / "kcl.npz"
    save_girf(import_girf([mat]), girf)
    base = tmp_path / "epi.seq"
    base.write_bytes(epi())
    out = tmp_path / "obl.seq"
    argv = ["optimize", base, "--girf", girf, "--gmax", "45", "--smax", "180", "--orientation", OBLIQUE_TEXT]
    code, _, err = run_cli(capsys, *argv, "-o", out, "--json", tmp_path / "m.json", "-q")
    assert code == 0, err
    m = json.loads((tmp_path / "m.json").read_text())
    assert np.allclose(m["orientation"]["R_logical_to_physical"], OBLIQUE)
    # the limits hold on the physical axes (and the logical ones), no longer a conservative logical bound
    assert m["limits"]["gmax_mT_per_m"] == 45 and m["limits"]["physical_gmax_mT_per_m"] == 45
    assert "physical" in m["limits"]["source"]["gmax_mT_per_m"]
    h = dtoc.load_model(girf=str(girf))
    b, o = load_sequence(base), load_sequence(out)
    k0, dk = b.nominal_kspace_rad_per_m(), b.dk_rad_per_m
    fin = np.isfinite(dk)

    def err_dk(ir, chain):
        k = dtoc.Twin(ir, chain).forward().kspace_rad_per_m.detach().numpy()
        return float(np.max(np.abs(k[fin] - k0[fin]) / dk[fin, None]))

    at_oblique = err_dk(o, RotatedChain(h, OBLIQUE))
    at_tra = err_dk(o, h)
    assert at_oblique < 0.05 and at_tra > 3 * at_oblique, (at_oblique, at_tra)
    # every physical axis within the physical limit at that orientation
    g_phys = OBLIQUE @ o.grad_mT_per_m
    assert np.abs(g_phys).max() <= 45 * (1 + 1e-6)
    # check warns when the file is checked for another orientation, and not for its own
    code, _, err = run_cli(capsys, "check", out, "--gmax", "45", "--smax", "180", "--orientation", "tra")
    assert code == 0 and "compiled for orientation" in err
    code, _, err = run_cli(capsys, "check", out, "--gmax", "45", "--smax", "180", "--orientation", OBLIQUE_TEXT)
    assert code == 0 and "orientation" not in err
