"""The CLI shell: version, one-line errors, atomic outputs."""

import subprocess
import sys

import pytest

from dtoc import __version__
from dtoc.errors import InputError
from dtoc.util.atomic import atomic_write_text


def _dtoc(*args):
    return subprocess.run([sys.executable, "-m", "dtoc", *args], capture_output=True, text=True, timeout=300)


def test_version():
    r = _dtoc("--version")
    assert r.returncode == 0 and r.stdout.strip() == f"dtoc {__version__}"


def test_unknown_command_is_an_error_without_traceback():
    r = _dtoc("no-such-command")
    assert r.returncode != 0
    assert "Traceback" not in r.stderr


def test_atomic_write_refuses_to_clobber(tmp_path):
    p = tmp_path / "out.txt"
    atomic_write_text(p, "one\n")
    with pytest.raises(InputError, match="--force"):
        atomic_write_text(p, "two\n")
    assert p.read_text() == "one\n"
    atomic_write_text(p, "two\n", force=True)
    assert p.read_text() == "two\n"
    assert [q.name for q in tmp_path.iterdir()] == ["out.txt"]  # no temp files left behind
    with pytest.raises(InputError, match="does not exist"):
        atomic_write_text(tmp_path / "nope" / "x.txt", "x")
