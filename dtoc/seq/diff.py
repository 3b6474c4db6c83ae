"""Semantic comparison of two ``.seq`` files (``dtoc diff``), for CI regression of outputs.

Compared: definitions (numbers within tolerance, strings exactly; not the provenance entry
``DtocBaseSha256`` an optimize output records), the block count and each block's
duration, RF events (flip angle, phase, frequency offset, delay, centre, duration, use) and ADC events
(samples, dwell, delay, phase, frequency offset), and the played gradient waveforms on the fine grid.
A number ``a`` matches ``b`` when ``|a - b| <= atol + rtol * |b|`` (gradients: ``rtol`` times the
largest |g| of that axis); ``atol`` is in the quantity's own unit (mT/m, s, rad, Hz).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dtoc.constants import AXES, BASE_HASH_DEFINITION


@dataclass
class DiffResult:
    a: str
    b: str
    rtol: float
    atol: float
    differences: list[dict] = field(default_factory=list)
    n_differences: int = 0  # all differences found (``differences`` lists at most ``max_items``)

    @property
    def same(self) -> bool:
        return not self.differences

    def to_dict(self) -> dict:
        return {
            "a": self.a,
            "b": self.b,
            "rtol": self.rtol,
            "atol": self.atol,
            "same": self.same,
            "n_differences": self.n_differences,
            "n_listed": len(self.differences),
            "differences": self.differences,
        }


def _close(x: float, y: float, rtol: float, atol: float) -> bool:
    return abs(x - y) <= atol + rtol * abs(y)


def diff_ir(
    ia, ib, rtol: float = 1e-6, atol: float = 1e-9, a: str = "A", b: str = "B", max_items: int = 50
) -> DiffResult:
    """Compare two :class:`SequenceIR` (with their definitions and events)."""
    res = DiffResult(str(a), str(b), rtol, atol)
    d = res.differences

    def add(kind, where, va, vb):
        res.n_differences += 1
        if len(d) < max_items:
            d.append({"what": kind, "where": where, "a": va, "b": vb})

    # definitions
    da, db = ia.definitions, ib.definitions
    for k in sorted((set(da) | set(db)) - {BASE_HASH_DEFINITION}):  # provenance, not what plays
        if k not in da or k not in db:
            add("definition", k, da.get(k), db.get(k))
            continue
        va, vb = da[k], db[k]
        if isinstance(va, str) or isinstance(vb, str):
            if str(va).strip() != str(vb).strip():
                add("definition", k, va, vb)
            continue
        xa, xb = np.atleast_1d(np.asarray(va, float)), np.atleast_1d(np.asarray(vb, float))
        if xa.shape != xb.shape or not all(_close(p, q, rtol, atol) for p, q in zip(xa, xb)):
            add("definition", k, va, vb)
    # blocks
    ea, eb = np.asarray(ia.block_edges_s), np.asarray(ib.block_edges_s)
    if len(ea) != len(eb):
        add("block_count", "", len(ea) - 1, len(eb) - 1)
    else:
        dur_a, dur_b = np.diff(ea), np.diff(eb)
        for i in np.flatnonzero(np.abs(dur_a - dur_b) > atol + rtol * np.abs(dur_b)):
            add("block_duration", f"block {i + 1} (s)", float(f"{dur_a[i]:.9g}"), float(f"{dur_b[i]:.9g}"))
    # RF / ADC events
    for name, la, lb, fields in (
        (
            "rf",
            ia.rf,
            ib.rf,
            ("block", "t_start_s", "t_center_s", "duration_s", "flip_angle_rad", "phase_rad", "freq_offset_hz", "use"),
        ),
        ("adc", ia.adc, ib.adc, ("block", "t_start_s", "num_samples", "dwell_s", "phase_rad", "freq_offset_hz")),
    ):
        if len(la) != len(lb):
            add(f"{name}_count", "", len(la), len(lb))
            continue
        for i, (x, y) in enumerate(zip(la, lb)):
            for f in fields:
                vx, vy = getattr(x, f), getattr(y, f)
                if f in ("block", "num_samples", "use"):
                    if vx != vy:
                        add(name, f"{name} {i} (block {x.block + 1}) {f}", vx, vy)
                elif not _close(float(vx), float(vy), rtol, atol):
                    add(name, f"{name} {i} (block {x.block + 1}) {f}", float(vx), float(vy))
    # played gradients
    ga, gb = ia.grad_mT_per_m, ib.grad_mT_per_m
    if ga.shape != gb.shape or ia.raster_s != ib.raster_s:
        add("gradient_grid", "", [list(ga.shape), ia.raster_s], [list(gb.shape), ib.raster_s])
    else:
        for ax in range(3):
            tol = atol + rtol * max(np.abs(ga[ax]).max(), np.abs(gb[ax]).max())
            err = np.abs(ga[ax] - gb[ax])
            bad = np.flatnonzero(err > tol)
            if bad.size:
                i = int(bad[np.argmax(err[bad])])
                blk = int(ia.block_of_fine_index(np.array([i]))[0]) + 1
                add(
                    "gradient",
                    f"{AXES[ax]}: {bad.size} samples differ, worst at t = {i * ia.dt_fine_s * 1e3:.4f} ms (block {blk})",
                    float(ga[ax, i]),
                    float(gb[ax, i]),
                )
    return res


def diff_files(path_a: str | Path, path_b: str | Path, rtol: float = 1e-6, atol: float = 1e-9) -> DiffResult:
    """Compare two ``.seq`` files (both read with signature checks)."""
    from dtoc.seq.read import read_seq

    return diff_ir(read_seq(path_a), read_seq(path_b), rtol=rtol, atol=atol, a=str(path_a), b=str(path_b))
