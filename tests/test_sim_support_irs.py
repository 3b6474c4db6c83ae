"""Synthetic Cartesian sequences (SequenceIR built directly, no file I/O) for the sim-support tests.

``cartesian_gre_ir(nx, ny, fov)``: one excitation per phase line, readout along x with ADC sample i at
k_x = (i - nx/2) dkx and line l at k_y = (l - ny/2) dky exactly (PWL-exact trapezoid areas), so a
plain iFFT reconstruction needs no interpolation.  Also tested here: the builder puts every sample on
the grid (the premise of the reconstruction tests).
"""

from __future__ import annotations

import numpy as np

from dtoc.constants import GAMMA_RAD_PER_S_PER_MT
from dtoc.seq.ir import ADCEvent, RFEvent, SequenceIR, edges_to_fine


def _trap(edges: np.ndarray, start: int, area_mT_s_per_m: float, ramp: int, flat: int, raster: float) -> int:
    """Add a trapezoid (ramps of ``ramp`` raster steps) of the given area at edge ``start``; return end edge."""
    amp = area_mT_s_per_m / ((ramp + flat) * raster)
    edges[start : start + ramp + 1] = amp * np.arange(ramp + 1) / ramp
    edges[start + ramp : start + ramp + flat + 1] = amp
    edges[start + ramp + flat : start + 2 * ramp + flat + 1] = amp * (1 - np.arange(ramp + 1) / ramp)
    return start + 2 * ramp + flat


def cartesian_gre_ir(
    nx: int = 8,
    ny: int = 8,
    fov_m=(0.032, 0.032),
    *,
    raster_s: float = 10e-6,
    dwell_steps: int = 4,
    tr_steps: int | None = None,
    flip_deg: float = 15.0,
    rf_spoil_deg: float = 0.0,
) -> SequenceIR:
    """A 2D Cartesian gradient echo: readout x, phase y, one line per TR (see module docstring)."""
    fov = np.asarray(fov_m, dtype=np.float64)
    dkx, dky = 2 * np.pi / fov
    g = GAMMA_RAD_PER_S_PER_MT
    dwell = dwell_steps * raster_s
    ramp = 4
    rf_steps = 20
    ro_flat = nx * dwell_steps
    g_ro = dkx / (g * dwell)  # mT/m
    area_ro_ramp = 0.5 * g_ro * ramp * raster_s
    pre_len = 2 * ramp + 6
    line_len = rf_steps + pre_len + ramp + ro_flat + ramp + 2 * ramp + 6 + 4
    tr = tr_steps or line_len
    assert tr >= line_len
    n_edges = ny * tr + 1
    gx = np.zeros(n_edges)
    gy = np.zeros(n_edges)
    gz = np.zeros(n_edges)
    rf, adc, block_edges = [], [], []
    for ln in range(ny):
        t0 = ln * tr
        block_edges += [t0, t0 + rf_steps, t0 + rf_steps + pre_len, t0 + rf_steps + pre_len + 2 * ramp + ro_flat]
        phase_rad = np.deg2rad(0.5 * rf_spoil_deg * ln * (ln + 1)) if rf_spoil_deg else 0.0
        rf.append(
            RFEvent(
                block=4 * ln,
                t_start_s=t0 * raster_s,
                t_center_s=(t0 + rf_steps / 2) * raster_s,
                duration_s=rf_steps * raster_s,
                flip_angle_rad=np.deg2rad(flip_deg),
                phase_rad=phase_rad,
                freq_offset_hz=0.0,
                use="excitation",
            )
        )
        s = t0 + rf_steps
        kx_pre = -(nx / 2 + 0.5) * dkx
        _trap(gx, s, kx_pre / g - area_ro_ramp, ramp, 6, raster_s)
        _trap(gy, s, (ln - ny / 2) * dky / g, ramp, 6, raster_s)
        s += pre_len
        _trap(gx, s, g_ro * (ro_flat + ramp) * raster_s, ramp, ro_flat, raster_s)
        adc.append(
            ADCEvent(
                block=4 * ln + 2, t_start_s=(s + ramp) * raster_s, num_samples=nx, dwell_s=dwell, phase_rad=phase_rad
            )
        )
        s += 2 * ramp + ro_flat
        _trap(gy, s, -(ln - ny / 2) * dky / g, ramp, 6, raster_s)  # rewinder
        _trap(gx, s, 2.0 * nx * dkx / g, ramp, 6, raster_s)  # spoiler
    block_edges.append(ny * tr)
    grad = edges_to_fine(np.stack([gx, gy, gz]))
    return SequenceIR(
        raster_s=raster_s,
        grad_mT_per_m=grad,
        block_edges_s=np.asarray(block_edges) * raster_s,
        rf=rf,
        adc=adc,
        fov_m=(float(fov[0]), float(fov[1]), 0.005),
        matrix=(nx, ny),
        kind="gre",
        readout_axis=0,
        phase_axis=1,
    )


def test_builder_samples_on_grid():
    ir = cartesian_gre_ir(6, 4, (0.03, 0.024))
    k0 = ir.nominal_kspace_rad_per_m()
    dk = 2 * np.pi / np.array([0.03, 0.024])
    u = k0[:2] / dk[:, None]
    assert np.max(np.abs(u - np.rint(u))) < 1e-9
    assert np.allclose(u[0, :6], np.arange(6) - 3, atol=1e-9)
    assert np.allclose(u[1, ::6], np.arange(4) - 2, atol=1e-9)
