"""Limits are never assumed: optimize takes them from --gmax/--smax or the file's definitions, else refuses
with one line; the manifest and the printed summary name the limits and where they came from."""

import json
from pathlib import Path

import pypulseq as pp
import pytest
from cli_helpers import run_cli

from dtoc.seq.pulseq import quiet

REPO = Path(__file__).resolve().parents[1]


def _without(tmp_path: Path, *keys: str) -> Path:
    """epi_small.seq re-written by pypulseq without the given definitions (signed again)."""
    seq = pp.Sequence()
    with quiet():
        seq.read(str(REPO / "sequences" / "epi_small.seq"))
        for k in keys:
            seq.definitions.pop(k, None)
        out = tmp_path / ("no_" + "_".join(k.split("_")[0] for k in keys) + ".seq")
        seq.write(str(out), create_signature=True)
    return out


@pytest.mark.parametrize(
    "keys, opts, msg",
    [
        (("MaxGrad_mT_per_m", "MaxSlew_T_per_m_per_s"), [], "no gmax limit"),
        (("MaxSlew_T_per_m_per_s",), [], "no smax limit"),
        (("MaxGrad_mT_per_m", "MaxSlew_T_per_m_per_s"), ["--gmax", "40"], "no smax limit"),
    ],
)
def test_missing_limits_are_refused(capsys, tmp_path, keys, opts, msg):
    seq = _without(tmp_path, *keys)
    code, out, err = run_cli(
        capsys, "optimize", seq, "--girf", REPO / "girf" / "example_7T.npz", "-o", tmp_path / "o.seq", *opts
    )
    assert code == 2 and msg in err and "never assumed" in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "o.seq").exists()


def test_given_limits_are_used_recorded_and_printed(capsys, tmp_path):
    seq = _without(tmp_path, "MaxGrad_mT_per_m", "MaxSlew_T_per_m_per_s")
    code, out, err = run_cli(
        capsys,
        "optimize",
        seq,
        "--girf",
        REPO / "girf" / "example_7T.npz",
        "-o",
        tmp_path / "o.seq",
        "--json",
        tmp_path / "m.json",
        "--gmax",
        "60",
        "--smax",
        "178",
        "--warm-iters",
        "20",
        "--iters",
        "0",
    )
    assert code == 0, err
    lim = json.loads((tmp_path / "m.json").read_text())["limits"]
    assert lim["gmax_mT_per_m"] == 60 and lim["smax_T_per_m_per_s"] == 178
    assert lim["source"] == {"gmax_mT_per_m": "--gmax", "smax_T_per_m_per_s": "--smax"}
    text = " ".join(err.split())  # the summary goes to stderr (rich may wrap it)
    assert "gmax 60 mT/m (--gmax)" in text and "smax 178 T/m/s (--smax)" in text
    code, out, err = run_cli(capsys, "check", tmp_path / "o.seq", "--gmax", "60", "--smax", "178")
    assert code == 0, out + err


def test_file_definitions_are_named_as_the_source(capsys, tmp_path):
    code, out, err = run_cli(
        capsys,
        "optimize",
        REPO / "sequences" / "epi_small.seq",
        "--girf",
        REPO / "girf" / "example_7T.npz",
        "-o",
        tmp_path / "o.seq",
        "--warm-iters",
        "10",
        "--iters",
        "0",
    )
    assert code == 0, err
    assert "gmax 72 mT/m (file definition MaxGrad_mT_per_m)" in " ".join(err.split())


def test_hardware_is_never_silently_ideal(capsys, tmp_path):
    epi = REPO / "sequences" / "epi_small.seq"
    code, _, err = run_cli(capsys, "optimize", epi, "-o", tmp_path / "o.seq")
    assert code == 2 and "no hardware model" in err and "--ideal" in err
    code, _, err = run_cli(
        capsys, "optimize", epi, "--ideal", "--girf", REPO / "girf" / "example_7T.npz", "-o", tmp_path / "o.seq"
    )
    assert code == 2 and "not both" in err
    assert not (tmp_path / "o.seq").exists()
    code, _, err = run_cli(
        capsys, "optimize", epi, "--ideal", "-o", tmp_path / "o.seq", "--warm-iters", "5", "--iters", "0"
    )
    assert code == 0, err
    assert (tmp_path / "o.seq").exists()
