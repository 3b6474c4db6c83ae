"""The warm start's steps are replayable as CUDA graphs (issue 33, Build point 2; dtoc.util.replay).

A CUDA graph holds a step only if the step never waits for the device and moves no host data: no
``aten::_local_scalar_dense`` (``.item()``, ``float()``/``bool()`` of a tensor, a Python branch on a value), no
``nonzero``/``masked_select``/``unique`` (a shape read from the device), no ``lift_fresh`` (a tensor made from host
data: numpy or a Python list).  Checked here on the CPU, with the GPU's schedule (the twin's recursion by FFT) and
the projection's tensor path (:data:`dtoc.optimize.limits.HOST_DEVICES` emptied), around every step that
:class:`~dtoc.util.replay.Replay` wraps during real ``dtoc.optimize_sequence`` runs: the affine solve's evaluation
(README-like EPI, example 7 T GIRF), the fixed-count warm start's evaluation and projected FISTA iteration and the
exact projections' Dykstra rounds (the Figure-5 GRE with the paper's eddy model).  On CUDA
(tests/test_sim_cuda.py) the same steps are captured and replayed, with the numbers of the eager steps.
"""

from __future__ import annotations

import sys
from collections import Counter
from pathlib import Path

import pytest
import torch
from torch.utils._python_dispatch import TorchDispatchMode

import dtoc
from dtoc.util.replay import Replay

REPO = Path(__file__).resolve().parents[1]
_PKG = Path(dtoc.__file__).resolve().parent
_FORBIDDEN = ("_local_scalar_dense", "aten.item", "nonzero", "masked_select", "aten.unique", "lift_fresh")


class _Forbid(TorchDispatchMode):
    """Records (op, innermost dtoc line) of every forbidden operation dispatched inside."""

    def __init__(self):
        super().__init__()
        self.n = 0
        self.bad: Counter = Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        self.n += 1
        if any(b in str(func) for b in _FORBIDDEN):
            f = sys._getframe(1)
            while f is not None and not Path(f.f_code.co_filename).resolve().is_relative_to(_PKG):
                f = f.f_back
            where = "?" if f is None else f"{Path(f.f_code.co_filename).name}:{f.f_lineno}"
            self.bad[(str(func), where)] += 1
        return func(*args, **(kwargs or {}))


@pytest.fixture
def watched(monkeypatch):
    """Every Replay'd step after its warm-up calls (those a GPU would capture and replay) runs under
    :class:`_Forbid`; returns (ops per step name, forbidden ops)."""
    from dtoc.hardware import recursion
    from dtoc.optimize import limits

    monkeypatch.setattr(recursion, "batched", lambda device: True)
    monkeypatch.setattr(limits, "HOST_DEVICES", frozenset())
    seen: Counter = Counter()
    bad: Counter = Counter()
    orig = Replay.__call__

    def call(self, *inputs):
        self._watched = getattr(self, "_watched", 0) + 1
        if self._watched <= self.warmup:  # the eager warm-up calls (they make the device's constants)
            return orig(self, *inputs)
        with _Forbid() as m:
            out = orig(self, *inputs)
        seen[getattr(self.step, "__name__", "?")] += m.n
        bad.update(m.bad)
        return out

    monkeypatch.setattr(Replay, "__call__", call)
    return seen, bad


def test_the_affine_solves_evaluation_reads_nothing_back(watched, tmp_path):
    """README-like job (the bundled 32x32 EPI, example 7 T GIRF, solved to the tolerance): every evaluation of
    the solver's quadratic and every Dykstra projection is free of host reads."""
    from dtoc.optimize.config import load_config

    seen, bad = watched
    ir = dtoc.load_sequence(REPO / "sequences" / "epi_small.seq")
    cfg = load_config("epi", None, {"iters": 0})
    res = dtoc.optimize_sequence(
        ir, girf=REPO / "girf" / "example_7T.npz", out=tmp_path / "o.seq", config=cfg, force=True
    )
    assert res.manifest["solver"]["evaluations"] > 10
    assert seen["_step"] > 1000 and seen["<lambda>"] > 100, seen  # evaluations and Dykstra rounds ran watched
    assert not bad, bad


def test_the_fixed_count_warm_starts_fista_iteration_reads_nothing_back(watched, tmp_path):
    """The Figure-5 GRE with the paper's eddy model, a fixed-count warm start (CG, then projected FISTA with its
    restart decided on the device): the evaluation and the whole FISTA iteration (evaluation, projection,
    restart, momentum) are free of host reads."""
    from dtoc.optimize.config import load_config

    seen, bad = watched
    ir = dtoc.load_sequence(REPO / "sequences" / "gre_small.seq")
    cfg = load_config("gre", None, {"iters": 0, "warm_iters": 40, "n_dummies": 0, "gmax_mT_per_m": 10.0})
    dtoc.optimize_sequence(
        ir, model=REPO / "girf" / "paper_eddy_both.json", out=tmp_path / "o.seq", config=cfg, force=True
    )
    assert seen["_fista_step"] > 1000 and seen["_value_grad"] > 1000, seen
    assert not bad, bad


def test_replay_runs_the_step_eagerly_on_the_cpu():
    """On the CPU nothing is captured: the step itself runs each call (state 'eager'), same outputs."""
    calls = []

    def step(x):
        calls.append(1)
        return (2.0 * x, x.sum())

    r = Replay(step)
    x = torch.arange(4.0)
    for _ in range(4):
        a, s = r(x)
    assert len(calls) == 4 and r.state == "eager" and r.replays == 0
    assert torch.equal(a, 2.0 * x) and float(s) == 6.0
