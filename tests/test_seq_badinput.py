"""Bad .seq input: one line naming the problem, no traceback, non-zero exit; pypulseq's hang guarded."""

import subprocess
import sys
from pathlib import Path

import pytest

from dtoc.errors import InputError
from dtoc.seq.read import read_seq
from dtoc.seq.seqtext import sign_text

REPO = Path(__file__).resolve().parents[1]
SMALL = REPO / "sequences" / "epi_small.seq"
RAW = SMALL.read_bytes()
BODY = RAW[: RAW.find(b"\n[SIGNATURE]")]


def _write(tmp_path, data: bytes, name="bad.seq"):
    p = tmp_path / name
    p.write_bytes(data)
    return p


CASES = {
    "missing": (None, r"no such file"),
    "empty": (b"", r"empty file"),
    "binary": (b"\x89PNG\r\n\x1a\n\x00\x00\x00", r"binary data"),
    "not_pulseq": (b"hello world\n", r"content before the first section"),
    "no_version": (b"[BLOCKS]\n1 1 0 0 0 0 0 0\n", r"no \[VERSION\] section"),
    "wrong_version": (RAW.replace(b"minor 5", b"minor 6", 1), r"version 1\.6\.0 is not supported"),
    "pulseq_binary_truncated": (b"\x01pulseq\x02" + bytes(10), r"binary Pulseq file truncated at byte 8"),
    "truncated_mid_shapes": (RAW[: RAW.find(b"shape_id 9")], r"shape 9 is not defined \(file truncated\?\)"),
    "truncated_mid_gradients": (
        RAW[: RAW.find(b"[GRADIENTS]") + 40],
        r"expected 7 fields, got \d+ \(file truncated\?\)",
    ),
    "truncated_refs": (RAW[: RAW.find(b"[TRAP]")], r"uses gradient 1, which is not defined \(file truncated\?\)"),
    "corrupt_number": (sign_text(BODY.replace(b"1 16 10000 0", b"1 16 1OOOO 0", 1)), r"\[ADC\]: not a number: '1OOOO'"),
    "corrupt_shape": (
        sign_text(BODY.replace(b"num_samples 3", b"num_samples 9", 1)),
        r"compressed data do not expand to 9 samples",
    ),
    "bad_signature": (RAW.replace(b"Created by PyPulseq", b"Created by PyPulsex"), r"signature mismatch"),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_bad_seq_one_line(tmp_path, case):
    data, msg = CASES[case]
    p = tmp_path / "missing.seq" if data is None else _write(tmp_path, data)
    with pytest.raises(InputError, match=msg) as ei:
        read_seq(p)
    s = str(ei.value)
    assert "\n" not in s and str(p) in s


def test_unsigned_file_ending_in_shapes_does_not_hang(tmp_path):
    """pypulseq 1.5.0.post1 loops forever on this; dtoc reads it (when unsigned files are allowed)."""
    import threading

    body = BODY.rstrip(b"\n")  # ends with the last shape sample, no trailing newline at all
    p = _write(tmp_path, body)
    result = {}
    th = threading.Thread(target=lambda: result.update(ir=read_seq(p, require_signature=False)), daemon=True)
    th.start()
    th.join(timeout=30)
    assert not th.is_alive(), "read_seq hangs"
    assert len(result["ir"].adc) == 16


def test_pulseq_14_file_is_read(tmp_path):
    """A 1.4.x file (written by pypulseq's write_v141) is read; its trapezoid/extended gradients match."""
    from dtoc.seq.read import quiet

    ir = read_seq(SMALL)
    p = tmp_path / "v14.seq"
    with quiet():
        ir.source.write(str(p), create_signature=True, v141_compat=True)
    ir14 = read_seq(p)
    assert ir14.grad_mT_per_m.shape == ir.grad_mT_per_m.shape
    assert abs(ir14.grad_mT_per_m - ir.grad_mT_per_m).max() < 1e-3 * abs(ir.grad_mT_per_m).max()
    assert len(ir14.adc) == len(ir.adc)


def _cli(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "dtoc", *args], capture_output=True, text=True, timeout=120, cwd=cwd)


def _run(capsys, *args):
    """The console entry point in-process: (exit code, stderr)."""
    from dtoc.cli.main import run

    with pytest.raises(SystemExit) as e:
        run(list(args))
    return e.value.code, capsys.readouterr().err


def test_cli_process_one_line_error_no_traceback(tmp_path):
    trunc = _write(tmp_path, RAW[: len(RAW) // 2], "trunc.seq")
    r = _cli("check", str(trunc))
    assert r.returncode == 2 and r.stderr.startswith("dtoc: error: ") and "Traceback" not in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and "trunc.seq" in r.stderr


def test_cli_bad_spec_messages(tmp_path, capsys):
    spec = tmp_path / "s.yaml"
    spec.write_text("kind: gre\nname: g\nfov_mm: 0\n")
    code, err = _run(capsys, "build", str(spec), "-o", str(tmp_path / "o.seq"))
    assert code == 2 and "fov_mm: Input should be greater than 0" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "o.seq").exists()
    spec.write_text("kind: epi\nname: e\necho_spacing_ms: 0.81\ndwel_us: 10\n")
    code, err = _run(capsys, "build", str(spec), "-o", str(tmp_path / "o.seq"))
    assert code == 2 and "dwel_us: unknown key" in err
    spec.write_text("kind: gre\nname: g\nte_ms: 2\n")
    code, err = _run(capsys, "build", str(spec), "-o", str(tmp_path / "o.seq"))
    assert code == 2 and "te_ms 2 is shorter than the minimum" in err and str(spec) in err
    code, err = _run(capsys, "build", str(tmp_path / "none.yaml"), "-o", str(tmp_path / "o.seq"))
    assert code == 2 and "spec file not found" in err


def test_cli_build_force_and_overlimit_warning(tmp_path, capsys):
    out = tmp_path / "e.seq"
    spec = str(REPO / "sequences" / "epi_esp073.yaml")
    code, err = _run(capsys, "build", spec, "-o", str(out))
    assert code in (0, None) and "warning" in err and "208.8 > 180" in err
    assert len(read_seq(out).adc) == 64
    code, err = _run(capsys, "build", spec, "-o", str(out))
    assert code == 2 and "exists; pass --force" in err
    code, err = _run(capsys, "build", spec, "-o", str(out), "--force")
    assert code in (0, None)


@pytest.mark.parametrize("name", ["a\n[BLOCKS]", "two words", "x\r", "tab\there", "ünï"])
def test_spec_name_that_would_inject_text_into_the_seq_is_refused(tmp_path, name):
    """The spec name is written into [DEFINITIONS]: a newline would start a section of its own."""
    import yaml

    from dtoc.seq.build import build_to_file
    from dtoc.seq.spec import load_spec

    spec = yaml.safe_load((Path(__file__).resolve().parents[1] / "sequences" / "epi_small.yaml").read_text())
    spec["name"] = name
    p = tmp_path / "s.yaml"
    p.write_text(yaml.safe_dump(spec))
    with pytest.raises(InputError, match="name"):
        build_to_file(load_spec(p), tmp_path / "o.seq")
    assert not (tmp_path / "o.seq").exists()


def test_identify_example_help_is_a_usage_line(capsys):
    from dtoc.identify.example import main

    assert main(["--help"]) == 0 and "usage:" in capsys.readouterr().out
    assert main([]) == 2
