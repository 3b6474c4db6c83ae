"""Options of `dtoc optimize` (pydantic): defaults per sequence type, YAML file, CLI overrides.

Precedence: built-in defaults for the sequence kind (GRE / EPI / other) < YAML config file < command
line.  Every field has a unit in its name where it has one.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from dtoc.constants import DEFAULT_B0_T, default_dummies
from dtoc.errors import InputError


class LossWeights(BaseModel):
    """Weights of the normalised loss terms (see :mod:`dtoc.optimize.loss`).

    Attributes:
        image: L_I = ||I - I0|| / ||I0|| (NRMSE; dimensionless).
        kspace: L_k = mean over ADC samples of sum_axes ((k - k0) / dk)^2 (units dk^2 per sample).
        amplitude: L_g = mean over samples of max(|g| - gmax, 0) / gmax (zero under hard limits).
        slew: L_s = mean over segments of max(|dg/dt| - smax, 0) / smax (zero under hard limits).
        rf: L_tRF = mean over RF-period samples of sum_axes (G - g0)^2 / g_ref^2, g_ref the base's
            peak |g| (the paper penalises realized gradient during RF: g0 = 0 there in GRE).
        moment: L_m = mean over RF pulses of sum_axes ((m - m0)/dk)^2 with m the realized k-space
            moment just before each pulse (dephasing per repetition: spoiling).
        reg: Tikhonov term mean((g - g0)^2) / g_ref^2 of the linear warm start only.
    """

    model_config = ConfigDict(extra="forbid")
    image: float = Field(1.0, ge=0)
    kspace: float = Field(1.0, ge=0)
    amplitude: float = Field(10.0, ge=0)
    slew: float = Field(10.0, ge=0)
    rf: float = Field(1.0, ge=0)
    moment: float = Field(1.0, ge=0)
    reg: float = Field(1e-6, ge=0)


class OptimizeConfig(BaseModel):
    """All options of one optimization run.

    Attributes:
        method: 'dto' (linear warm start then the full loss), 'adam-paper' (the paper's Adam with
            restarts from the base waveform), 'warmstart' (linear warm start only), 'preemphasis'
            (Eq. 2 classic pre-emphasis with fitted coefficients and its TE fallbacks).
        gmax_mT_per_m / smax_T_per_m_per_s: hard limits (default: from the sequence's system limits).
        amp_margin / slew_margin: relative safety margins of the hard limits.
        weights: loss weights (defaults per kind).
        warm_iters: None (default): the warm start is solved to the k-space tolerance ``k_tol_dk``
            (:mod:`dtoc.optimize.solver`, within ``solve_budget`` evaluations); an integer: the fixed-count
            algorithm with that many iterations (CG then projected FISTA, as before the solver).
        k_tol_dk: the warm start's stopping tolerance on the k error of every reachable ADC sample, dk
            (``--k-tol``).
        solve_budget: most objective evaluations (forward + backward passes) of one warm-start solve.
        certify_groups: the worst groups of samples above ``k_tol_dk`` a whole solve certifies after it stops
            (:mod:`dtoc.optimize.certificate`: proven unreachable, reachable, or not proven; two small LPs per
            group, ~0.6 s each on the README job); 0 (default): none, the manifest says so.
        minimax_rounds / minimax_budget: when the solve stops above ``k_tol_dk`` at its least-squares optimum,
            up to this many rounds of Lawson's reweighting towards the smallest worst k error, within this many
            further evaluations (each round at most ``solve_budget``; docs/optimize.md, "Minimax rounds");
            0 rounds: the least-squares optimum (and the CG + FISTA fallback, as before these rounds).
        robust_rounds: rounds of iteratively reweighted least squares after the warm start (Cauchy
            weights on the per-sample k error, scale ``robust_scale_dk`` in dk): samples that cannot
            reach their target within the limits stop pulling the others off theirs (0 = plain LS).
        iters: iterations of the full-loss stage.
        optimizer: full-loss stage of 'dto': 'pgd' (monotone projected gradient with backtracking)
            or 'adam' (projected Adam).  'adam-paper' always uses Adam.
        full_kspace_scale: factor on the k-space weight in the full-loss stage only.
        sim_preset / sim_dtype: PDG simulator preset and precision inside the full-loss loop (image and
            target both simulated with it); the reported before/after figures and the discarding always
            use the default preset in float64.
        lr: Adam learning rate; for 'pgd' the largest first move of any sample, mT/m.
        restarts: Adam restart iterations (paper: 500, 1500, 3000, ... scaled to ``iters``).
        augment_rotations: number of rotated phantoms cycled through (0 = no augmentation).
        augment_max_deg: rotation range +- degrees.
        augment_every: iterations between phantom switches.
        discard: post-hoc discarding of samples whose k-space error exceeds an optimised threshold.
        phantom_size: phantom matrix (default: the sequence's matrix).
        b0_T: field strength of the built-in phantom's tissue values, T (``--b0``; default
            :data:`dtoc.constants.DEFAULT_B0_T`, shared with ``dtoc simulate``).
        n_dummies: dummy repetitions for the steady-state initial magnetisation (0 = none).
        seed: random seed (augmentation angles).
        threads: torch threads (fixed for reproducibility).
        checkpoint_every: iterations between checkpoints when a checkpoint path is set.
        windowed: long sequences (docs/optimize.md, "Long sequences"): 'auto' = solve the warm start one
            excitation period at a time (:mod:`dtoc.optimize.windowed`; k-space terms only, no full-loss stage)
            when the sequence is longer than ``window_auto_s`` or its whole solve is estimated far costlier than
            the windowed one (many short periods), the hardware chain is affine, and no image asked for would
            enter the full loss; an image the optimization does not use (``iters`` 0, warmstart) is kept for the
            report and the discarding (default); 'on' = always (an error when impossible); 'off' = never (the
            whole sequence in one piece: memory and time grow with its length).
        window_auto_s: sequence duration above which 'auto' windows, s.
        window_horizon_max_s: cap of the history / lookahead kept around each period, s (default: the
            hardware's memory, :func:`dtoc.hardware.memory.memory_s`, up to this cap).
    """

    model_config = ConfigDict(extra="forbid")
    method: Literal["dto", "adam-paper", "warmstart", "preemphasis"] = "dto"
    gmax_mT_per_m: float | None = Field(None, gt=0)
    smax_T_per_m_per_s: float | None = Field(None, gt=0)
    amp_margin: float = Field(0.005, ge=0, lt=0.5)
    slew_margin: float = Field(0.01, ge=0, lt=0.5)
    weights: LossWeights = Field(default_factory=LossWeights)
    warm_iters: int | None = Field(None, ge=0)
    k_tol_dk: float = Field(0.01, gt=0)
    solve_budget: int = Field(600, ge=8)
    certify_groups: int = Field(0, ge=0, le=64)
    minimax_rounds: int = Field(8, ge=0)
    minimax_budget: int = Field(1800, ge=0)
    robust_rounds: int = Field(0, ge=0)
    robust_scale_dk: float = Field(0.5, gt=0)
    iters: int = Field(60, ge=0)
    optimizer: Literal["pgd", "adam"] = "pgd"
    full_kspace_scale: float = Field(1.0, ge=0)
    sim_preset: Literal["fast", "default", "strict"] = "fast"
    sim_dtype: Literal["float32", "float64"] = "float32"
    lr: float | None = Field(None, gt=0)
    restarts: list[int] = Field(default_factory=list)
    augment_rotations: int = Field(0, ge=0)
    augment_max_deg: float = Field(90.0, ge=0, le=180)
    augment_every: int = Field(5, ge=1)
    discard: bool = True
    phantom_size: int | None = Field(None, ge=4)
    b0_T: float = Field(DEFAULT_B0_T, gt=0, le=21.1)
    n_dummies: int = Field(0, ge=0)
    seed: int = 0
    threads: int = Field(1, ge=1)
    checkpoint_every: int = Field(20, ge=1)
    windowed: Literal["auto", "on", "off"] = "auto"
    window_auto_s: float = Field(4.0, gt=0)
    window_horizon_max_s: float = Field(0.5, gt=0)


#: Defaults per sequence kind, applied below the config file.
KIND_DEFAULTS: dict[str, dict] = {
    "gre": {
        "weights": {"image": 1.0, "kspace": 1.0, "rf": 1.0, "moment": 0.1},
        "lr": 0.05,
        "iters": 0,
        "n_dummies": default_dummies("gre"),  # shared with dtoc simulate
        # no warm_iters: the warm start is solved to k_tol_dk, the spoiler moments (k before each RF pulse)
        # included in the stopping rule (docs/optimize.md, "Solver")
        "robust_rounds": 3,
        # the robust rounds down-weight the samples the limits leave far off (they are discarded, and the image
        # decides): the minimax rounds would weight those very samples up, the opposite aim
        "minimax_rounds": 0,
    },
    "epi": {
        "weights": {"image": 1.0, "kspace": 4.0, "rf": 1.0},
        "lr": 0.01,
        "iters": 2,
        "n_dummies": default_dummies("epi"),
    },
    # turbo spin echo (an excitation, then refocusing pulses with a readout between them; HASTE too): the k-space
    # warm start is the solution -- k at the ADC samples, the moments before the refocusing pulses (the crushers and
    # the CPMG condition) and G during the pulses -- and the image is the report's (NRMSE), not optimized (as the
    # GRE); docs/optimize.md (the defaults, "Sequence kinds")
    "tse": {
        "weights": {"image": 1.0, "kspace": 1.0, "rf": 1.0, "moment": 1.0},
        "iters": 0,
        "n_dummies": default_dummies("tse"),
    },
}

PAPER_RESTARTS = [500, 1500, 3000, 5000, 7500, 10500, 14000, 18000]


def _deep_update(a: dict, b: dict) -> dict:
    out = dict(a)
    for k, v in b.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = _deep_update(out[k], v)
        else:
            out[k] = v
    return out


def load_config(kind: str | None, path: str | Path | None = None, overrides: dict | None = None) -> OptimizeConfig:
    """Build the run configuration.

    Args:
        kind: sequence kind ('gre', 'epi', 'tse' or None) selecting the built-in defaults.
        path: optional YAML file with any :class:`OptimizeConfig` fields (``weights`` as a mapping).
        overrides: command-line values (``None`` entries are ignored).
    Raises:
        InputError: unreadable file or invalid values (one line naming the field).
    """
    data: dict = dict(KIND_DEFAULTS.get(kind or "", {}))
    if path is not None:
        p = Path(path)
        try:
            loaded = yaml.safe_load(p.read_text()) or {}
        except OSError as e:
            raise InputError(f"{p}: cannot read config ({e.strerror})") from None
        except yaml.YAMLError as e:
            raise InputError(f"{p}: not valid YAML ({str(e).splitlines()[0]})") from None
        if not isinstance(loaded, dict):
            raise InputError(f"{p}: config must be a mapping of option: value")
        data = _deep_update(data, loaded)
    if overrides:
        data = _deep_update(data, {k: v for k, v in overrides.items() if v is not None})
    try:
        return OptimizeConfig(**data)
    except ValidationError as e:
        err = e.errors()[0]
        loc = ".".join(str(x) for x in err["loc"])
        src = f"{path}: " if path else ""
        raise InputError(f"{src}config field '{loc}': {err['msg']}") from None
