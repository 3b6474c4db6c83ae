"""Generate girf/example_7T.npz: a self-made, parametric GIRF resembling a 7 T head/body gradient system.

Deterministic (no random numbers); run ``python girf/make_example.py --force`` to regenerate.
Nothing here comes from a measured file: it is a model with round numbers.

Frequency responses (f in Hz, s = 2 pi i f), on a 2048-point two-sided grid at dt = 10 us:
- self terms: |H| = 1 / sqrt(1 + (f/fc)^4) (second-order Butterworth magnitude, zero phase),
  fc = 10.7 kHz (the -3 dB point), times a small mechanical resonance
  (1 + a_r * [L(f - f_r) + L(f + f_r)]), L a Lorentzian of half-width 150 Hz, f_r = 1.1 / 1.3 / 0.9 kHz on
  x / y / z, a_r = 3 %, times a residual bulk delay exp(-s d), d = 2 / 1.5 / 2.5 us;
- cross terms (output o, input i): 1 % eddy-current-like high-pass 0.01 * s tau / (1 + s tau) with
  tau = 0.3 ... 0.8 ms, band-limited by the same low-pass;
- B0 terms: 0.02 uT per (mT/m) * s tau / (1 + s tau), tau = 1 / 1.5 / 0.8 ms on x / y / z inputs.
Taps: inverse DFT, centred: t0 = -1024 * 10 us.  DC gains: 1 (self), 0 (cross and B0).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from dtoc.hardware.girf_io import GirfData, freq_to_taps, save_girf

N, DT = 2048, 10e-6
FC, AR, GAMMA_HZ = 10.7e3, 0.03, 150.0
F_RES = (1.1e3, 1.3e3, 0.9e3)
DELAY = (2e-6, 1.5e-6, 2.5e-6)
CROSS_TAU = {(1, 0): 0.5e-3, (2, 0): 0.8e-3, (0, 1): 0.4e-3, (2, 1): 0.6e-3, (0, 2): 0.3e-3, (1, 2): 0.7e-3}
B0_TAU = (1e-3, 1.5e-3, 0.8e-3)


def make() -> GirfData:
    f = (np.arange(N) - N // 2) / (N * DT)
    s = 2j * np.pi * f
    lp = 1.0 / np.sqrt(1.0 + (f / FC) ** 4)
    lor = lambda x: GAMMA_HZ**2 / (x**2 + GAMMA_HZ**2)  # noqa: E731
    H = np.zeros((3, 3, N), dtype=np.complex128)
    for a in range(3):
        H[a, a] = lp * (1 + AR * (lor(f - F_RES[a]) + lor(f + F_RES[a]))) * np.exp(-s * DELAY[a])
        H[a, a] /= H[a, a][N // 2].real  # DC gain exactly 1
    for (o, i), tau in CROSS_TAU.items():
        H[o, i] = 0.01 * s * tau / (1 + s * tau) * lp
    H0 = np.stack([0.02 * s * tau / (1 + s * tau) * lp for tau in B0_TAU])
    dt, t0, h = freq_to_taps(f, H)
    _, _, h0 = freq_to_taps(f, H0)
    return GirfData(
        dt_s=dt,
        t0_s=t0,
        h=h,
        h0=h0,
        source="girf/make_example.py (self-made parametric model)",
        notes=[
            "synthetic 7 T-like GIRF: fc 10.7 kHz, 3 % resonances at 1.1/1.3/0.9 kHz, 1 % cross terms, "
            "0.02 uT/(mT/m) high-pass B0 terms; see girf/make_example.py"
        ],
    )


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("-o", default=str(Path(__file__).with_name("example_7T.npz")))
    ap.add_argument("--force", action="store_true")
    a = ap.parse_args()
    print(save_girf(make(), a.o, force=a.force))
