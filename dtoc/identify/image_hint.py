"""Image-level hint: fit effect parameters to measured EPI raw data through the differentiable twin.

The Nyquist ghost of an EPI comes from readout k-space positions that differ between odd and even echoes;
an unmodelled gradient delay on the readout axis is the classic cause.  Given the base EPI, the declared model
and the measured raw ADC signal of one scan of a known object (a phantom), :func:`fit_delays_to_raw` appends
``delay`` effects on the chosen axes to the declared model and minimises

    L(tau) = || s_measured - s_twin(tau) ||^2 / || s_measured ||^2

where ``s_twin`` is the PDG simulation of the base sequence played through declared model + delays
(:class:`dtoc.sim.imager.Imager`, differentiable), by L-BFGS on the delays (in us) with gradients from
autograd through simulator and hardware model.  Returns the fitted delays, the loss and the EPI ghost ratio of
the reconstructed twin images before/after, and the updated model.

Scope (optional part of issue 6): only delays, only raw data (not magnitude images), object known.  It is the
same forward model as identify/optimize; the tests check that a 3.5 us x delay is recovered from the raw data
of a simulated scan to within 0.1 us.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from dtoc.hardware.model import HardwareModel, build_effect


@dataclass
class RawFit:
    delays_s: dict  # axis -> fitted delay, s
    loss_before: float  # ||s_meas - s_twin||^2 / ||s_meas||^2 with the declared model
    loss_after: float  # same with the fitted delays
    ghost_measured: float | None  # EPI ghost ratio of the image reconstructed from the measured raw data
    ghost_twin_before: float | None  # ... as the declared model predicts it
    ghost_twin_after: float | None  # ... as the model with the fitted delays predicts it
    iterations: int
    model: HardwareModel


def _ghost(img, ref, ir) -> float | None:
    from dtoc.sim import metrics

    if ir.kind != "epi":
        return None
    return float(metrics.ghost_ratio(img, ref, phase_dim=ir.phase_image_dim))


def fit_delays_to_raw(
    ir, phantom, declared: HardwareModel | None, signal_measured, axes=("x",), max_iter: int = 30
) -> RawFit:
    """Fit per-axis delays (appended to ``declared``) to a measured raw signal of ``ir`` on ``phantom``.

    Args:
        ir: base sequence (:class:`dtoc.seq.ir.SequenceIR`), Cartesian, e.g. an EPI.
        phantom: the scanned object (:class:`dtoc.sim.phantom.Phantom`).
        declared: declared hardware model (None: ideal).
        signal_measured: complex raw ADC signal, shape as :meth:`Imager.signal` returns.
        axes: axes whose delay is fitted.
    """
    from dtoc.sim.imager import Imager

    declared = declared if declared is not None else HardwareModel([])
    for p in declared.parameters():
        p.requires_grad_(False)
    imager = Imager(ir, [phantom])
    s_meas = torch.as_tensor(signal_measured)
    g = torch.as_tensor(ir.grad_mT_per_m, dtype=torch.float64)
    dt = ir.dt_fine_s
    with torch.no_grad():
        G0, b00 = declared(g, dt)
    delays = [build_effect("delay", {"seconds": 0.0}, axis=a) for a in axes]
    chain = HardwareModel(delays)
    u = torch.zeros(len(axes), dtype=torch.float64, requires_grad=True)  # delays in us
    norm = float((s_meas.abs() ** 2).sum())

    def loss_of(uu):
        for d, v in zip(delays, uu):
            d.seconds.data = (v * 1e-6).detach().clone()
        over = {f"effects.{i}.seconds": uu[i] * 1e-6 for i in range(len(axes))}
        G, b0 = torch.func.functional_call(chain, over, (G0, dt), {"b0": b00})
        s = imager.signal(G, b0, 0)
        return ((s - s_meas).abs() ** 2).sum() / norm, s

    with torch.no_grad():
        l0, s0 = loss_of(u.detach())
    opt = torch.optim.LBFGS(
        [u], lr=1.0, max_iter=max_iter, line_search_fn="strong_wolfe", tolerance_grad=1e-12, tolerance_change=1e-14
    )
    n_eval = [0]

    def closure():
        opt.zero_grad()
        loss, _ = loss_of(u)
        loss.backward()
        n_eval[0] += 1
        return loss

    opt.step(closure)
    with torch.no_grad():
        l1, s1 = loss_of(u.detach())
        ref = imager.targets[0]
        gm = _ghost(imager.image(s_meas), ref, ir)
        g0 = _ghost(imager.image(s0), ref, ir)
        g1 = _ghost(imager.image(s1), ref, ir)
    fitted = {a: float(v) * 1e-6 for a, v in zip(axes, u.detach())}
    model = HardwareModel(
        [*declared.effects, *[build_effect("delay", {"seconds": fitted[a]}, axis=a) for a in axes]],
        description=(declared.description or "declared model") + " + delays fitted to EPI raw data",
    )
    return RawFit(fitted, float(l0), float(l1), gm, g0, g1, n_eval[0], model)
