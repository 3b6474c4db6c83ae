"""Regenerate the MRzeroCore reference fixtures (tests/fixtures/mrzero_*), run once by hand.

    python -m bench.sim.make_reference [--mrzero-python /tmp/mrzero_env/bin/python]

For each scenario it writes, from dtoc itself: the ``.seq`` file (built from the shipped spec in
``sequences/``) and the phantom ``.npz`` (built-in brain phantom, B0 = 0, B1 = 1); then it runs
``bench/sim/mrzero_reference.py`` in the MRzeroCore environment (a subprocess; MRzeroCore is never
imported here) and stores only MRzero's signal (complex, (1, N_adc)) with its version and thresholds.
Scenarios: the paper's GRE (32x32, 32 repetitions, FOV 32 mm, 10 us raster) and the 64x64 single-shot
EPI (FOV 250 mm, echo spacing 0.81 ms).  See docs/metrics.md ("Agreement with MRzeroCore").
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
FIXTURES = REPO / "tests" / "fixtures"
SCENARIOS = {
    # name: (spec in sequences/, phantom matrix, phantom FOV m)
    "gre": ("gre_paper.yaml", 32, 0.032),
    "epi": ("epi_esp081.yaml", 64, 0.25),
}


def make(name: str, mrzero_python: str) -> None:
    from dtoc.seq.build import build_to_file
    from dtoc.seq.spec import load_spec
    from dtoc.sim.phantom import brain_phantom, save_phantom

    spec, n, fov = SCENARIOS[name]
    seq_path = FIXTURES / f"mrzero_{name}.seq"
    ph_path = FIXTURES / f"mrzero_{name}_phantom.npz"
    ref_path = FIXTURES / f"mrzero_{name}_signal.npz"
    build_to_file(load_spec(REPO / "sequences" / spec), seq_path, force=True)
    save_phantom(brain_phantom(n, field_T=3.0, fov_m=fov), ph_path, force=True)
    with tempfile.TemporaryDirectory() as td:
        out = Path(td) / "ref.npz"
        cmd = [
            mrzero_python,
            str(REPO / "bench" / "sim" / "mrzero_reference.py"),
            "reference",
            "--seq",
            str(seq_path),
            "--phantom",
            str(ph_path),
            "--out",
            str(out),
        ]
        subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
        with np.load(out) as z:
            np.savez_compressed(
                ref_path,
                signal=z["signal"].astype(np.complex128),
                mrzero_version=z["mrzero_version"],
                thresholds=z["thresholds"],
                spec=np.asarray(spec),
            )
    print(f"{name}: wrote {seq_path.name}, {ph_path.name}, {ref_path.name}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--mrzero-python", default="/tmp/mrzero_env/bin/python")
    ap.add_argument("scenarios", nargs="*", default=list(SCENARIOS))
    a = ap.parse_args(argv)
    if not shutil.which(a.mrzero_python) and not Path(a.mrzero_python).exists():
        sys.exit(f"MRzeroCore python {a.mrzero_python} not found (see bench/sim/mrzero_reference.py)")
    FIXTURES.mkdir(parents=True, exist_ok=True)
    for s in a.scenarios:
        make(s, a.mrzero_python)


if __name__ == "__main__":
    main()
