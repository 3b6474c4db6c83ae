"""The twin's hardware chain reads no device tensor on the host (issue 33): run on a waveform on the
``meta`` device, whose values cannot be read at all (``.item()``/``float()`` raise), as a GPU tensor's
cannot without a device synchronisation.  The parameters live on the host (float64, cast on use), so
integer shifts computed from them are free; the exponential recursions take their FFT form off the CPU
(dtoc/hardware/recursion.py)."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

import dtoc
from dtoc.hardware.effects import B0Eddy, CrossEddy, Delay, ExpEddy, Gain, Offset, Resonance
from dtoc.hardware.model import HardwareModel

REPO = Path(__file__).resolve().parents[1]


def _meta(T: int = 4000) -> torch.Tensor:
    return torch.zeros((1, 3, T), dtype=torch.float64, device="meta")


def test_parametric_chain_reads_nothing_on_the_host():
    """Delay (fractional, the integer shift from the host parameter), the three eddy kinds, gain, offset and a
    coil resonance: the forward runs on meta tensors and keeps the shapes."""
    m = HardwareModel(
        [
            Delay(1.37e-5),
            ExpEddy([0.1, 0.1], [1e-3, 0.1]),
            CrossEddy([0.01], [5e-3], axis="y", input_axis="x"),
            B0Eddy([0.2], [2e-3], input_axis="z"),
            Gain(0.98, axis="x"),
            Offset(0.01, axis="z"),
            Resonance(1300.0, 20.0, 0.01),
        ]
    ).frozen()
    G, b0 = m(_meta(), 5e-6)
    assert G.shape == (1, 3, 4000) and G.device.type == "meta"
    assert b0 is not None and b0.shape == (1, 4000)


@pytest.mark.parametrize(
    "model", [dict(girf=REPO / "girf" / "example_7T.npz"), dict(model=REPO / "girf" / "paper_eddy_both.json")]
)
def test_shipped_models_read_nothing_on_the_host(model):
    """The example 7 T GIRF (FFT convolution with its B0 row) and the paper's eddy model, as ``dtoc`` loads them."""
    G, _ = dtoc.load_model(**model)(_meta(20_000), 5e-6)
    assert G.shape == (1, 3, 20_000) and G.device.type == "meta"
