"""bench.identify_public: the conversion of the public Bruker-GIRF triangles (issue 37, point 6).

The data are not in the repository; these tests write ParaVision-style JCAMP files whose k is the exact
integral of the nominal triangles and check that the conversion gives back the contract's units and times.
"""

from __future__ import annotations

import numpy as np
import pytest

from bench.identify_public import (
    BRUKER_AMP,
    BRUKER_DT,
    BRUKER_FILES,
    BRUKER_N,
    BRUKER_SLEW,
    _jcamp_arrays,
    load_bruker,
)

GAMMA_BAR = 42.577478e6  # Hz/T


def _write_jcamp(path, arrays: dict[str, np.ndarray]) -> None:
    lines = ["##TITLE=Parameter List, ParaVision 6.0.1", "##JCAMPDX=4.24", "$$ synthetic"]
    for name, v in arrays.items():
        lines.append(f"##$PVM_Traj{name}=( {v.size} )")
        lines += [" ".join(repr(float(x)) for x in v[i : i + 5]) for i in range(0, v.size, 5)]
    lines.append("##END=")
    path.write_text("\n".join(lines) + "\n")


def _nominal_k_per_mm(m: int, delay_s: float = 0.0) -> np.ndarray:
    """k (1/mm, the files' unit) of triangle m (1-based) played exactly, shifted by ``delay_s``."""
    t = np.arange(BRUKER_N) * BRUKER_DT - delay_s
    amp = m * BRUKER_AMP * 1e-3  # T/m
    rise = 4 * m * BRUKER_DT
    s = amp / rise
    k = np.where(t <= 0, 0.0, 0.0)
    k = np.where((t > 0) & (t <= rise), 0.5 * s * t**2, k)
    k = np.where((t > rise) & (t <= 2 * rise), amp * rise - 0.5 * s * (2 * rise - t) ** 2, k)
    k = np.where(t > 2 * rise, amp * rise, k)
    return GAMMA_BAR * k * 1e-3


@pytest.fixture(scope="module")
def bruker_folder(tmp_path_factory):
    folder = tmp_path_factory.mktemp("bruker_girf")
    for m, num in enumerate(BRUKER_FILES, start=1):
        k = _nominal_k_per_mm(m)
        _write_jcamp(
            folder / f"result_{num}.jcamp",
            {"Kx": k, "Bx": 0 * k, "Ky": 0.99 * k, "By": 0 * k, "Kz": _nominal_k_per_mm(m, 4e-6), "Bz": 0 * k},
        )
    return folder


def test_bruker_conversion_units_times_and_axes(bruker_folder):
    d = load_bruker(bruker_folder)
    M = 3 * len(BRUKER_FILES)
    assert d.g.shape == (M, 3, BRUKER_N) and d.k.shape == (M, 3, BRUKER_N)
    assert d.dt_s == BRUKER_DT
    # one axis driven and measured per waveform, in the order x, y, z of each file
    assert (d.axes_measured == np.tile(np.eye(3, dtype=bool), (len(BRUKER_FILES), 1))).all()
    assert ((d.g != 0).any(axis=2) == d.axes_measured).all()
    last = d.g[-3, 0]
    assert last.max() == pytest.approx(13 * BRUKER_AMP, rel=1e-12)
    # peak at sample 4m, zero from sample 8m on; the demanded slew is the data set's
    assert int(np.argmax(last)) == 4 * 13 and not last[8 * 13 :].any()
    assert np.abs(np.diff(last)).max() / BRUKER_DT * 1e-3 == pytest.approx(BRUKER_SLEW, rel=1e-5)
    # k in rad/m: the exact integral of the demanded triangle (the PWL prediction identify makes)
    gamma = 2 * np.pi * GAMMA_BAR
    for i in range(0, M, 3):
        g = d.g[i, 0]
        kp = gamma * 1e-3 * np.concatenate([[0.0], np.cumsum(0.5 * (g[1:] + g[:-1]) * BRUKER_DT)])
        np.testing.assert_allclose(d.k[i, 0], kp, rtol=1e-12, atol=1e-9 * np.abs(kp).max())
        np.testing.assert_allclose(d.k[i + 1, 1], 0.99 * kp, rtol=1e-12, atol=1e-9 * np.abs(kp).max())
        # z was written two samples late: the same k, two samples later (the conversion adds no time shift)
        np.testing.assert_allclose(d.k[i + 2, 2, 2:], kp[:-2], rtol=1e-12, atol=1e-9 * np.abs(kp).max())
    assert d.labels[:3] == ["x triangle 48.6 mT/m", "y triangle 48.6 mT/m", "z triangle 48.6 mT/m"]


def test_jcamp_count_mismatch_is_an_error(tmp_path):
    p = tmp_path / "result_7.jcamp"
    p.write_text("##$PVM_TrajKx=( 4 )\n1 2 3\n##END=\n")
    with pytest.raises(ValueError, match="PVM_TrajKx holds 3 values, header says 4"):
        _jcamp_arrays(p)
