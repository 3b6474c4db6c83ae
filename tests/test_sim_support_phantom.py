"""Built-in brain phantom, rotation and .npz phantom files (dtoc.sim.phantom)."""

from __future__ import annotations

import numpy as np
import pytest

from dtoc.errors import InputError
from dtoc.sim import phantom as P


def _class_means(p: P.Phantom):
    """T1 of voxels that are (almost) pure tissue, keyed by T1 value found."""
    pure = p.pd > 0
    return np.unique(np.round(p.t1_s[pure], 6))


def test_brain_tissue_values_3T_and_7T():
    for field in (3.0, 7.0):
        tab = P.TISSUE_PARAMS[field]
        p = P.brain_phantom(128, field_T=field, oversample=4)
        # pure voxels carry exactly the table values (e.g. deep WM / GM / ventricle CSF)
        for name in ("wm", "gm", "csf"):
            pd, t1, t2, t2d, d = tab[name]
            hit = (np.abs(p.t1_s - t1) < 1e-9) & (np.abs(p.pd - pd) < 1e-9)
            assert hit.sum() > 20, (field, name)
            assert (
                np.allclose(p.t2_s[hit], t2) and np.allclose(p.t2dash_s[hit], t2d) and np.allclose(p.d_m2_per_s[hit], d)
            )
    # physics sanity of the table: T2 < T2* ... T2 << T1, T1 grows and T2 shrinks with field
    for name in ("wm", "gm", "csf", "fat"):
        a, b = P.TISSUE_PARAMS[3.0][name], P.TISSUE_PARAMS[7.0][name]
        assert a[2] < a[1] and b[2] < b[1]
        assert b[1] >= a[1] and b[2] <= a[2]
    # contrast order: T1(WM) < T1(GM) < T1(CSF); PD(WM) < PD(GM) < PD(CSF)
    t = P.TISSUE_PARAMS[3.0]
    assert t["wm"][1] < t["gm"][1] < t["csf"][1] and t["wm"][0] < t["gm"][0] < t["csf"][0]


def test_brain_geometry_any_matrix_and_deterministic():
    a = P.brain_phantom(64, fov_m=0.25)
    b = P.brain_phantom(64, fov_m=0.25)
    assert all(np.array_equal(getattr(a, k), getattr(b, k)) for k in P.MAP_KEYS)
    c = P.brain_phantom(64, seed=3)
    assert not np.array_equal(a.pd, c.pd)  # seed changes the folding
    r = P.brain_phantom((24, 40), fov_m=(0.3, 0.18))
    assert r.shape == (24, 40) and r.fov_m == (0.3, 0.18)
    # head occupies ~85 % of the FOV along y and is background at the FOV edge
    assert a.pd[0].max() == 0 and a.pd[:, 0].max() == 0
    rows = np.where(a.pd.max(axis=1) > 0)[0]
    assert 0.8 < (rows[-1] - rows[0] + 1) / 64 < 0.95
    assert np.all(np.isinf(a.t1_s[a.pd == 0])) and np.all(a.t1_s[a.pd > 0] < 5)


def test_brain_without_scalp_keeps_the_brain_and_quiets_the_kspace_edge():
    """``scalp=False`` (the paper's kind of phantom: BrainWeb GM / WM / CSF only) drops the extracranial
    fat and the skull and nothing else; the bright one-voxel fat ring is what carries the head's k-space
    edge energy.  Measured at 32x32 on a T1-weighted proxy PD (1 - exp(-TR/T1)), TR 10 ms: Nyquist column
    energy 0.99 % of the total with the scalp, 0.040 % without."""
    head = P.brain_phantom(32, fov_m=0.032)
    brain = P.brain_phantom(32, fov_m=0.032, scalp=False)
    t = P.TISSUE_PARAMS[3.0]
    brain_t1 = min(t[k][1] for k in ("csf", "gm", "wm", "lesion"))
    assert head.t1_s[head.pd > 0].min() < brain_t1 - 0.1  # fat is there ...
    assert brain.t1_s[brain.pd > 0].min() >= brain_t1 - 1e-12  # ... and gone, with the skull
    assert 0 < (brain.pd > 0).sum() < (head.pd > 0).sum()
    # voxels without fat or skull content are untouched
    same = (brain.pd > 0) & (head.t1_s == brain.t1_s)
    assert same.sum() > 0.8 * (brain.pd > 0).sum()
    assert np.array_equal(head.pd[same], brain.pd[same])

    def nyquist_fraction(p):
        m = p.pd * (1 - np.exp(-0.01 / p.t1_s))
        e = np.abs(np.fft.fftshift(np.fft.fft2(m))) ** 2
        return e[:, 0].sum() / e.sum()

    assert nyquist_fraction(head) > 10 * nyquist_fraction(brain)


def test_resolve_phantom_specs():
    a = P.resolve_phantom("brain-noscalp:16", fov_m=(0.032, 0.032))
    b = P.brain_phantom(16, fov_m=0.032, scalp=False)
    assert a.shape == (16, 16) and np.array_equal(a.pd, b.pd)
    assert np.array_equal(
        P.resolve_phantom(None, matrix=(16, 16), fov_m=(0.032, 0.032)).pd, P.brain_phantom(16, fov_m=0.032).pd
    )
    with pytest.raises(InputError, match="brain-noscalp:N"):
        P.resolve_phantom("brain-noscalp:x", fov_m=(0.032, 0.032))
    with pytest.raises(InputError, match="matrix unknown"):
        P.resolve_phantom("brain-noscalp", fov_m=(0.032, 0.032))


def test_area_averaging_is_consistent_across_resolutions():
    # Voxel i of an n-matrix is centred at (i - n/2) dx (the FFT positions), so coarse and fine voxels do
    # not nest; what box averaging guarantees is (1) the proton content per area is independent of the
    # matrix and (2) each voxel holds the area mean of the tissue inside it.
    hi = P.brain_phantom(64, oversample=16)
    lo = P.brain_phantom(32, oversample=32)
    assert lo.pd.sum() * 4 == pytest.approx(hi.pd.sum(), rel=1e-9)
    # (2) at boundary voxels: compare with an independent 200 x 200 point average over the voxel area
    tab = P.TISSUE_PARAMS[3.0]
    for iy, ix in [(2, 16), (16, 4), (10, 21)]:
        assert 0 < lo.pd[iy, ix] < 1.0
        sub = (np.arange(200) + 0.5) / 200 - 0.5
        u = (ix - 16 + sub) * 2 / 32
        v = (iy - 16 + sub) * 2 / 32
        vv, uu = np.meshgrid(v, u, indexing="ij")
        lab = P.label_map(uu, vv, 0, True)
        pd_ref = np.mean([tab[P.TISSUES[t]][0] if t else 0.0 for t in lab.ravel()])
        assert lo.pd[iy, ix] == pytest.approx(pd_ref, abs=0.01)
    assert np.sum((lo.pd > 0.06) & (lo.pd < 0.68)) > 10  # partial voxels on boundaries, no hard aliasing edges


def test_b0_b1_maps():
    p3 = P.brain_phantom(64, field_T=3.0, b0=True, b1=True)
    p7 = P.brain_phantom(64, field_T=7.0, b0=True, b1=True)
    assert np.ptp(p7.b0_hz) == pytest.approx(7 / 3 * np.ptp(p3.b0_hz), rel=1e-12)
    assert 10 < np.ptp(p3.b0_hz) < 200  # tens of Hz at 3 T
    assert 0.85 < p3.b1.min() and p3.b1.max() < 1.15 and np.ptp(p7.b1) > 2 * np.ptp(p3.b1)
    q = P.brain_phantom(64)
    assert np.all(q.b0_hz == 0) and np.all(q.b1 == 1)


def test_rotate():
    p = P.brain_phantom(48, b0=True)
    assert np.array_equal(P.rotate(p, 0).pd, p.pd) and np.array_equal(P.rotate(p, 360).pd, p.pd)
    r90 = P.rotate(p, 90)
    # counter-clockwise: the voxel at (x, y) moves to (-y, x); pixel (iy, ix) <- (ny - ix, iy - ny/2 + nx/2)
    n = 48
    for iy, ix in [(10, 30), (24, 5), (40, 20)]:
        x, y = ix - n / 2, iy - n / 2
        src_x, src_y = y, -x  # R(-90) applied to (x, y)
        assert r90.pd[iy, ix] == pytest.approx(p.pd[int(src_y + n / 2), int(src_x + n / 2)], abs=1e-12)
    # four quarter turns give back the phantom (up to the row/column that leaves the FOV)
    r360 = P.rotate(P.rotate(r90, 90), 180)
    assert np.allclose(r360.pd[1:, 1:], p.pd[1:, 1:], atol=1e-12)
    # arbitrary angle: deterministic, mass conserved, no new tissue values outside the table's range
    a, b = P.rotate(p, 17.0), P.rotate(p, 17.0)
    assert np.array_equal(a.t2_s, b.t2_s)
    assert a.pd.sum() == pytest.approx(p.pd.sum(), rel=0.01)
    m = a.pd > 0
    assert a.t1_s[m].min() >= p.t1_s[p.pd > 0].min() - 1e-9 and a.t1_s[m].max() <= p.t1_s[p.pd > 0].max() + 1e-9
    P.validate_phantom(a)


def test_npz_roundtrip_and_byte_identical(tmp_path):
    p = P.brain_phantom(16, b0=True, b1=True)
    f1, f2 = tmp_path / "a.npz", tmp_path / "b.npz"
    P.save_phantom(p, f1)
    P.save_phantom(p, f2)
    assert f1.read_bytes() == f2.read_bytes()
    q = P.load_phantom(f1)
    assert all(np.array_equal(getattr(p, k), getattr(q, k)) for k in P.MAP_KEYS) and q.fov_m == p.fov_m
    with pytest.raises(InputError, match="output exists"):
        P.save_phantom(p, f1)


def _write(path, **arrays):
    np.savez(path, **arrays)
    return path


@pytest.mark.parametrize(
    "mutate,msg",
    [
        (lambda d: d.pop("t1_s"), r"missing key\(s\) t1_s"),
        (lambda d: d.pop("fov_m"), r"missing key\(s\) fov_m"),
        (lambda d: d.__setitem__("t1_s", -np.ones((4, 4))), r"'t1_s' must be > 0"),
        (lambda d: d.__setitem__("t2_s", np.ones((4, 5))), r"'t2_s' has shape \(4, 5\), expected \(4, 4\)"),
        (lambda d: d.__setitem__("pd", np.ones(4)), r"'pd' has shape \(4,\), expected \(ny, nx\)"),
        (lambda d: d.__setitem__("pd", -np.ones((4, 4))), r"'pd' must be finite and >= 0"),
        (lambda d: d.__setitem__("fov_m", np.array([-1.0])), r"'fov_m'"),
        (lambda d: d.__setitem__("d_m2_per_s", np.full((4, 4), 1e-3)), "implausible"),
    ],
)
def test_bad_npz_one_line_errors(tmp_path, mutate, msg):
    d = {"pd": np.ones((4, 4)), "t1_s": np.ones((4, 4)), "t2_s": np.full((4, 4), 0.1), "fov_m": np.array(0.1)}
    mutate(d)
    f = _write(tmp_path / "p.npz", **d)
    with pytest.raises(InputError, match=msg) as e:
        P.load_phantom(f)
    assert "\n" not in str(e.value) and str(f) in str(e.value)


def test_npz_defaults_and_unreadable(tmp_path):
    f = _write(
        tmp_path / "p.npz", pd=np.ones((3, 2)), t1_s=np.ones((3, 2)), t2_s=np.ones((3, 2)), fov_m=np.array([0.2, 0.3])
    )
    q = P.load_phantom(f)
    assert np.all(np.isinf(q.t2dash_s)) and np.all(q.d_m2_per_s == 0) and np.all(q.b1 == 1) and q.fov_m == (0.2, 0.3)
    bad = tmp_path / "x.npz"
    bad.write_bytes(b"not a zip")
    with pytest.raises(InputError, match="not a readable .npz"):
        P.load_phantom(bad)
    with pytest.raises(InputError, match="not found"):
        P.load_phantom(tmp_path / "nope.npz")
