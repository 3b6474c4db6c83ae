"""Whitened residuals and the per-unit least-squares statistics every candidate is scored with.

For the current model's prediction P (realized gradient (M, 3, N) mT/m, B0 (M, N) uT) the residual of
each measured channel c is whitened by its noise floor: z_c = (y_c - pred_c) * mask_c / sigma_c, with
pred_k = gamma * cumulative trapezoid of pred_G (docs: :func:`dtoc.identify.data.integrate_k`).  A candidate
effect proposes changes of the prediction, dG (mT/m) and dB0 (uT), one per *column*; the whitened columns
s_j follow the same map.  For a linear model r ~ sum_j theta_j s_j the chi-square is

    chi2(theta) = c - 2 theta.b + theta^T A theta,   A = s s^T,  b = s z,  c = z.z

accumulated per held-out unit (:mod:`dtoc.identify.folds`), so that the fit on any set of folds and the
score on the others are exact and cheap.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dtoc.identify.data import IdentData, integrate_k
from dtoc.identify.folds import Folds


@dataclass
class Prediction:
    """A model's prediction of the measured channels: G (M, 3, N) mT/m and b0 (M, N) uT (None: zero)."""

    G: np.ndarray
    b0: np.ndarray | None = None


class Workspace:
    """Residuals of one prediction, whitened, with per-unit statistics for candidate columns."""

    def __init__(self, data: IdentData, sigma: dict, folds: Folds, pred: Prediction):
        self.data = data
        self.sigma = {c: float(sigma[c]) for c in data.channels()}
        self.folds = folds
        self.masks = {c: data.mask(c) for c in data.channels()}
        self.set_prediction(pred)

    # -- prediction and residual -------------------------------------------------------------------
    def predicted(self, pred: Prediction) -> dict:
        """Predicted channels {c: array like the measurement} of ``pred``."""
        d = self.data
        out = {}
        if d.G is not None:
            out["G"] = pred.G
        if d.k is not None:
            out["k"] = integrate_k(pred.G, d.dt_s)
        if d.b0 is not None:
            out["b0"] = np.zeros((d.M, d.N)) if pred.b0 is None else pred.b0
        return out

    def residuals(self, pred: Prediction) -> dict:
        """Unwhitened residuals measured - predicted per channel, zero where not measured."""
        p = self.predicted(pred)
        return {c: (self.data.measured(c) - p[c]) * self.masks[c] for c in p}

    def set_prediction(self, pred: Prediction) -> None:
        self.pred = pred
        self.res = self.residuals(pred)
        self.z = {c: self.res[c] / self.sigma[c] for c in self.res}
        self.c_units = np.array([self._unit_energy(self.z, u) for u in self.folds.units])

    def _unit_energy(self, z: dict, u) -> float:
        return float(sum(np.sum(z[c][u.m, ..., u.n0 : u.n1] ** 2) for c in z))

    # -- columns ---------------------------------------------------------------------------------
    def whiten_change(self, dG: dict, db0: np.ndarray | None, ms: np.ndarray) -> list:
        """Whitened channel changes of p columns for waveforms ``ms``.

        Args:
            dG: {axis index: (p, len(ms), N)} change of the realized gradient on that axis, mT/m (axes
                not listed are unchanged).
            db0: (p, len(ms), N) change of B0, uT, or None.
        Returns:
            [(channel, axis or None, (p, len(ms), N) whitened and masked change)].
        """
        out = []
        d = self.data
        for a, x in (dG or {}).items():
            if d.G is not None:
                out.append(("G", a, x * self.masks["G"][ms, a][None] / self.sigma["G"]))
            if d.k is not None:
                out.append(("k", a, integrate_k(x, d.dt_s) * self.masks["k"][ms, a][None] / self.sigma["k"]))
        if d.b0 is not None and db0 is not None:
            out.append(("b0", None, db0 / self.sigma["b0"]))
        return out

    def unit_stats(self, make_change, p: int, chunk: int = 4, full: bool = False):
        """Per-unit Gram and projection of the columns produced by ``make_change``.

        Args:
            make_change: callable(ms: int array) -> (dG {axis: (p, len(ms), N)}, db0 (p, len(ms), N) | None).
            p: number of columns.
            chunk: waveforms per call (bounds memory: p * chunk * N floats per changed axis).
            full: return the full Gram (U, p, p) (needed when an option uses several columns together);
                otherwise only its diagonal (U, p) (options of single columns).
        Returns:
            (A, b): A (U, p, p) or (U, p), b (U, p).
        """
        U = len(self.folds.units)
        A = np.zeros((U, p, p)) if full else np.zeros((U, p))
        b = np.zeros((U, p))
        M = self.data.M
        for start in range(0, M, chunk):
            ms = np.arange(start, min(M, start + chunk))
            dG, db0 = make_change(ms)
            W = self.whiten_change(dG, db0, ms)
            for ui, u in enumerate(self.folds.units):
                if not (ms[0] <= u.m <= ms[-1]):
                    continue
                j = u.m - ms[0]
                for c, a, x in W:
                    V = x[:, j, u.n0 : u.n1]
                    zz = self.z[c][u.m, a, u.n0 : u.n1] if a is not None else self.z[c][u.m, u.n0 : u.n1]
                    if full:
                        A[ui] += np.einsum("pn,qn->pq", V, V)  # einsum: no BLAS threads (see docs)
                    else:
                        A[ui] += np.einsum("pn,pn->p", V, V)
                    b[ui] += np.einsum("pn,n->p", V, zz)
        return A, b

    @property
    def n_samples(self) -> int:
        """Number of measured samples over all channels (the n of the information criterion)."""
        if not hasattr(self, "_n_samples"):
            self._n_samples = int(sum(np.sum(self.masks[c] > 0) for c in self.masks))
        return self._n_samples


# -- fold arithmetic ------------------------------------------------------------------------------
def _solve(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Least-squares solve with a tiny relative ridge (guards exactly collinear columns)."""
    p = A.shape[0]
    lam = 1e-12 * max(np.trace(A) / max(p, 1), 1e-300)
    try:
        return np.linalg.solve(A + lam * np.eye(p), b)
    except np.linalg.LinAlgError:
        return np.linalg.lstsq(A, b, rcond=None)[0]


def chi2_of(theta, A, b, c) -> float:
    """c - 2 theta.b + theta^T A theta for summed statistics."""
    return float(c - 2.0 * theta @ b + theta @ A @ theta)


@dataclass
class OptionResult:
    """Cross-validated result of one candidate option (a column set, free or fixed coefficients)."""

    cv_chi2: float  # sum over folds of the test chi2 (fit on the other folds)
    full_chi2: float  # chi2 of the fit on all data
    theta: np.ndarray  # coefficients fitted on all data
    option: int  # index of the option chosen on all data


def cross_validate(A, b, c, folds: Folds, options: list, free: bool) -> OptionResult:
    """Choose, per fold, the option with the lowest train chi2 and score it on the fold's test units.

    Args:
        A, b: per-unit statistics of all columns: A (U, P, P) full Gram or (U, P) its diagonal (then every
            option must be a single column), b (U, P); c: (U,) residual energies.
        options: list of column-index lists; with ``free`` their coefficients are fitted by least squares,
            otherwise they are fixed at 1 (each option is then one fixed change, e.g. a delay value).
    Returns:
        The :class:`OptionResult` (cv over folds; full-data best option and its coefficients).
    """
    fou = np.asarray(folds.fold_of_unit)
    if A.ndim == 2:
        return _cross_validate_single(A, b, c, fou, folds.K, [o[0] for o in options], free)

    def sums(units_mask, cols):
        idx = np.asarray(cols)
        return A[units_mask][:, idx][:, :, idx].sum(0), b[units_mask][:, idx].sum(0), c[units_mask].sum()

    cv = 0.0
    for f in range(folds.K):
        train = fou != f
        test = ~train
        if not train.any():
            train = test
        best = None
        for cols in options:
            As, bs, cs = sums(train, cols)
            th = _solve(As, bs) if free else np.ones(len(cols))
            ch = chi2_of(th, As, bs, cs)
            if best is None or ch < best[0]:
                best = (ch, cols, th)
        cv += chi2_of(best[2], *sums(test, best[1]))
    allu = np.ones(len(fou), dtype=bool)
    best = None
    for oi, cols in enumerate(options):
        As, bs, cs = sums(allu, cols)
        th = _solve(As, bs) if free else np.ones(len(cols))
        ch = chi2_of(th, As, bs, cs)
        if best is None or ch < best[0]:
            best = (ch, oi, th)
    return OptionResult(cv_chi2=float(cv), full_chi2=float(best[0]), theta=best[2], option=best[1])


def _cross_validate_single(Ad, b, c, fou, K, cols, free) -> OptionResult:
    """Vectorised :func:`cross_validate` for single-column options (diagonal statistics)."""
    cols = np.asarray(cols)
    Ad = Ad[:, cols]
    b = b[:, cols]

    def fit(units):
        As, bs, cs = Ad[units].sum(0), b[units].sum(0), c[units].sum()
        th = np.where(As > 0, bs / np.where(As > 0, As, 1.0), 0.0) if free else np.ones_like(bs)
        return th, cs - 2 * th * bs + th * th * As

    cv = 0.0
    for f in range(K):
        train = fou != f
        test = ~train
        if not train.any():
            train = test
        th, ch = fit(train)
        j = int(np.argmin(ch))
        cv += float(c[test].sum() - 2 * th[j] * b[test, j].sum() + th[j] ** 2 * Ad[test, j].sum())
    th, ch = fit(np.ones(len(fou), dtype=bool))
    j = int(np.argmin(ch))
    return OptionResult(cv_chi2=float(cv), full_chi2=float(ch[j]), theta=np.array([th[j]]), option=j)
