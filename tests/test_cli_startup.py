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


DEFER_PROBE = (
    "import sys\n"
    "from dtoc.cli.main import run\n"
    "try:\n"
    "    run(sys.argv[1:])\n"
    "except SystemExit:\n"
    "    pass\n"
    "real = [m for m in ('matplotlib', 'scipy.signal', 'scipy.interpolate') if hasattr(sys.modules.get(m), '__file__')]\n"
    "print(','.join(real) or 'NONE', file=sys.stderr)\n"
)


@pytest.mark.parametrize(
    "argv", [["check", "sequences/epi_small.seq"], ["build", "sequences/epi_small.yaml", "-o", "{tmp}/b.seq"]]
)
def test_reading_and_writing_seq_files_skips_pypulseqs_plotting_imports(repo_root, tmp_path, argv):
    """pypulseq's plotting / PNS / spectrum modules (matplotlib, scipy.signal) and scipy.interpolate are deferred
    (dtoc.seq.pulseq): none of them is loaded for real (a deferred stand-in has no __file__)."""
    argv = [a.replace("{tmp}", str(tmp_path)) for a in argv]
    r = subprocess.run([sys.executable, "-c", DEFER_PROBE, *argv], cwd=repo_root, capture_output=True, text=True)
    assert r.stderr.strip().splitlines()[-1] == "NONE", r.stderr[-2000:]


def test_deferred_pypulseq_functions_still_work():
    """The deferred names load the real module when called: pypulseq's own gradient spectrum runs, and
    ``Sequence.get_gradients`` builds real scipy PPoly objects."""
    code = (
        "import sys\n"
        "from dtoc.seq.pulseq import import_pypulseq\n"
        "pp = import_pypulseq()\n"
        "assert 'scipy.signal' not in sys.modules\n"
        "seq = pp.Sequence()\n"
        "seq.read('sequences/gre_paper.seq')\n"
        "assert not hasattr(sys.modules['scipy.interpolate'], '__file__')  # deferred\n"
        "gw = seq.get_gradients()  # builds scipy PPoly objects\n"
        "assert hasattr(sys.modules['scipy.interpolate'], '__file__')  # the real module now\n"
        "from scipy.interpolate import PPoly\n"
        "assert isinstance(gw[0], PPoly) and abs(float(gw[0](gw[0].x[1]))) < 1e9\n"
        "spec = seq.calculate_gradient_spectrum(plot=False)\n"
        "assert 'scipy.signal' in sys.modules and len(spec[0]) == 3\n"
        "from pypulseq.Sequence import calc_grad_spectrum as m\n"
        "assert hasattr(m, 'spectrogram')  # the real module now\n"
        "print('OK')\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=_REPO)
    assert r.stdout.strip().endswith("OK"), r.stderr[-2000:]


_REPO = __import__("pathlib").Path(__file__).resolve().parents[1]
