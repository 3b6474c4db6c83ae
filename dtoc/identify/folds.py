"""Held-out evaluation: which samples fit a model and which judge it.

With several test waveforms the folds are waveforms (k-fold, K = min(M, 5), waveform m in fold m % K;
repeats of the same demanded waveform are kept in one fold, counted by distinct waveforms): a model fitted on
the other waveforms is judged on waveforms it never saw, which is what matters when the updated model later
predicts a new sequence.  With a single (distinct) waveform the folds are K = 4 contiguous time blocks: the prediction still uses the whole demanded waveform (the hardware is causal and has memory), only
the samples that enter the fit and the score differ.

The atoms are *units* (one waveform, or one time block of the single waveform); statistics are accumulated
per unit so that any fold's train/test sums are cheap combinations.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Unit:
    """Samples n0 <= n < n1 of waveform m."""

    m: int
    n0: int
    n1: int


@dataclass(frozen=True)
class Folds:
    """Units and their fold assignment."""

    mode: str  # "waveforms" | "time blocks"
    units: tuple
    fold_of_unit: tuple
    M: int
    N: int

    @property
    def K(self) -> int:
        return max(self.fold_of_unit) + 1

    def sample_mask(self, fold: int, train: bool) -> np.ndarray:
        """(M, N) float mask: 1 on the train (``train=True``) or test samples of ``fold``."""
        out = np.zeros((self.M, self.N))
        for u, f in zip(self.units, self.fold_of_unit):
            if (f != fold) == train:
                out[u.m, u.n0 : u.n1] = 1.0
        return out

    def describe(self) -> str:
        return f"{self.K}-fold across {self.mode}"


def waveform_groups(g: np.ndarray) -> list:
    """Group index per waveform: waveforms whose demanded ``g`` (M, 3, N) is identical share a group."""
    keys: dict[bytes, int] = {}
    return [keys.setdefault(np.ascontiguousarray(g[m]).tobytes(), len(keys)) for m in range(g.shape[0])]


def make_folds(M: int, N: int, max_folds: int = 5, n_blocks: int = 4, groups=None) -> Folds:
    """Deterministic folds for M waveforms of N samples (see module docstring).

    Args:
        groups: optional group index per waveform (:func:`waveform_groups`): repeats of the same demanded
            waveform always fall into the same fold, so that a held-out waveform is never one the fit has seen
            (with a single distinct waveform, time blocks are used across all of them).
    """
    grp = list(range(M)) if groups is None else [int(x) for x in groups]
    n_groups = len(set(grp))
    if n_groups >= 2:
        order = {gid: i for i, gid in enumerate(dict.fromkeys(grp))}  # groups in order of first appearance
        K = min(n_groups, max_folds)
        units = tuple(Unit(m, 0, N) for m in range(M))
        mode = "waveforms" if n_groups == M else "distinct waveforms (repeats kept together)"
        return Folds(mode, units, tuple(order[grp[m]] % K for m in range(M)), M, N)
    K = max(2, min(n_blocks, N // 16))
    edges = [int(round(i * N / K)) for i in range(K + 1)]
    units = tuple(Unit(m, edges[i], edges[i + 1]) for m in range(M) for i in range(K))
    return Folds("time blocks", units, tuple(i for m in range(M) for i in range(K)), M, N)
