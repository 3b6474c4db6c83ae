"""3D-encoded sequences: the 3D grid read off the ADC k, the 3D phantom, the simulator's z phase, the 3D iFFT,
and the image term of `simulate` / `optimize` on a 3D phantom (docs/foreign.md, docs/simulator.md)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from dtoc.errors import InputError
from dtoc.seq.geometry import infer_cartesian_grid, infer_cartesian_grid_3d
from dtoc.seq.load import load_sequence
from dtoc.sim import recon
from dtoc.sim.pdg import PDGConfig, simulate
from dtoc.sim.phantom import Phantom, brain_phantom, brain_phantom_3d, load_phantom, phantom_for, save_phantom


@pytest.fixture(scope="module")
def gre3d_path(tmp_path_factory):
    from tests.foreign.writers import gre3d

    p = tmp_path_factory.mktemp("g3") / "gre3d.seq"
    p.write_bytes(gre3d(n=8, nz=4, fov=0.2, fovz=0.06))
    return p


@pytest.fixture(scope="module")
def ir3(gre3d_path):
    return load_sequence(gre3d_path)


def test_3d_grid_is_read_off_the_adc_k(ir3):
    g = ir3.meta["grid3d"]
    assert g["matrix_xyz"] == [8, 8, 4] and g["readout_axis"] == 0
    assert np.allclose(g["fov_m"], [0.2, 0.2, 0.06], rtol=1e-5)
    # pypulseq's readout has its centre half a sample off the grid: the x offset; y and z on the grid
    assert abs(abs(g["offset_dk"][0]) - 0.5) < 1e-3 and max(abs(g["offset_dk"][1]), abs(g["offset_dk"][2])) < 1e-3
    assert ir3.geometry is None and np.allclose(ir3.dk_rad_per_m, 2 * np.pi / np.asarray(g["fov_m"]))
    k0 = ir3.nominal_kspace_rad_per_m()
    sizes = [a.num_samples for a in ir3.adc]
    assert infer_cartesian_grid(k0, sizes) is None  # not a 2D grid
    # a 2D layout (z constant) is not 3D; a spiral-like one (two axes within a readout) is neither
    k2 = k0.copy()
    k2[2] = 0.0
    assert infer_cartesian_grid_3d(k2, sizes) is None
    k3 = k0.copy()
    k3[1] += 0.3 * k0[0]
    assert infer_cartesian_grid_3d(k3, sizes) is None


def test_brain_phantom_3d_is_a_head_and_round_trips(tmp_path):
    ph = brain_phantom_3d((16, 16, 8), (0.22, 0.22, 0.16))
    assert ph.shape == (8, 16, 16) and ph.is_3d and ph.voxel_size_z_m == pytest.approx(0.02)
    s = ph.pd.sum(axis=(1, 2))
    assert s[0] == 0.0 and s[4] == s.max() and np.allclose(s[1:4], s[5:8][::-1])  # symmetric about z = 0
    # the central slice is the axial section of the 2D phantom (box-averaged on a finer sub-grid)
    c2 = brain_phantom(16, fov_m=0.22).pd
    assert np.corrcoef(ph.pd[4].ravel(), c2.ravel())[0, 1] > 0.98
    p = save_phantom(ph, tmp_path / "h3.npz")
    back = load_phantom(p)
    assert back.shape == ph.shape and back.fov_m == ph.fov_m and np.array_equal(back.pd, ph.pd)
    bad = tmp_path / "bad.npz"
    np.savez(bad, pd=ph.pd, t1_s=ph.t1_s, t2_s=ph.t2_s, fov_m=[0.22, 0.22])
    with pytest.raises(InputError, match=r"\(fov_x, fov_y, fov_z\)"):
        load_phantom(bad)


def test_z_phase_is_exp_minus_i_kz_z(ir3):
    """A single voxel moved by dz: every sample's signal turns by exp(-i kz dz), kz the nominal k (ideal
    gradients), in the direct and matrix-product evaluations; the moved voxel changes nothing else."""
    n = (4, 8, 8)

    def one_voxel(iz):
        pd = np.zeros(n)
        pd[iz, 5, 2] = 1.0
        return Phantom(
            pd, np.full(n, 1.0), np.full(n, 1e-3), np.full(n, np.inf), np.zeros(n), np.zeros(n), np.ones(n),
            (0.2, 0.2, 0.06), voxel_shape="none",
        )  # fmt: skip

    k0 = ir3.nominal_kspace_rad_per_m()
    dz = 0.06 / 4
    for method in ("direct", "gemm"):
        cfg = PDGConfig(signal_method=method)
        a = simulate(ir3, one_voxel(1), config=cfg)[0].numpy()
        b = simulate(ir3, one_voxel(3), config=cfg)[0].numpy()
        want = a * np.exp(-1j * k0[2] * (2 * dz))
        assert np.max(np.abs(b - want)) < 2e-3 * np.max(np.abs(a)), method


def test_3d_phantom_in_the_z0_plane_equals_the_2d_phantom(ir3):
    """k_z z = 0 in the plane z = 0: a 3D phantom holding a 2D one in its central slice gives the 2D signal."""
    p2 = brain_phantom(8, fov_m=0.2)
    p2.voxel_shape = "none"
    maps = {}
    for k in ("pd", "t1_s", "t2_s", "t2dash_s", "d_m2_per_s", "b0_hz", "b1"):
        a = getattr(p2, k)
        fill = {"pd": 0.0, "t1_s": np.inf, "t2_s": np.inf, "t2dash_s": np.inf, "b1": 1.0}.get(k, 0.0)
        m = np.full((4, 8, 8), fill)
        m[2] = a  # z = (2 - 4/2) dz = 0
        maps[k] = m
    p3 = Phantom(**maps, fov_m=(0.2, 0.2, 0.06), voxel_shape="none")
    s2 = simulate(ir3, p2)
    s3 = simulate(ir3, p3)
    assert torch.allclose(s3, s2, rtol=0, atol=1e-12 * float(s2.abs().max()))


def test_3d_ifft_puts_every_voxel_where_the_phantom_has_it(ir3):
    """Synthetic samples s_i = sum_v m_v exp(-i k_i . r_v) at the sequence's nominal k: the 3D reconstruction
    returns |m| voxel for voxel (the half-sample readout offset only adds a linear phase)."""
    rng = np.random.default_rng(3)
    m = rng.uniform(0.2, 1.0, (4, 8, 8))
    ph = brain_phantom_3d((8, 8, 4), (0.2, 0.2, 0.06))
    xyz = ph.axis_positions_m()
    zz, yy, xx = np.meshgrid(xyz[2], xyz[1], xyz[0], indexing="ij")
    k0 = ir3.nominal_kspace_rad_per_m()
    E = np.exp(-1j * (np.outer(k0[0], xx.ravel()) + np.outer(k0[1], yy.ravel()) + np.outer(k0[2], zz.ravel())))
    s = torch.as_tensor(E @ m.ravel())[None]
    img = recon.reconstruct(s, ir3)
    assert img.shape == (4, 8, 8)
    assert np.allclose(img.abs().numpy(), m, atol=1e-10)


def test_simulated_image_of_the_3d_head(ir3):
    ph = phantom_for(ir3, "brain3d")
    img = recon.reconstruct(simulate(ir3, ph), ir3).abs().numpy()
    for z in range(4):  # T1-weighted PD: the head's section in every slice, where the phantom has it
        assert np.corrcoef(img[z].ravel(), ph.pd[z].ravel())[0, 1] > 0.95
    # the ellipsoid: the edge slice holds a small section, the central one the largest
    e, p = img.sum(axis=(1, 2)), ph.pd.sum(axis=(1, 2))
    assert np.argmax(e) == np.argmax(p) == 2 and e[0] < 0.5 * e[2] and p[0] < 0.5 * p[2]


def test_a_2d_phantom_on_a_3d_sequence_is_refused(ir3):
    from dtoc.sim.comparison import compare_ideal_realized

    with pytest.raises(InputError, match="3D-encoded"):
        compare_ideal_realized(ir3, brain_phantom(8, fov_m=0.2))


def test_simulate_and_optimize_cli_image_term_on_the_3d_head(gre3d_path, tmp_path, capsys):
    from tests.cli_helpers import run_cli

    js = tmp_path / "s.json"
    code, _, err = run_cli(capsys, "simulate", gre3d_path, "--girf", "girf/example_7T.npz", "--json", js, "-q")
    assert code == 0, err
    rep = json.loads(js.read_text())
    assert rep["phantom"]["source"] == "brain3d" and rep["phantom"]["shape"] == [4, 8, 8]
    assert rep["sequence"]["matrix"] == [8, 8, 4] and rep["nrmse_percent"] > 0.1
    cfg = tmp_path / "c.yaml"
    cfg.write_text("warm_iters: 40\niters: 0\nn_dummies: 20\n")
    o, m = tmp_path / "o.seq", tmp_path / "m.json"
    code, _, err = run_cli(
        capsys,
        "optimize", gre3d_path, "--girf", "girf/example_7T.npz", "--gmax", "32", "--smax", "130",
        "--phantom", "brain3d", "--config", cfg, "-o", o, "--json", m, "-q",
    )  # fmt: skip
    assert code == 0, err
    man = json.loads(m.read_text())
    assert man["sequence"]["image_term"] is True
    assert man["after"]["nrmse_percent"] < 0.25 * man["before"]["nrmse_percent"]
    assert man["after"]["kspace_max_error_dk"] < 0.1 * man["before"]["kspace_max_error_dk"]
    # without a 3D phantom: k-space terms only
    m2 = tmp_path / "m2.json"
    code, _, err = run_cli(
        capsys,
        "optimize", gre3d_path, "--girf", "girf/example_7T.npz", "--gmax", "32", "--smax", "130",
        "--config", cfg, "-o", tmp_path / "o2.seq", "--json", m2, "-q",
    )  # fmt: skip
    assert code == 0, err
    assert json.loads(m2.read_text())["sequence"]["image_term"] is False


def test_a_phantom_of_the_wrong_dimension_is_refused_by_the_cli(gre3d_path, tmp_path, capsys):
    """One line and exit 2, no output written: a 2D phantom on a 3D file (simulate and optimize: a given phantom
    is never silently ignored) and the built-in 3D head on a 2D file."""
    from tests.cli_helpers import run_cli
    from tests.foreign.writers import gre

    p2 = tmp_path / "p2.npz"
    save_phantom(brain_phantom(8, fov_m=0.2), p2)
    g2 = tmp_path / "gre.seq"
    g2.write_bytes(gre(n=8))
    lim = ("--girf", "girf/example_7T.npz", "--gmax", "32", "--smax", "130")
    cases = [
        (("simulate", gre3d_path, "--phantom", p2), "needs a 3D phantom"),
        (("simulate", gre3d_path, "--phantom", "brain"), "needs a 3D phantom"),
        (("optimize", gre3d_path, *lim, "--phantom", p2, "-o", tmp_path / "a.seq"), "needs a 3D phantom"),
        (("simulate", g2, "--phantom", "brain3d"), "needs a 3D-encoded sequence"),
        (("optimize", g2, *lim, "--phantom", "brain3d", "-o", tmp_path / "b.seq"), "needs a 3D-encoded sequence"),
    ]
    for argv, msg in cases:
        code, _, err = run_cli(capsys, *argv, "-q")
        lines = [ln for ln in err.strip().splitlines() if not ln.startswith("note:")]
        assert code == 2 and len(lines) == 1 and msg in lines[0], (argv, err)
    assert not (tmp_path / "a.seq").exists() and not (tmp_path / "b.seq").exists()
