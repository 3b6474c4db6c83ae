"""A fixed-shape step replayed as one CUDA graph: thousands of small kernels launched by one call.

An optimizer's iteration on a 64x64 EPI is a few hundred small torch operations; on a GPU each costs a kernel
launch plus Python, so the iteration runs at the launch latency, not at the GPU's speed (docs/optimize.md,
"Execution on a GPU").  :class:`Replay` wraps such a step -- a function of tensors whose shapes, dtypes and
devices do not change from call to call, which never waits for the device (no ``.item()``, no copy to the host,
no branch on a tensor's value) and moves no host data (every constant it reads already on the device) -- and
on CUDA captures it once (``torch.cuda.CUDAGraph``) after ``warmup`` eager calls, then replays the graph with
each call's inputs copied into the captured ones.  The graph runs the same kernels on the same data as the eager
step, so the numbers are those of the eager step.  On the CPU (or with ``DTOC_CUDA_GRAPHS=0``) the step runs
eagerly: the same code, the same numbers as before.  A capture that fails (an operation that waits for the
device, a shape that changes) leaves the step eager for the rest of the run and says why in :attr:`Replay.state`.

A Replay called while another is being captured runs its step inline (its operations join the outer graph).
Only the step's tensor outputs come back (cloned: the graph's own buffers are overwritten by the next replay);
Python side effects inside the step run during the eager calls and the capture, never on a replay.
"""

from __future__ import annotations

import os
from collections.abc import Callable

import torch

#: environment variable: "0" keeps every step eager on CUDA too (to compare, or to rule the graphs out)
ENV = "DTOC_CUDA_GRAPHS"


def enabled(device: torch.device) -> bool:
    """True where a step on ``device`` is captured: CUDA, unless ``DTOC_CUDA_GRAPHS=0``."""
    return device.type == "cuda" and os.environ.get(ENV, "1") != "0"


#: process-wide counts, for the manifest and the benchmarks: steps captured, replays run, captures that failed
#: (their reasons, the first few)
TOTALS: dict = {"captured": 0, "replays": 0, "failed": []}


def totals() -> dict:
    """A copy of :data:`TOTALS` (captured, replays, failed reasons)."""
    return {"captured": TOTALS["captured"], "replays": TOTALS["replays"], "failed": list(TOTALS["failed"])}


class Replay:
    """``step(*tensors) -> tuple of tensors`` captured once as a CUDA graph and replayed (module doc).

    Args:
        step: the function; its inputs' shapes, dtypes and devices are fixed after the first call.
        warmup: eager calls (on a side stream, as CUDA graph capture requires) before the capture.
    Attributes:
        state: 'eager' (CPU, or off), 'warming', 'graph' (captured; replays), or 'eager (capture failed: ...)'.
        replays: how many calls ran as a replay.
    """

    def __init__(self, step: Callable[..., tuple[torch.Tensor, ...]], warmup: int = 2):
        self.step = step
        self.warmup = warmup
        self.state = "eager"
        self.replays = 0
        self._calls = 0
        self._graph: torch.cuda.CUDAGraph | None = None
        self._inputs: list[torch.Tensor] = []
        self._outputs: tuple[torch.Tensor, ...] = ()

    def __call__(self, *inputs: torch.Tensor) -> tuple[torch.Tensor, ...]:
        dev = inputs[0].device
        if not enabled(dev) or self.state.startswith("eager (") or torch.cuda.is_current_stream_capturing():
            return self.step(*inputs)  # (inside another step's capture: its operations join that graph)
        if self._graph is None:
            self._calls += 1
            if self._calls <= self.warmup:
                self.state = "warming"
                side = torch.cuda.Stream(dev)
                side.wait_stream(torch.cuda.current_stream(dev))
                with torch.cuda.stream(side):
                    out = self.step(*inputs)
                torch.cuda.current_stream(dev).wait_stream(side)
                return out
            try:
                self._capture(inputs)
            except Exception as e:  # noqa: BLE001 -- any failure leaves the step eager, with its reason
                self._graph = None
                self.state = f"eager (capture failed: {type(e).__name__}: {str(e).splitlines()[0][:160]})"
                if len(TOTALS["failed"]) < 8:
                    TOTALS["failed"].append(f"{getattr(self.step, '__qualname__', '?')}: {self.state}")
                torch.cuda.synchronize(dev)
                return self.step(*inputs)
        if len(inputs) != len(self._inputs) or any(
            a.shape != b.shape or a.dtype != b.dtype for a, b in zip(inputs, self._inputs)
        ):
            raise ValueError("Replay: a captured step was called with inputs of other shapes or dtypes")
        for buf, x in zip(self._inputs, inputs):
            buf.copy_(x.detach())
        assert self._graph is not None
        self._graph.replay()
        self.replays += 1
        TOTALS["replays"] += 1
        return tuple(o.clone() for o in self._outputs)

    def _capture(self, inputs: tuple[torch.Tensor, ...]) -> None:
        dev = inputs[0].device
        self._inputs = [x.detach().clone() for x in inputs]
        torch.cuda.synchronize(dev)
        g = torch.cuda.CUDAGraph()
        with torch.cuda.graph(g):
            out = self.step(*self._inputs)
        self._outputs = tuple(out)
        self._graph = g
        self.state = "graph"
        TOTALS["captured"] += 1
