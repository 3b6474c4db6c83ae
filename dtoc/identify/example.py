"""End-to-end example behind docs/identify.md: a real measured GIRF as the declared model.

``python -m dtoc.identify.example DECLARED_GIRF.npz OUT_DIR`` (the GIRF imported with ``dtoc girf import``
from ``../shared/data``; nothing of it is stored in the repository):

1. the declared model is that GIRF;
2. a synthetic "true scanner" is the same GIRF plus one effect the GIRF measurement missed (a 3.5 us
   delay on x, the classic time-origin error, and nothing else);
3. 8 probe waveforms x 3 axes x 5000 samples (10 us) are played through the true scanner, white noise
   sigma_G = 0.02 mT/m is added, and the noise level is NOT given to ``identify``;
4. ``identify`` runs exactly as the CLI does; the script prints the numbers as markdown and writes
   measurement, report, updated model and residual PNG into OUT_DIR.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from dtoc.hardware.model import HardwareModel, build_effect, model_from_girf
from dtoc.identify.api import run_identify
from dtoc.identify.synth import probe_waveforms, save_measurement, simulate_measurement

DT = 10e-6
TRUE_EXTRA = dict(kind="delay", params={"seconds": 3.5e-6}, axis="x")
SIGMA_G = 0.02


def build_measurement(girf_npz: str | Path, out_dir: Path, M: int = 8, N: int = 5000, seed: int = 7) -> Path:
    """Write the synthetic measurement of the true scanner (declared GIRF + TRUE_EXTRA) into out_dir."""
    declared = model_from_girf(girf_npz)
    extra = build_effect(TRUE_EXTRA["kind"], TRUE_EXTRA["params"], axis=TRUE_EXTRA["axis"])
    true = HardwareModel([*declared.effects, extra])
    g = probe_waveforms(M, N, DT, seed=seed)
    d = simulate_measurement(true, g, DT, sigma_G=SIGMA_G, seed=seed + 1)
    p = out_dir / "measured.npz"
    save_measurement(d, p, force=True)
    return p


class _Plays(torch.nn.Module):
    """A 'hardware model' for :func:`dtoc.sim.comparison.compare_ideal_realized` that ignores the base
    sequence's demanded gradient and returns ``scanner(g_played)``: the image a pre-compensated sequence
    gives on that scanner, reconstructed on the base sequence's nominal grid."""

    def __init__(self, scanner, g_played_fine):
        super().__init__()
        self.scanner = scanner
        self.g = torch.as_tensor(np.asarray(g_played_fine, dtype=np.float64))

    def forward(self, g, dt_s):
        if tuple(g.shape[-2:]) != tuple(self.g.shape):
            raise ValueError(f"optimized waveform {tuple(self.g.shape)} does not match the base {tuple(g.shape)}")
        gp = self.g.to(g.dtype)
        return self.scanner(gp if g.ndim == 2 else gp[None], dt_s)


def image_on_scanner(base_seq, played_seq, scanner) -> dict:
    """NRMSE / ghost ratio / k error of ``played_seq`` (default: the base itself) on ``scanner``,
    against the ideal image of ``base_seq`` (same phantom and reconstruction as ``dtoc simulate``)."""
    from dtoc.seq.load import load_sequence
    from dtoc.sim.comparison import compare_ideal_realized
    from dtoc.sim.phantom import phantom_for

    ir = load_sequence(base_seq)
    ph = phantom_for(ir, None)
    played = ir.grad_mT_per_m if played_seq is None else load_sequence(played_seq).grad_mT_per_m
    res = compare_ideal_realized(ir, ph, _Plays(scanner, played))
    m = res.metrics
    return {k: m[k] for k in ("nrmse", "ghost_ratio", "kspace_rmse_rad_per_m", "kspace_max_err_dk")}


def main(argv=None) -> int:
    """``GIRF.npz OUT_DIR [BASE_EPI.yaml]``: identify, then (with a base EPI) the image check."""
    import subprocess

    from dtoc.hardware.model import load_model, save_model

    argv = sys.argv[1:] if argv is None else argv
    if len(argv) not in (2, 3) or any(a in ("-h", "--help") for a in argv):
        sys.stdout.write("usage: python -m dtoc.identify.example GIRF.npz OUT_DIR [BASE_EPI.yaml]\n")
        return 0 if any(a in ("-h", "--help") for a in argv) else 2
    girf, out = Path(argv[0]).resolve(), Path(argv[1])
    out.mkdir(parents=True, exist_ok=True)
    meas = build_measurement(girf, out)
    declared = model_from_girf(girf)
    extra = build_effect(TRUE_EXTRA["kind"], TRUE_EXTRA["params"], axis=TRUE_EXTRA["axis"])
    truth = HardwareModel([*declared.effects, extra], description="true scanner (example)")
    save_model(truth, out / "truth.json", force=True)
    t0 = time.perf_counter()
    res = run_identify(
        meas,
        girf=girf,
        out_model=out / "updated_model.json",
        json_out=out / "report.json",
        png_out=out / "residuals.png",
        force=True,
    )
    wall = time.perf_counter() - t0
    rep = json.loads((out / "report.json").read_text())
    print(f"identify wall time: {wall:.1f} s")
    print(
        json.dumps(
            {
                k: rep[k]
                for k in (
                    "before",
                    "after",
                    "heldout_before",
                    "heldout_after",
                    "noise",
                    "explained",
                    "remaining",
                    "noise_method",
                    "heldout",
                )
            },
            indent=1,
        )
    )
    for e in rep["effects"]:
        print(e["kind"], e["axis"], e["input_axis"], e["params"], e["stderr"], e["score"])
    print(json.dumps(rep["screening"][0][:4]))
    print("per_axis", json.dumps(rep["per_axis"]))
    if len(argv) > 2:
        base = Path(argv[2]).resolve()
        updated = load_model(out / "updated_model.json")
        for tag, opt in (
            ("declared", ["--girf", str(girf)]),
            ("updated", ["--model", str(out / "updated_model.json")]),
        ):
            subprocess.run(
                [
                    sys.executable,
                    "-m",
                    "dtoc",
                    "optimize",
                    str(base),
                    *opt,
                    "-o",
                    str(out / f"opt_{tag}.seq"),
                    "--json",
                    str(out / f"opt_{tag}.json"),
                    "--force",
                ],
                check=True,
                capture_output=True,
            )
        rows = [
            ("base", None, "declared GIRF", declared),
            ("base", None, "true scanner", truth),
            ("optimized for the declared GIRF", out / "opt_declared.seq", "true scanner", truth),
            ("optimized for the updated model", out / "opt_updated.seq", "true scanner", truth),
            ("optimized for the updated model", out / "opt_updated.seq", "updated model", updated),
        ]
        print("| sequence | played on | NRMSE | ghost ratio | max k error (dk) |")
        print("|---|---|---|---|---|")
        for name, seq, on, scanner in rows:
            m = image_on_scanner(base, seq, scanner)
            print(
                f"| {name} | {on} | {100 * m['nrmse']:.3f} % | {100 * m['ghost_ratio']:.3f} % | {m['kspace_max_err_dk']:.4f} |"
            )
    return 0 if res is not None else 1


if __name__ == "__main__":
    raise SystemExit(main())
