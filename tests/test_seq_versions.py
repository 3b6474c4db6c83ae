"""Pulseq format versions (docs/contracts.md §1, "Format versions"): every released text layout read, the
version the interpreter reads written, the 1.5.1 extensions, edge values of 1.4.0 arbitrary gradients, and
a file that cannot be written in the target version refused before any work.

All files come from our own writers (tests/foreign/writers.py): pypulseq scripts written as 1.5.0, rewritten
in the older layouts, and hand-written files for what pypulseq cannot write (1.4.0 spirals, 1.5.1
oversampling and rotations)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import run_cli
from foreign.writers import as_version, epi, gre, oversampled_151, radial, spiral_140_ending_on_zero

from dtoc.constants import hz_per_m_from_mT_per_m
from dtoc.errors import InputError
from dtoc.seq.check import check_file
from dtoc.seq.ir import edges_to_fine
from dtoc.seq.read import read_seq
from dtoc.seq.system import SystemSpec
from dtoc.seq.write import seq_bytes_of, unwritable

REPO = Path(__file__).resolve().parents[1]
GIRF = REPO / "girf" / "example_7T.npz"


def _version_of(data: bytes) -> str:
    t = data.decode()
    i = t.index("[VERSION]")
    vals = dict(ln.split() for ln in t[i:].split("\n")[1:4])
    return f"{vals['major']}.{vals['minor']}.{vals['revision']}"


@pytest.fixture(scope="module")
def gre15(tmp_path_factory):
    d = tmp_path_factory.mktemp("versions")
    p = d / "gre15.seq"
    p.write_bytes(gre(n=16))
    return p


@pytest.mark.parametrize("version", ["1.2.0", "1.2.1", "1.3.0", "1.3.1", "1.4.0", "1.4.1"])
def test_every_older_layout_reads_as_the_original(gre15, tmp_path, version):
    """The same GRE in each older layout (delays instead of durations, no time shapes, compressed shapes, no
    extension column in 1.2.x) plays the same gradients, RF centres and ADC samples."""
    ref = read_seq(gre15)
    p = tmp_path / f"gre_{version}.seq"
    p.write_bytes(as_version(gre15.read_bytes(), version))
    assert _version_of(p.read_bytes()) == version
    ir = read_seq(p)
    assert ir.meta["format_version"] == version
    assert ir.grad_mT_per_m.shape == ref.grad_mT_per_m.shape
    assert np.abs(ir.grad_mT_per_m - ref.grad_mT_per_m).max() <= 1e-6 * np.abs(ref.grad_mT_per_m).max()
    assert len(ir.rf) == len(ref.rf) == 16 and len(ir.adc) == len(ref.adc) == 16
    assert max(abs(a.t_center_s - b.t_center_s) for a, b in zip(ir.rf, ref.rf, strict=True)) < 1e-9
    assert max(abs(a.flip_angle_rad - b.flip_angle_rad) for a, b in zip(ir.rf, ref.rf, strict=True)) < 1e-6
    assert max(abs(a.t_start_s - b.t_start_s) for a, b in zip(ir.adc, ref.adc, strict=True)) < 1e-12
    # written in the version the interpreter reads: the input's (pre-1.4: 1.4.1, the oldest dtoc writes)
    out = seq_bytes_of(ir)
    assert _version_of(out) == (version if version >= "1.4" else "1.4.1")


def test_14_file_writes_14_and_15_after_a_change(tmp_path):
    """pypulseq's own 1.4 port leaves the RF use table empty and its writer then fails (KeyError: 1); dtoc's
    reader fills it: a changed 1.4.1 EPI is written as 1.4.1 (default), 1.4.0 and 1.5.x, each read back."""
    p = tmp_path / "epi14.seq"
    p.write_bytes(as_version(epi(n=16), "1.4.1"))
    ir = read_seq(p)
    e = ir.edge_grad_mT_per_m.copy()
    free = ir.free_mask[:, ::2]
    e[free] *= 1.02
    new = ir.with_grad(edges_to_fine(e))
    for version in (None, "1.4.0", "1.5.0", "1.5.1", "1.5.2"):
        data = seq_bytes_of(new, version=version)
        assert _version_of(data) == (version or "1.4.1")
        q = tmp_path / f"out_{version}.seq"
        q.write_bytes(data)
        back = read_seq(q)
        assert np.abs(back.grad_mT_per_m - new.grad_mT_per_m).max() < 1e-5 * np.abs(new.grad_mT_per_m).max()
        assert np.abs(back.grad_mT_per_m - ir.grad_mT_per_m).max() > 1e-3  # the change is in the file


@pytest.mark.skipif(not GIRF.exists(), reason="girf/example_7T.npz absent")
def test_14_file_optimizes_end_to_end(tmp_path, capsys):
    """A 1.4.1 EPI (pypulseq's 1.4 writer) optimizes, and the output is 1.4.1 by default, 1.5.0 on request."""
    base = tmp_path / "epi14.seq"
    base.write_bytes(as_version(epi(n=16), "1.4.1"))
    fast = ["--warm-iters", "30", "--iters", "1", "--threads", "1", "--b0", "7", "--gmax", "32", "--smax", "130"]
    for version in (None, "1.5.0"):
        out, man = tmp_path / f"o{version}.seq", tmp_path / f"o{version}.json"
        extra = [] if version is None else ["--format-version", version]
        code, _, err = run_cli(capsys, "optimize", base, "--girf", GIRF, "-o", out, "--json", man, "-q", *fast, *extra)
        assert code == 0, err
        m = json.loads(man.read_text())
        assert m["output"]["format_version"] == (version or "1.4.1") == _version_of(out.read_bytes())
        assert m["after"]["kspace_max_error_dk"] < 0.5 * m["before"]["kspace_max_error_dk"]
        assert read_seq(out).meta["format_version"] == (version or "1.4.1")


def test_140_spiral_edge_values_are_not_extrapolated(tmp_path):
    """A 1.4.0 spiral whose last sample is 0 plays no step at its end: the edge takes the value the next block
    states (0), not the half-raster extrapolation of the last samples (pypulseq/Pulseq MATLAB), and
    `dtoc check` finds no continuity violation."""
    p = tmp_path / "spiral140.seq"
    p.write_bytes(spiral_140_ending_on_zero())
    ir = read_seq(p)
    for b in (1, 4):  # the two spiral blocks
        m0 = int(round(ir.block_edges_s[b] / ir.dt_fine_s))
        m1 = int(round(ir.block_edges_s[b + 1] / ir.dt_fine_s))
        seg = ir.grad_mT_per_m[:2, m0 : m1 + 1]
        assert np.all(seg[:, 0] == 0) and np.all(seg[:, -1] == 0)
        extrapolated = 1.5 * seg[:, -2] - 0.5 * seg[:, -4]  # what an extrapolating reader puts at the end edge
        assert np.abs(extrapolated).max() > 1e-3  # the test would see the false step
    res = check_file(p, SystemSpec(max_grad_mT_per_m=40, max_slew_T_per_m_per_s=200))
    assert not {"continuity", "grad_end_nonzero", "grad_start_nonzero"} & res.rules(), res.violations


def test_151_oversampled_gradient_plays_its_half_raster_samples(tmp_path):
    """time shape id -1 (1.5.1): samples every half raster between the stated first and last, read exactly."""
    data, played_hz = oversampled_151()
    p = tmp_path / "os.seq"
    p.write_bytes(data)
    ir = read_seq(p)
    m0, m1 = (int(round(ir.block_edges_s[b] / ir.dt_fine_s)) for b in (1, 2))
    g = hz_per_m_from_mT_per_m(ir.grad_mT_per_m[0, m0 : m1 + 1])
    assert g.shape == played_hz.shape and np.abs(g - played_hz).max() < 1e-6 * np.abs(played_hz).max()
    assert _version_of(seq_bytes_of(ir)) == "1.5.1"


def _realized_k(ir, orientation: str | None = None):
    """Realized k through the example GIRF, the file played at ``orientation`` (as --orientation)."""
    from dtoc.api import load_model
    from dtoc.hardware.orientation import RotatedChain, parse_orientation
    from dtoc.sim.twin import Twin

    hw = load_model(girf=GIRF)
    if orientation is not None:
        hw = RotatedChain(hw, parse_orientation(orientation))
    return Twin(ir, hw).forward(moments=False).kspace_rad_per_m.detach().numpy()


def test_rotation_extension_equals_its_prerotated_twin(tmp_path):
    """A radial file whose spokes are turned by the 1.5.1 rotation extension plays the gradients and (through
    a GIRF) the realized k of the same file with pre-rotated spokes; the extension is kept on output (1.5.1 on),
    and a 1.4 or 1.5.0 output is refused by name."""
    rot, pre = tmp_path / "rot.seq", tmp_path / "pre.seq"
    rot.write_bytes(radial(n=16, spokes=8, rotation_extension=True))
    pre.write_bytes(radial(n=16, spokes=8))
    a, b = read_seq(rot), read_seq(pre)
    assert a.meta["format_version"] == "1.5.1" and len(a.meta["rotations"]) == 24
    peak = np.abs(b.grad_mT_per_m).max()
    assert np.abs(a.grad_mT_per_m - b.grad_mT_per_m).max() < 1e-5 * peak  # files state 6 digits
    assert np.abs(a.grad_mT_per_m[1]).max() > 0.5 * peak  # y is played although the file states x only
    dk = 2 * math.pi / 0.22
    k_nom_a, k_nom_b = a.nominal_kspace_rad_per_m(), b.nominal_kspace_rad_per_m()
    assert np.abs(k_nom_a - k_nom_b).max() < 1e-4 * dk
    if GIRF.exists():
        for orientation in (None, "sag", "0.8,0,0.6, 0,1,0, -0.6,0,0.8"):  # composed with --orientation
            ka, kb = _realized_k(a, orientation), _realized_k(b, orientation)
            assert np.abs(ka - k_nom_a).max() > 0.01 * dk  # the GIRF moves k ...
            assert np.abs(ka - kb).max() < 1e-4 * dk  # ... identically for both files
    # preserved on output, with a changed gradient in rotated blocks
    e = a.edge_grad_mT_per_m.copy()
    e[a.free_mask[:, ::2]] *= 1.02
    new = a.with_grad(edges_to_fine(e))
    q = tmp_path / "out.seq"
    q.write_bytes(seq_bytes_of(new))
    back = read_seq(q)
    assert back.meta["rotations"] == a.meta["rotations"]
    assert np.abs(back.grad_mT_per_m - new.grad_mT_per_m).max() < 1e-5 * peak
    for version in ("1.4.1", "1.5.0"):
        with pytest.raises(InputError, match=r"rotation extension \(24 rotated blocks\) needs format 1\.5\.1"):
            seq_bytes_of(a, version=version)


def _stated_use(data: bytes, use: str) -> bytes:
    """The 1.5 text with every RF event's use column set to ``use`` (re-signed)."""
    import hashlib

    t = data[: data.find(b"\n[SIGNATURE]")].decode().split("\n")
    i = t.index("[RF]") + 1
    while t[i].strip():
        if not t[i].startswith("#"):
            f = t[i].split()
            t[i] = " ".join([*f[:-1], use])
        i += 1
    body = ("\n".join(t) + "\n").encode()
    return body + b"\n[SIGNATURE]\nType md5\nHash " + hashlib.md5(body).hexdigest().encode() + b"\n"


def test_unwritable_in_target_version_fails_fast(tmp_path, capsys, monkeypatch):
    """A 1.5 file stating an RF use a 1.4 reader would not detect, asked for as 1.4.1: one line naming it, exit 2,
    no output, and the optimization never starts (its first step after the pre-flight, the projector, is made to
    fail)."""
    import dtoc.optimize.run as run_mod

    def no_work(*a, **k):
        raise AssertionError("the optimization started")

    monkeypatch.setattr(run_mod, "EdgeProjector", no_work)
    base = tmp_path / "epi_inv.seq"
    base.write_bytes(_stated_use(epi(n=16), "i"))
    ir = read_seq(base)
    assert any("stated as inversion" in r for r in unwritable(ir, (1, 4, 1)))
    assert unwritable(ir, (1, 5, 0)) == []
    out = tmp_path / "o.seq"
    argv = ["optimize", base, "--ideal", "--gmax", "32", "--smax", "130", "-o", out, "-q"]
    code, stdout, err = run_cli(capsys, *argv, "--format-version", "1.4.1")
    lines = [ln for ln in err.splitlines() if ln.startswith("dtoc: error")]
    assert code == 2 and len(lines) == 1, err
    assert "cannot write Pulseq format 1.4.1: RF event 1 is stated as inversion" in lines[0]
    assert not out.exists() and "Traceback" not in err
    # an unknown version: one line too
    code, _, err = run_cli(capsys, *argv, "--format-version", "1.3.1")
    assert code == 2 and "format version 1.3.1: dtoc writes 1.4.0, 1.4.1, 1.5.0, 1.5.1, 1.5.2" in err
    # the default (the input's 1.5.0) passes the pre-flight and reaches the optimization
    code, _, err = run_cli(capsys, *argv)
    assert code == 3 and "the optimization started" in err


def test_unsigned_file_from_another_writer_is_valid(gre15, tmp_path):
    raw = gre15.read_bytes()
    p = tmp_path / "unsigned.seq"
    p.write_bytes(raw[: raw.find(b"\n[SIGNATURE]") + 1])
    ir = read_seq(p)
    assert ir.meta["unsigned"] and len(ir.adc) == 16


@pytest.mark.parametrize(
    "edit, msg",
    [
        (
            (b"minor 5\nrevision 0", b"minor 5\nrevision 3"),
            r"format version 1\.5\.3 is not supported .*1\.2\.0 to 1\.5\.2",
        ),
        ((b"minor 5\nrevision 0", b"minor 6\nrevision 0"), r"format version 1\.6\.0 is not supported"),
        (
            (b"[DEFINITIONS]\n", b"[DEFINITIONS]\nRequiredExtensions ROTATIONS GRADIENT_WARP\n"),
            r"requires extension GRADIENT_WARP",
        ),
    ],
)
def test_unknown_versions_and_required_extensions_refused_by_name(gre15, tmp_path, edit, msg):
    raw = gre15.read_bytes()
    body = raw[: raw.find(b"\n[SIGNATURE]") + 1].replace(*edit)
    p = tmp_path / "x.seq"
    p.write_bytes(body)
    with pytest.raises(InputError, match=msg) as e:
        read_seq(p)
    assert "\n" not in str(e.value)


def test_152_reads(gre15, tmp_path):
    raw = gre15.read_bytes()
    p = tmp_path / "v152.seq"
    p.write_bytes(raw[: raw.find(b"\n[SIGNATURE]") + 1].replace(b"minor 5\nrevision 0", b"minor 5\nrevision 2"))
    ir = read_seq(p)
    assert ir.meta["format_version"] == "1.5.2" and _version_of(seq_bytes_of(ir)) == "1.5.2"


def _with_empty_block(data: bytes, after: int) -> bytes:
    """The 1.5 text with a zero-duration block without events after block ``after`` (JEMRIS writes such
    blocks), blocks renumbered; re-signed."""
    import hashlib

    t = data[: data.find(b"\n[SIGNATURE]")].decode().split("\n")
    i = t.index("[BLOCKS]") + 1
    j = i
    while t[j].strip():
        j += 1
    rows = [r.split()[1:] for r in t[i:j] if not r.startswith("#")]
    rows.insert(after, ["0"] * 7)
    t[i:j] = [" ".join([str(k + 1), *r]) for k, r in enumerate(rows)]
    body = ("\n".join(t) + "\n").encode()
    return body + b"\n[SIGNATURE]\nType md5\nHash " + hashlib.md5(body).hexdigest().encode() + b"\n"


def test_zero_duration_block_between_gradients_is_written(tmp_path):
    """A zero-duration block between two readout blocks shares their boundary sample but holds no gradient:
    an optimized output (every free sample moved) is written and reads back; the pre-flight says so first."""
    from dtoc.seq.write import preflight_write

    base = epi(n=16)
    ir0 = read_seq(_write(tmp_path / "a.seq", base))
    ro = next(a.block for a in ir0.adc)  # the first readout block (0-based)
    p = _write(tmp_path / "b.seq", _with_empty_block(base, ro + 1))
    ir = read_seq(p)
    assert len(ir.block_edges_s) == len(ir0.block_edges_s) + 1
    assert preflight_write(ir) == (1, 5, 0)
    e = ir.edge_grad_mT_per_m.copy()
    e[ir.free_mask[:, ::2]] += 0.05  # mT/m: the other boundary samples move too (the empty block's is held)
    new = ir.with_grad(edges_to_fine(e))
    back = read_seq(_write(tmp_path / "c.seq", seq_bytes_of(new)))
    assert np.abs(back.grad_mT_per_m - new.grad_mT_per_m).max() < 1e-5 * np.abs(new.grad_mT_per_m).max()


def _write(p: Path, data: bytes) -> Path:
    p.write_bytes(data)
    return p


def test_rf_shimming_extension_read_kept_and_refused_where_it_would_be_lost(tmp_path):
    """RF_SHIMS (1.5.1) on every excitation: read, written back unchanged (1.5.1 on, also after a gradient
    change), refused by name for 1.4.x and 1.5.0."""
    from foreign.writers import with_extension

    base = gre(n=8)
    ir0 = read_seq(_write(tmp_path / "a.seq", base))
    rf_blocks = {r.block + 1: (2.0, 1.0, 0.0, 0.7, 1.5708) for r in ir0.rf}
    ir = read_seq(_write(tmp_path / "s.seq", with_extension(base, "RF_SHIMS", rf_blocks)))
    assert ir.meta["rf_shims"] == {b - 1: list(v) for b, v in rf_blocks.items()}
    assert np.array_equal(ir.grad_mT_per_m, ir0.grad_mT_per_m)
    e = ir.edge_grad_mT_per_m.copy()
    e[ir.free_mask[:, ::2]] += 0.05
    new = ir.with_grad(edges_to_fine(e))
    for version in ("1.5.1", "1.5.2"):
        back = read_seq(_write(tmp_path / f"o{version}.seq", seq_bytes_of(new, version=version)))
        assert back.meta["rf_shims"] == ir.meta["rf_shims"]
    for version in ("1.4.1", "1.5.0"):
        with pytest.raises(InputError, match=r"RF shimming extension \(8 blocks\) needs format 1\.5\.1"):
            seq_bytes_of(new, version=version)


def test_rotated_trapezoids_without_shapes_are_written(tmp_path):
    """A file without [SHAPES] (trapezoids only) whose rotated blocks the optimizer changes: written (pypulseq's
    reader leaves it a shape library its writer cannot extend), the rotations kept, the gradients read back."""
    from foreign.writers import rotated_trapezoids_151

    from dtoc.seq.write import preflight_write

    ir = read_seq(_write(tmp_path / "r.seq", rotated_trapezoids_151()))
    assert len(ir.meta["rotations"]) == 5
    gy = ir.grad_mT_per_m[1]
    assert np.abs(gy).max() == pytest.approx(np.abs(ir.grad_mT_per_m[0]).max(), rel=1e-9)  # the 90 deg block
    assert preflight_write(ir) == (1, 5, 1)
    e = ir.edge_grad_mT_per_m.copy()
    e[:2, 1:-1] *= 1.01
    new = ir.with_grad(edges_to_fine(e))
    back = read_seq(_write(tmp_path / "o.seq", seq_bytes_of(new)))
    assert back.meta["rotations"] == ir.meta["rotations"]
    assert np.abs(back.grad_mT_per_m - new.grad_mT_per_m).max() < 1e-5 * np.abs(new.grad_mT_per_m).max()


def test_binary_format_reads_as_its_text(gre15, tmp_path):
    """The specification's binary format (our own writer, from its section table) reads as the text file it
    came from (shapes are float32: 1e-6 of the peak); a corrupted byte is a signature mismatch, a cut file
    one line naming the byte."""
    from foreign.writers import as_binary

    ref = read_seq(gre15)
    data = as_binary(gre15.read_bytes())
    ir = read_seq(_write(tmp_path / "g.bseq.seq", data))
    assert ir.meta["format_version"] == "1.5.0"
    assert np.abs(ir.grad_mT_per_m - ref.grad_mT_per_m).max() < 1e-6 * np.abs(ref.grad_mT_per_m).max()
    assert max(abs(a.t_center_s - b.t_center_s) for a, b in zip(ir.rf, ref.rf, strict=True)) < 1e-12
    assert max(abs(a.flip_angle_rad - b.flip_angle_rad) for a, b in zip(ir.rf, ref.rf, strict=True)) < 1e-6
    assert [a.t_start_s for a in ir.adc] == pytest.approx([a.t_start_s for a in ref.adc], abs=1e-12)
    res = check_file(tmp_path / "g.bseq.seq", SystemSpec(max_grad_mT_per_m=32, max_slew_T_per_m_per_s=130))
    assert "signature" not in res.rules()  # its md5 section was checked over the binary bytes
    bad = bytearray(data)
    bad[200] ^= 0x01
    with pytest.raises(InputError, match="signature mismatch"):
        read_seq(_write(tmp_path / "bad.seq", bytes(bad)))
    with pytest.raises(InputError, match=r"binary Pulseq file truncated at byte \d+"):
        read_seq(_write(tmp_path / "cut.seq", as_binary(gre15.read_bytes(), sign=False)[:500]))
