"""Start-up contract of docs/cli.md: the light commands never import torch (timing: bench/startup.py)."""

import subprocess
import sys

import pytest

PROBE = (
    "import sys\n"
    "from dtoc.cli.main import run\n"
    "try:\n"
    "    run(sys.argv[1:])\n"
    "except SystemExit:\n"
    "    pass\n"
    "print('TORCH' if 'torch' in sys.modules else 'NO-TORCH', file=sys.stderr)\n"
)


@pytest.mark.parametrize(
    "argv",
    [
        ["--help"],
        ["check", "sequences/epi_small.seq"],
        ["check", "sequences/epi_small.seq", "--gmax", "30", "--json", "-"],
        ["diff", "sequences/epi_small.seq", "sequences/gre_small.seq"],
        ["build", "sequences/epi_small.yaml", "-o", "{tmp}/b.seq"],
        ["optimize", "--help"],
    ],
)
def test_light_commands_do_not_import_torch(repo_root, tmp_path, argv):
    argv = [a.replace("{tmp}", str(tmp_path)) for a in argv]
    r = subprocess.run([sys.executable, "-c", PROBE, *argv], cwd=repo_root, capture_output=True, text=True)
    assert r.stderr.strip().splitlines()[-1] == "NO-TORCH", r.stderr[-2000:]


def test_the_probe_sees_torch_when_a_command_needs_it(repo_root):
    # the test above could pass because the probe is blind: predict needs torch and must show it
    argv = ["predict", "sequences/epi_small.seq"]
    r = subprocess.run([sys.executable, "-c", PROBE, *argv], cwd=repo_root, capture_output=True, text=True)
    assert r.stderr.strip().splitlines()[-1] == "TORCH", r.stderr[-2000:]
