"""Hostile inputs, round 2 (docs/cli.md, "Outputs" and "Accepted ranges"): every file a command reads is an
input, outputs never go through links or onto non-regular files, one of two concurrent writers wins, every
option and file-borne value is range-checked at the boundary, a scanner profile is loaded whole, impossible
work is refused before it starts.  Each refusal: exit 2, exactly one ``dtoc: error:`` line, no traceback or
"unexpected", and every file of the folder byte-identical before and after (sha256)."""

from __future__ import annotations

import hashlib
import io
import json
import os
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import run_cli

from dtoc.seq.seqtext import sign_text

REPO = Path(__file__).resolve().parents[1]
GRE = REPO / "sequences" / "gre_small.seq"
EPI = REPO / "sequences" / "epi_small.seq"
SPEC = REPO / "sequences" / "epi_small.yaml"
GRE_SPEC = REPO / "sequences" / "gre_small.yaml"
GIRF = REPO / "girf" / "example_7T.npz"
EPI_BODY = EPI.read_bytes()[: EPI.read_bytes().find(b"\n[SIGNATURE]")]


def _digest(folder: Path) -> dict[str, str]:
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file() and not p.is_symlink()
    }


def refused(capsys, folder: Path, argv: list, contains: str | None = None) -> str:
    """Run the CLI in-process: exit 2, one ``dtoc: error:`` line, nothing in ``folder`` written or changed."""
    before = _digest(folder)
    names_before = sorted(os.listdir(folder))
    code, out, err = run_cli(capsys, *argv)
    assert code == 2, (code, out[-300:], err)
    assert "Traceback" not in err and "unexpected" not in err and "ValidationError" not in err, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("dtoc: error: "), err
    assert "╭" not in err and "Usage:" not in err, err
    assert _digest(folder) == before, "a file was written or changed"
    assert sorted(os.listdir(folder)) == names_before, "a file or folder appeared"
    if contains is not None:
        assert contains in err, err
    return err


def _epi_with(old: bytes, new: bytes) -> bytes:
    assert old in EPI_BODY, old
    return sign_text(EPI_BODY.replace(old, new, 1))


def _profile(tmp: Path, *, name: str = "Test-7T", hardware: str | None = "  girf: h.npz\n") -> Path:
    (tmp / "h.npz").write_bytes(GIRF.read_bytes()) if not (tmp / "h.npz").exists() else None
    text = (
        f"name: {json.dumps(name)}\nb0_T: 6.98\ngmax_mT_per_m: 72\nsmax_T_per_m_per_s: 180\n"
        "rasters: {grad_s: 1.0e-5, rf_s: 1.0e-6, adc_s: 1.0e-7, block_s: 1.0e-5}\n"
        "dead_times: {rf_dead_time_s: 1.0e-4, rf_ringdown_time_s: 3.0e-5, adc_dead_time_s: 1.0e-5}\n"
    )
    if hardware is not None:
        text += "hardware:\n" + hardware
    p = tmp / "p.yaml"
    p.write_text(text)
    return p


# ---------------------------------------------------------------------------------------------------
# 1. files destroyed: every read file is an input; no output through a link or onto a non-regular file
# ---------------------------------------------------------------------------------------------------
def _phantom_npz(path: Path, n: int = 16) -> Path:
    np.savez(path, pd=np.ones((n, n)), t1_s=np.ones((n, n)), t2_s=np.full((n, n), 0.05), fov_m=np.array(0.25))
    return path


OUTPUT_ON_INPUT = {
    "o_on_phantom_force": lambda t: [
        "optimize", EPI, "--girf", GIRF, "--phantom", _phantom_npz(t / "ph.npz"), "-o", t / "ph.npz", "--force",
    ],
    "json_on_phantom_force": lambda t: [
        "optimize", EPI, "--girf", GIRF, "--phantom", _phantom_npz(t / "ph.npz"), "-o", t / "o.seq",
        "--json", t / "ph.npz", "--force",
    ],
    "o_on_resumed_checkpoint": lambda t: [
        "optimize", EPI, "--girf", GIRF, "--resume", _ck(t / "ck.npz"), "-o", t / "ck.npz", "--force",
    ],
    "hard_link_of_input": lambda t: ["simulate", _hardlink(t), "--json", t / "link.seq", "--force"],
    "identify_o_on_measurement": lambda t: ["identify", _meas(t / "m.npz"), "--girf", GIRF, "-o", t / "m.npz", "--force"],
    "identify_json_on_girf": lambda t: [
        "identify", _meas(t / "m.npz"), "--girf", _copy(GIRF, t / "g.npz"), "-o", t / "u.json", "--json", t / "g.npz",
        "--force",
    ],
}  # fmt: skip


def _copy(src: Path, dst: Path) -> Path:
    dst.write_bytes(src.read_bytes())
    return dst


def _hardlink(t: Path) -> Path:
    a = _copy(EPI, t / "a.seq")
    os.link(a, t / "link.seq")
    return a


def _ck(path: Path, nan: bool = False) -> Path:
    e = np.zeros((3, 10))
    if nan:
        e[0, 3] = np.nan
    np.savez(
        path, edges_mT_per_m=e, it=np.int64(2), stage=np.array("full"), history=np.array("[]"), config=np.array("{}")
    )
    return path


def _meas(path: Path, n: int = 400) -> Path:
    g = np.zeros((1, 3, n))
    g[:, 0, n // 2 :] = 1.0
    np.savez(path, dt=np.array(1e-5), g=g, G=g.copy())
    return path


@pytest.mark.parametrize("case", sorted(OUTPUT_ON_INPUT))
def test_an_output_never_replaces_an_input(capsys, tmp_path, case):
    argv = OUTPUT_ON_INPUT[case](tmp_path)
    refused(capsys, tmp_path, argv, "would overwrite")


def _symlink_to_file(t: Path) -> Path:
    (t / "target.json").write_text("keep")
    os.symlink(t / "target.json", t / "link.json")
    return t / "link.json"


def _dangling(t: Path) -> Path:
    os.symlink(t / "nowhere.json", t / "dangling.json")
    return t / "dangling.json"


def _fifo(t: Path) -> Path:
    os.mkfifo(t / "fifo.json")
    return t / "fifo.json"


NOT_REGULAR = {
    "json_symlink_force": lambda t: ["check", EPI, "--json", _symlink_to_file(t), "--force"],
    "json_symlink": lambda t: ["check", EPI, "--json", _symlink_to_file(t)],
    "json_dangling_symlink": lambda t: ["diff", EPI, EPI, "--json", _dangling(t)],
    "build_o_symlink_force": lambda t: ["build", SPEC, "-o", _seq_link(t), "--force"],
    "json_fifo_force": lambda t: ["check", EPI, "--json", _fifo(t), "--force"],
    "json_dev_null_force": lambda t: ["girf", "show", GIRF, "--json", "/dev/null", "--force"],
    "png_dev_stdout_force": lambda t: ["girf", "show", GIRF, "--png", "/dev/stdout", "--force"],
    "json_directory_force": lambda t: ["check", EPI, "--json", t, "--force"],
}


def _seq_link(t: Path) -> Path:
    (t / "real.seq").write_text("keep")
    os.symlink("real.seq", t / "o.seq")
    return t / "o.seq"


@pytest.mark.parametrize("case", sorted(NOT_REGULAR))
def test_no_output_through_a_link_or_onto_a_non_regular_file(capsys, tmp_path, case):
    argv = NOT_REGULAR[case](tmp_path)
    err = refused(capsys, tmp_path, argv)
    assert any(w in err for w in ("symbolic link", "not a regular file", "directory", "exists")), err
    for p in tmp_path.iterdir():  # links are still links, the FIFO still a FIFO
        if p.name in ("link.json", "dangling.json", "o.seq"):
            assert p.is_symlink()
        if p.name == "fifo.json":
            assert not p.is_file()


def test_an_existing_checkpoint_needs_force(capsys, tmp_path):
    ck = tmp_path / "mine.npz"
    ck.write_bytes(b"an unrelated file")
    refused(
        capsys, tmp_path, ["optimize", EPI, "--girf", GIRF, "-o", tmp_path / "o.seq", "--checkpoint", ck], "--force"
    )


def test_a_file_that_appears_during_the_command_is_not_replaced(tmp_path):
    """The publish without --force is exclusive: a file created meanwhile by another writer wins."""
    from dtoc.errors import InputError
    from dtoc.util.atomic import atomic_write_bytes, outputs_together

    out = tmp_path / "o.seq"
    with pytest.raises(InputError, match="appeared while this command ran"), outputs_together():
        atomic_write_bytes(out, b"mine")
        out.write_bytes(b"the other writer's")
    assert out.read_bytes() == b"the other writer's"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["o.seq"]  # no temporary left


def test_two_concurrent_builds_one_wins(tmp_path):
    """Two ``dtoc build`` to one output without --force, started together: exactly one exits 0, the other 2
    with one line, and the file is the winner's complete output (bounded: 4 rounds)."""
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
    cmd = [sys.executable, "-m", "dtoc", "build", str(SPEC), "-o"]
    expected = None
    for i in range(4):
        out = tmp_path / f"o{i}.seq"
        procs = [subprocess.Popen([*cmd, str(out)], env=env, stderr=subprocess.PIPE, text=True) for _ in range(2)]
        res = [(p.wait(timeout=120), p.stderr.read()) for p in procs]  # type: ignore[union-attr]
        codes = sorted(c for c, _ in res)
        assert codes == [0, 2], res
        loser = next(e for c, e in res if c == 2).strip().splitlines()
        assert len(loser) == 1 and loser[0].startswith("dtoc: error: ") and "Traceback" not in loser[0], loser
        data = out.read_bytes()
        expected = expected or data
        assert data == expected  # complete, identical to the other rounds' winners
    assert sorted(p.name for p in tmp_path.iterdir()) == [f"o{i}.seq" for i in range(4)]


# ---------------------------------------------------------------------------------------------------
# 2. one validation layer: options and file-borne values out of range, one line naming value and range
# ---------------------------------------------------------------------------------------------------
OPT_RANGE = {
    "gmax_1e6": ["--gmax", "1e6"],
    "smax_1e9": ["--smax", "1e9"],
    "gmax_inf": ["--gmax", "inf"],
    "w_rf_inf": ["--w-rf", "inf"],
    "w_k_nan": ["--w-k", "nan"],
    "w_image_negative": ["--w-image", "-1"],
    "lr_zero": ["--lr", "0"],
    "seed_1e23": ["--seed", "100000000000000000000000"],
    "seed_negative": ["--seed", "-1"],
    "iters_1e9": ["--iters", "1000000000"],
    "warm_iters_negative": ["--warm-iters", "-5"],
    "augment_200": ["--augment", "200"],
    "threads_0": ["--threads", "0"],
    "threads_9999": ["--threads", "9999"],
    "b0_100": ["--b0", "100"],
    "phantom_brain_2048": ["--phantom", "brain:2048"],
}


@pytest.mark.parametrize("case", sorted(OPT_RANGE))
def test_optimize_option_ranges(capsys, tmp_path, case):
    err = refused(capsys, tmp_path, ["optimize", EPI, "--girf", GIRF, "-o", tmp_path / "o.seq", *OPT_RANGE[case]])
    assert "accepted range" in err or "cores" in err, err


OTHER_RANGE = {
    "check_gmax_1e6": lambda t: ["check", EPI, "--gmax", "1e6", "--smax", "180"],
    "check_smax_1e9": lambda t: ["check", EPI, "--gmax", "72", "--smax", "1e9"],
    "simulate_dummies_1e8": lambda t: ["simulate", EPI, "--dummies", "100000000"],
    "simulate_phantom_2048": lambda t: ["simulate", EPI, "--phantom", "brain:2048"],
    "simulate_b0_0": lambda t: ["simulate", EPI, "--b0", "0"],
    "identify_kinds_empty": lambda t: ["identify", _meas(t / "m.npz"), "--girf", GIRF, "-o", t / "u.json", "--kinds", ""],
    "identify_kinds_comma": lambda t: ["identify", _meas(t / "m.npz"), "--girf", GIRF, "-o", t / "u.json", "--kinds", ","],
    "identify_kinds_newline": lambda t: [
        "identify", _meas(t / "m.npz"), "--girf", GIRF, "-o", t / "u.json", "--kinds", "delay\nforged line",
    ],
    "identify_31_samples": lambda t: ["identify", _meas(t / "m.npz", 31), "--girf", GIRF, "-o", t / "u.json"],
    "identify_max_effects_1e6": lambda t: [
        "identify", _meas(t / "m.npz"), "--girf", GIRF, "-o", t / "u.json", "--max-effects", "1000000",
    ],
    "file_maxgrad_1e12": lambda t: [
        "optimize", _write(t / "b.seq", _epi_with(b"MaxGrad_mT_per_m 72 ", b"MaxGrad_mT_per_m 1e12 ")), "--girf", GIRF,
        "-o", t / "o.seq",
    ],
    "config_iters_negative": lambda t: [
        "optimize", EPI, "--girf", GIRF, "--config", _write(t / "c.yaml", b"iters: -1\n"), "-o", t / "o.seq",
    ],
    "config_dummies_1e8": lambda t: [
        "optimize", EPI, "--girf", GIRF, "--config", _write(t / "c.yaml", b"n_dummies: 100000000\n"), "-o", t / "o.seq",
    ],
    "spec_tr_1e9": lambda t: [
        "build", _write(t / "s.yaml", GRE_SPEC.read_bytes().replace(b"tr_ms: 6", b"tr_ms: 1e9")), "-o", t / "o.seq",
    ],
}  # fmt: skip


def _write(p: Path, data: bytes) -> Path:
    p.write_bytes(data)
    return p


@pytest.mark.parametrize("case", sorted(OTHER_RANGE))
def test_other_values_out_of_range(capsys, tmp_path, case):
    err = refused(capsys, tmp_path, OTHER_RANGE[case](tmp_path))
    assert "\nforged" not in err


USAGE = {
    "missing_argument": ["check"],
    "unknown_option": ["check", EPI, "--wormhole"],
    "not_an_integer": ["optimize", EPI, "-o", "x.seq", "--iters", "abc"],
    "not_a_number": ["check", EPI, "--gmax", "lots"],
    "missing_option_value": ["build", SPEC, "-o"],
}


@pytest.mark.parametrize("case", sorted(USAGE))
def test_usage_errors_are_one_line(capsys, tmp_path, case):
    err = refused(capsys, tmp_path, USAGE[case])
    assert "--help" in err


# ---------------------------------------------------------------------------------------------------
# 3. the scanner profile: loaded and validated whole by every command, its name restricted
# ---------------------------------------------------------------------------------------------------
def _nan_girf(t: Path) -> None:
    d = dict(np.load(GIRF))
    d["h"] = d["h"].copy()
    d["h"][0, 0, 3] = np.nan
    np.savez(t / "h.npz", **d)


def _pickled(t: Path) -> None:
    np.savez(t / "h.npz", h=np.array([{"a": 1}], dtype=object), dt=np.array(1e-5))


def _not_a_girf(t: Path) -> None:
    np.savez(t / "h.npz", wormhole=np.ones(3))


PROFILE_BAD = {
    "girf_missing": (None, "  girf: missing.npz\n"),
    "girf_nan": (_nan_girf, "  girf: h.npz\n"),
    "girf_pickled": (_pickled, "  girf: h.npz\n"),
    "girf_not_a_girf": (_not_a_girf, "  girf: h.npz\n"),
    "girf_and_model": (None, "  girf: h.npz\n  model: m.json\n"),
    "model_empty_object": (None, "  model: m.json\n"),
}


@pytest.mark.parametrize("cmd", ["check", "predict", "optimize"])
@pytest.mark.parametrize("case", sorted(PROFILE_BAD))
def test_a_profile_is_loaded_whole(capsys, tmp_path, case, cmd):
    make, hw = PROFILE_BAD[case]
    (tmp_path / "h.npz").write_bytes(GIRF.read_bytes())
    (tmp_path / "m.json").write_text("{}")
    if make is not None:
        make(tmp_path)
    prof = _profile(tmp_path, hardware=hw)
    extra = ["-o", tmp_path / "o.seq"] if cmd == "optimize" else []
    refused(capsys, tmp_path, [cmd, EPI, "--scanner", prof, *extra])


@pytest.mark.parametrize("cmd", ["check", "optimize", "predict"])
def test_a_profile_name_cannot_forge_lines(capsys, tmp_path, cmd):
    prof = _profile(tmp_path, name="T\ndtoc: warning: all checks passed")
    extra = ["-o", tmp_path / "o.seq"] if cmd == "optimize" else []
    err = refused(capsys, tmp_path, [cmd, EPI, "--scanner", prof, *extra], "name")
    assert "\ndtoc: warning" not in err


def test_predict_names_the_profiles_model(capsys, tmp_path):
    prof = _profile(tmp_path)
    code, out, err = run_cli(capsys, "predict", EPI, "--scanner", prof, "--json", "-")
    assert code == 0, err
    rep = json.loads(out)
    assert rep["model"].startswith("--scanner Test-7T: ") and rep["model"].endswith("h.npz"), rep["model"]
    assert rep["k_error"]["x"]["max_dk"] > 0  # the GIRF was applied, and is named


def test_an_empty_model_file_is_not_ideal_hardware(capsys, tmp_path):
    m = tmp_path / "m.json"
    m.write_text("{}")
    refused(capsys, tmp_path, ["predict", EPI, "--model", m], "effects")


# ---------------------------------------------------------------------------------------------------
# 4. unbounded work refused before it starts; archives checked before they are inflated
# ---------------------------------------------------------------------------------------------------
def _npz_declaring(path: Path, shape: tuple, key: str = "pd") -> Path:
    """A small deflated .npz whose member header declares ``shape`` (float64) but holds a few bytes."""
    hdr = io.BytesIO()
    np.lib.format.write_array_header_1_0(hdr, {"descr": "<f8", "fortran_order": False, "shape": shape})
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        zf.writestr(f"{key}.npy", hdr.getvalue() + b"\0" * 64)
    return path


BIG = {
    "phantom_header_80GB": lambda t: ["simulate", EPI, "--phantom", _npz_declaring(t / "ph.npz", (100_000, 100_000))],
    "phantom_2048_squared": lambda t: ["simulate", EPI, "--phantom", _phantom_npz(t / "ph.npz", 2048)],
    "optimize_phantom_2048": lambda t: [
        "optimize", EPI, "--girf", GIRF, "--phantom", _phantom_npz(t / "ph.npz", 2048), "-o", t / "o.seq",
    ],
    "girf_header_80GB": lambda t: ["girf", "show", _npz_declaring(t / "g.npz", (3, 3, 10**10), "h")],
    "girf_pickled": lambda t: ["predict", EPI, "--girf", _write(t / "g.npz", _pickle_npz())],
    "resume_truncated_member": lambda t: [
        "optimize", EPI, "--girf", GIRF, "--resume", _npz_declaring(t / "ck.npz", (3, 1000), "edges_mT_per_m"),
        "-o", t / "o.seq",
    ],
}  # fmt: skip


def _pickle_npz() -> bytes:
    b = io.BytesIO()
    np.savez(b, h=np.array([None, {"x": 1}], dtype=object), dt=np.array(1e-5))
    return b.getvalue()


@pytest.mark.parametrize("case", sorted(BIG))
def test_unbounded_work_is_refused_before_it_starts(capsys, tmp_path, case):
    refused(capsys, tmp_path, BIG[case](tmp_path))


def test_a_simulation_estimate_beyond_memory_is_refused():
    from dtoc.errors import InputError
    from dtoc.util.cost import check_simulation_cost

    text, sec = check_simulation_cost("x", 512 * 512, 512 * 512)  # a legal 512x512 EPI: estimated, allowed here
    assert "262144 voxels" in text and sec > 10
    with pytest.raises(InputError, match="needs about"):
        check_simulation_cost("x", 10**9, 100)


# ---------------------------------------------------------------------------------------------------
# 5. optimize refuses what the limits cannot improve; batch validates the plan and locks --out
# ---------------------------------------------------------------------------------------------------
def test_limits_that_leave_nothing_better_are_refused(capsys, tmp_path):
    err = refused(capsys, tmp_path, ["optimize", GRE, "--ideal", "--smax", "0.5", "-o", tmp_path / "o.seq"])
    assert "--allow-worse" in err and "needs" in err


def test_a_nan_checkpoint_is_not_resumed(capsys, tmp_path):
    ck = _ck(tmp_path / "ck.npz", nan=True)
    refused(capsys, tmp_path, ["optimize", EPI, "--girf", GIRF, "--resume", ck, "-o", tmp_path / "o.seq"], "NaN")


def _plan(t: Path, options: str = "{}", extra: str = "") -> Path:
    p = t / "plan.yaml"
    p.write_text(
        f"sequences: {{epi: {EPI}}}\nhardware: {{g: {{girf: {GIRF}}}}}\norientations: [tra]\n"
        f"options: {{o: {options}}}\n" + extra
    )
    return p


def _big_plan(t: Path) -> Path:
    seqs = "".join(f"  s{i}: {EPI}\n" for i in range(40))
    hw = "".join(f"  h{i}: {{girf: {GIRF}}}\n" for i in range(40))
    opts = "".join(f"  o{i}: {{seed: {i}}}\n" for i in range(10))
    p = t / "plan.yaml"
    p.write_text(
        f"sequences:\n{seqs}hardware:\n{hw}orientations: [tra, sag, cor, {', '.join(['tra'] * 9)}]\noptions:\n{opts}"
    )
    return p


BATCH = {
    "workers_0": lambda t: ["batch", _plan(t), "--out", t / "out", "--workers", "0"],
    "iters_negative": lambda t: ["batch", _plan(t, "{iters: -1}"), "--out", t / "out"],
    "augment_200": lambda t: ["batch", _plan(t, "{augment: 200}"), "--out", t / "out"],
    "w_rf_inf": lambda t: ["batch", _plan(t, "{w_rf: .inf}"), "--out", t / "out"],
    "unknown_option": lambda t: ["batch", _plan(t, "{wormhole: 1}"), "--out", t / "out"],
    "bad_name": lambda t: ["batch", _plan(t).parent / _write_plan_bad_name(t), "--out", t / "out"],
    "engine_unknown": lambda t: ["batch", _plan(t), "--out", t / "out", "--engine", "magic"],
    "jobs_192000": lambda t: ["batch", _big_plan(t), "--out", t / "out"],
    "out_is_input_folder": lambda t: ["batch", _plan(t), "--out", t],
}


def _write_plan_bad_name(t: Path) -> str:
    (t / "plan.yaml").write_text(f"sequences: {{'e p\\ni': {EPI}}}\nhardware: {{g: {{girf: {GIRF}}}}}\n")
    return "plan.yaml"


@pytest.mark.parametrize("case", sorted(BATCH))
def test_batch_refusals_create_no_folder(capsys, tmp_path, case):
    argv = BATCH[case](tmp_path)
    refused(capsys, tmp_path, argv)
    assert not (tmp_path / "out").exists()


def test_batch_job_link_clash_found_before_any_job(capsys, tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / ".dtoc-batch").write_text("marker\n")
    (out / "epi__g__tra__o").write_text("a user's file")
    refused(capsys, tmp_path, ["batch", _plan(tmp_path), "--out", out], "not a job link")
    assert not (out / "jobs").exists()


def test_a_second_batch_on_one_out_is_refused(capsys, tmp_path):
    from dtoc.batch.store import Store

    out = tmp_path / "out"
    first = Store.open(out)  # a running batch holds the folder
    try:
        refused(capsys, tmp_path, ["batch", _plan(tmp_path), "--out", out], "another dtoc batch")
    finally:
        first.close()


# ---------------------------------------------------------------------------------------------------
# contract details
# ---------------------------------------------------------------------------------------------------
def test_transversal_is_tra():
    from dtoc.hardware.orientation import parse_orientation

    assert np.array_equal(parse_orientation("transversal"), np.eye(3))
    assert np.array_equal(parse_orientation("Sagittal"), parse_orientation("sag"))


def test_check_names_a_garbage_recorded_orientation(capsys, tmp_path):
    p = _write(tmp_path / "b.seq", _epi_with(b"[DEFINITIONS]\n", b"[DEFINITIONS]\nDtocOrientation banana 1 2\n"))
    code, _, err = run_cli(capsys, "check", p)
    assert code == 0 and "DtocOrientation" in err and "banana" in err, err


def test_an_oversubscribing_thread_count_is_refused(capsys, tmp_path):
    n = len(os.sched_getaffinity(0))
    err = refused(capsys, tmp_path, ["optimize", EPI, "--girf", GIRF, "-o", tmp_path / "o.seq", "--threads", n + 1])
    assert "cores" in err


def test_the_new_corpus_is_large_enough():
    n = (
        len(OUTPUT_ON_INPUT) + len(NOT_REGULAR) + 2 + 1 + len(OPT_RANGE) + len(OTHER_RANGE) + len(USAGE)
        + 3 * len(PROFILE_BAD) + 3 + 1 + len(BIG) + 1 + 1 + len(BATCH) + 2 + 1
    )  # fmt: skip
    assert n >= 60, n


def _dtoc(*args, env=None):
    e = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1", **(env or {})}
    return subprocess.run([sys.executable, "-m", "dtoc", *map(str, args)], capture_output=True, text=True, env=e)


@pytest.mark.slow
def test_an_interrupt_never_replaces_an_unrelated_file_at_the_default_checkpoint(tmp_path):
    """The default checkpoint ``OUT.ckpt.npz`` takes a free name beside an unrelated file; a finished run from an
    interrupted best-so-far does not copy its ``DtocInterrupted`` flag."""
    fast = ["--warm-iters", "20", "--iters", "2", "--threads", "1", "-q"]
    out = tmp_path / "o.seq"
    mine = tmp_path / "o.seq.ckpt.npz"
    mine.write_bytes(b"an unrelated file")
    r = _dtoc("optimize", EPI, "--girf", GIRF, "-o", out, *fast, env={"DTOC_FAULT_SIGNAL": "warm_start:SIGINT"})
    assert r.returncode == 130, r.stderr
    assert mine.read_bytes() == b"an unrelated file"
    assert (tmp_path / "o-2.seq.ckpt.npz").is_file() and "o-2.seq.ckpt.npz" in r.stderr
    assert b"DtocInterrupted 1" in out.read_bytes()
    stale = _write(tmp_path / "s.seq", _epi_with(b"[DEFINITIONS]\n", b"[DEFINITIONS]\nDtocInterrupted 1\n"))
    r2 = _dtoc("optimize", stale, "--girf", GIRF, "-o", tmp_path / "f.seq", "--no-trajectory", *fast)
    assert r2.returncode == 0, r2.stderr
    assert b"DtocInterrupted" not in (tmp_path / "f.seq").read_bytes()


def test_an_adc_dwell_of_zero_fails_check(capsys, tmp_path):
    p = _write(tmp_path / "b.seq", _epi_with(b"[ADC]\n1 16 10000 0", b"[ADC]\n1 16 0 0"))
    code, out, err = run_cli(capsys, "check", p, "--json", "-")
    assert code == 1, err
    assert {v["rule"] for v in json.loads(out)["violations"]} == {"adc_dwell"}


def test_a_nan_in_a_time_shape_is_refused(capsys, tmp_path):
    raw = GRE.read_bytes()
    body = raw[: raw.find(b"\n[SIGNATURE]")]
    old = b"shape_id 7\nnum_samples 4\n0\n5\n"
    assert old in body
    p = _write(tmp_path / "b.seq", sign_text(body.replace(old, b"shape_id 7\nnum_samples 4\n0\nnan\n", 1)))
    refused(capsys, tmp_path, ["predict", p], "not finite")
    refused(capsys, tmp_path, ["check", p], "not finite")
