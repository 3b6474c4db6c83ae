"""No command destroys an input: an output path that resolves to an input (or to another output) is refused
with one line and exit 2, with or without --force, before any work; the input's bytes are unchanged."""

import hashlib
import shutil
from pathlib import Path

import numpy as np
import pytest
import scipy.io
from cli_helpers import run_cli

REPO = Path(__file__).resolve().parents[1]


def _sha(p: Path) -> str:
    return hashlib.sha256(p.read_bytes()).hexdigest()


@pytest.fixture()
def files(tmp_path):
    for name in ("epi_small.seq", "epi_small.yaml"):
        shutil.copy(REPO / "sequences" / name, tmp_path / name)
    shutil.copy(REPO / "girf" / "example_7T.npz", tmp_path / "h.npz")
    rng = np.random.default_rng(0)
    g = np.zeros((2, 3, 400))
    g[:, :, 50:150] = rng.normal(size=(2, 3, 1)) * np.hanning(100)
    np.savez(tmp_path / "meas.npz", dt=10e-6, g=g, G=g)
    t = np.linspace(-1e-4, 1e-4, 21)[None, :]
    h = np.zeros((21, 1))
    h[10] = 1.0
    scipy.io.savemat(tmp_path / "kernels.mat", {"hxx": h, "hyy": h, "hxy": 0 * h, "hyx": 0 * h, "t": t})
    return tmp_path


CASES = {
    "simulate --json = SEQ": ["simulate", "{d}/epi_small.seq", "--json", "{d}/epi_small.seq"],
    "simulate --png = --girf": ["simulate", "{d}/epi_small.seq", "--girf", "{d}/h.npz", "--png", "{d}/h.npz"],
    "predict --png = SEQ": ["predict", "{d}/epi_small.seq", "--png", "{d}/epi_small.seq"],
    "girf show --png = GIRF": ["girf", "show", "{d}/h.npz", "--png", "{d}/h.npz"],
    "girf fit -o = measurement": ["girf", "fit", "{d}/meas.npz", "-o", "{d}/meas.npz"],
    "girf import -o = input": ["girf", "import", "{d}/kernels.mat", "-o", "{d}/kernels.mat"],
    "optimize --json = BASE": ["optimize", "{d}/epi_small.seq", "-o", "{d}/o.seq", "--json", "{d}/epi_small.seq"],
    "optimize -o = --girf": ["optimize", "{d}/epi_small.seq", "--girf", "{d}/h.npz", "-o", "{d}/h.npz"],
    "optimize --checkpoint = BASE": [
        "optimize",
        "{d}/epi_small.yaml",
        "-o",
        "{d}/o.seq",
        "--checkpoint",
        "{d}/epi_small.yaml",
    ],
}


@pytest.mark.parametrize("force", [False, True])
@pytest.mark.parametrize("case", sorted(CASES))
def test_an_output_on_an_input_is_refused(capsys, files, case, force):
    argv = [a.format(d=files) for a in CASES[case]] + (["--force"] if force else [])
    before = {p.name: _sha(p) for p in files.iterdir()}
    code, out, err = run_cli(capsys, *argv)
    assert code == 2, (case, out, err)
    lines = [x for x in err.strip().splitlines() if x.strip()]
    assert len(lines) == 1 and "would overwrite" in lines[0] and "Traceback" not in err, err
    assert {p.name: _sha(p) for p in files.iterdir()} == before  # nothing written, nothing changed


def test_two_outputs_on_one_path_are_refused(capsys, files):
    code, _, err = run_cli(
        capsys, "optimize", files / "epi_small.seq", "-o", files / "o.seq", "--png", files / "o.seq", "--force"
    )
    assert code == 2 and "each output needs its own path" in err
    assert not (files / "o.seq").exists()


def test_a_symlink_to_an_input_is_the_input(capsys, files):
    (files / "link.seq").symlink_to(files / "epi_small.seq")
    before = _sha(files / "epi_small.seq")
    code, _, err = run_cli(capsys, "predict", files / "epi_small.seq", "--png", files / "link.seq", "--force")
    assert code == 2 and "would overwrite" in err
    assert _sha(files / "epi_small.seq") == before
