"""The model being identified: the declared chain plus the effects found, and its non-linear refit.

Order of the chain (``dtoc.hardware.model.HardwareModel``): ``slew_limit`` effects first (the amplifier
cannot follow the demand; they act on the demanded input), then the declared effects (fixed: they are
what the user declared), then the found parametric effects in the order they were added, then found
``lti`` corrections, then measurement-side effects (``time_base``: the measuring device's clock), which
predict the measurement but are not part of the updated hardware model.  Every found parametric effect is then refitted jointly by Levenberg-Marquardt
on the whitened residual of all measured channels, with the Jacobian taken through the differentiable
twin by forward-mode automatic differentiation (``torch.func.jvp``; central differences if an operation
lacks a forward-mode rule).  Positive parameters (time constants, slew limits) are fitted as logarithms,
delays in units of dt.  ``lti`` taps enter linearly at the end of the chain and are re-solved by linear
least squares after each refit (exact given the other parameters).

Standard errors: cov = (J^T J)^-1 * max(1, chi2 / dof) in whitened units (sigma from the noise floor),
mapped back through the parameter transforms.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from dtoc.constants import GAMMA_RAD_PER_S_PER_MT
from dtoc.hardware.effects import Lti
from dtoc.hardware.model import HardwareModel, build_effect
from dtoc.identify.data import IdentData
from dtoc.identify.workspace import Prediction

_LOG_PARAMS = {"tau_s", "max_slew_T_per_m_per_s", "f0_hz", "q"}


# Large products are taken with einsum rather than BLAS: identify runs on a few cores shared with other
# jobs, where multi-threaded BLAS on tall-skinny products is many times slower than one thread.
def _dot(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.einsum("n,n->", a, b))


def _gram(J: np.ndarray) -> np.ndarray:
    """J^T J of a tall (n, p) Jacobian."""
    return np.einsum("np,nq->pq", J, J)


def _proj(J: np.ndarray, r: np.ndarray) -> np.ndarray:
    """J^T r."""
    return np.einsum("np,n->p", J, r)


@dataclass
class Found:
    """One effect added by the search, with what the report needs about it."""

    effect: object  # dtoc.hardware.effects.Effect
    score: float
    position: str  # "pre" | "post" | "lti"
    stderr: dict = field(default_factory=dict)
    notes: dict = field(default_factory=dict)


class Twin:
    """Declared model + found effects; predictions on the measurement's waveforms."""

    def __init__(self, declared: HardwareModel | None, data: IdentData, sigma: dict):
        self.declared = declared if declared is not None else HardwareModel([])
        for p in self.declared.parameters():
            p.requires_grad_(False)
        self.data = data
        self.sigma = dict(sigma)
        self.found: list[Found] = []
        self.g = torch.as_tensor(data.g, dtype=torch.float64)

    # -- assembly ---------------------------------------------------------------------------------
    def chain(self, include=None, hardware_only: bool = False) -> HardwareModel:
        """The full chain (optionally only the found effects in ``include``); ``hardware_only`` leaves out the
        measurement-side effects (position "meas", e.g. ``time_base``), which are not part of the scanner."""
        fs = self.found if include is None else include
        pre = [f.effect for f in fs if f.position == "pre"]
        post = [f.effect for f in fs if f.position == "post"]
        lti = [f.effect for f in fs if f.position == "lti"]
        meas = [] if hardware_only else [f.effect for f in fs if f.position == "meas"]
        return HardwareModel([*pre, *self.declared.effects, *post, *lti, *meas])

    def add(self, kind: str, axis, input_axis, params: dict, score: float, position: str, notes=None) -> Found:
        eff = build_effect(kind, params, axis=axis, input_axis=input_axis)
        pos = "lti" if kind == "lti" else position
        f = Found(eff, score, pos, notes=notes or {})
        self.found.append(f)
        return f

    def updated_model(self) -> HardwareModel:
        """Declared + found hardware effects (measurement-side effects such as ``time_base`` left out)."""
        m = self.chain(hardware_only=True)
        base = self.declared.description or ("declared model" if self.declared.effects else "ideal hardware")
        m.description = base + (" + identified effects" if self.found else "")
        return m

    # -- prediction -------------------------------------------------------------------------------
    def _declared_out(self):
        """Declared chain applied to the measurement's g, computed once (it has no free parameters)."""
        if not hasattr(self, "_decl_cache"):
            with torch.no_grad():
                self._decl_cache = self.declared(self.g, self.data.dt_s)
        return self._decl_cache

    def forward_own(self, model_effects=None):
        """(callable() -> (G, b0)) evaluating the current chain on the measurement's g, reusing the cached
        declared output when no found effect precedes the declared chain."""
        fs = self.found if model_effects is None else model_effects
        if any(f.position == "pre" for f in fs):
            model = self.chain(fs)
            return model, lambda m: m(self.g, self.data.dt_s)
        post = [f.effect for pos in ("post", "lti", "meas") for f in fs if f.position == pos]
        model = HardwareModel(post)
        Gd, b0d = self._declared_out()
        return model, lambda m: m(Gd, self.data.dt_s, b0=b0d, demand=self.g)

    @torch.no_grad()
    def predict(self, g: np.ndarray | None = None, include=None) -> Prediction:
        if g is None:
            model, run = self.forward_own(include)
            G, b0 = run(model)
        else:
            G, b0 = self.chain(include)(torch.as_tensor(g, dtype=torch.float64), self.data.dt_s)
        return Prediction(G.numpy().copy(), b0.numpy().copy())

    def predict_fn(self, include=None):
        """callable(g ndarray) -> Prediction, for candidate screening."""
        return lambda g: self.predict(g, include)

    # -- residual vector in torch ---------------------------------------------------------------------
    def _targets(self, weight: np.ndarray | None):
        d = self.data
        w = np.ones((d.M, d.N)) if weight is None else weight
        out = {}
        for c in d.channels():
            mask = d.mask(c) * (w[:, None, :] if c != "b0" else w)
            out[c] = (torch.as_tensor(d.measured(c) * mask), torch.as_tensor(mask), self.sigma[c])
        return out

    def residual_torch(self, model, targets, run=None) -> torch.Tensor:
        G, b0 = model(self.g, self.data.dt_s) if run is None else run(model)
        parts = []
        for c, (y, mask, s) in targets.items():
            if c == "G":
                p = G
            elif c == "k":
                inc = 0.5 * self.data.dt_s * (G[..., 1:] + G[..., :-1])
                p = GAMMA_RAD_PER_S_PER_MT * torch.cat([torch.zeros_like(G[..., :1]), torch.cumsum(inc, -1)], -1)
            else:
                p = b0
            parts.append(((y - p * mask) / s).reshape(-1))
        return torch.cat(parts)

    # -- parameters -------------------------------------------------------------------------------
    def _free(self):
        """[(found index, param name, transform)] of the scalar parameters refitted by LM."""
        out = []
        for i, f in enumerate(self.found):
            if f.position == "lti":
                continue
            for n in f.effect.param_names:
                t = "log" if n in _LOG_PARAMS else ("dt" if n == "seconds" else "lin")
                if getattr(f.effect, n).numel() != 1:
                    continue
                out.append((i, n, t))
        return out

    def _get_u(self, free) -> np.ndarray:
        u = []
        for i, n, t in free:
            v = float(getattr(self.found[i].effect, n).detach().reshape(()))
            u.append(math.log(v) if t == "log" else (v / self.data.dt_s if t == "dt" else v))
        return np.asarray(u, dtype=np.float64)

    def _bounds(self, t, name=""):
        """Box for a transformed parameter: log time constants / slew limits within [dt/4, 100 x record]
        (resp. a generous slew range), delays within +- half the record (in dt)."""
        T = self.data.N * self.data.dt_s
        if t == "log" and name == "tau_s":
            return math.log(self.data.dt_s / 4), math.log(100.0 * T)
        if t == "log" and name == "f0_hz":
            return math.log(1.0 / T), math.log(0.5 / self.data.dt_s)
        if t == "log" and name == "q":
            return math.log(0.51), math.log(1e4)
        if t == "log":
            return math.log(1e-3), math.log(1e6)
        if t == "dt":
            return -0.5 * self.data.N, 0.5 * self.data.N
        return -math.inf, math.inf

    def _to_value(self, t, u, name=""):
        lo, hi = self._bounds(t, name)
        if math.isfinite(lo):
            u = torch.clamp(u, lo, hi)
        return torch.exp(u) if t == "log" else (u * self.data.dt_s if t == "dt" else u)

    def _set_u(self, free, u) -> None:
        for (i, n, t), ui in zip(free, u):
            p = getattr(self.found[i].effect, n)
            with torch.no_grad():
                p.copy_(self._to_value(t, torch.as_tensor(float(ui), dtype=torch.float64), n).reshape(p.shape))

    def _resid_of_u(self, free, targets):
        model, run = self.forward_own()
        names = {}
        for j, f in enumerate(model.effects):
            names[id(f)] = j

        def fn(u: torch.Tensor) -> torch.Tensor:
            over = {}
            for k, (i, n, t) in enumerate(free):
                eff = self.found[i].effect
                key = f"effects.{names[id(eff)]}.{n}"
                over[key] = self._to_value(t, u[k], n).reshape(getattr(eff, n).shape)
            return self.residual_torch(_Override(model, over), targets, run)

        return fn

    def _jacobian(self, fn, u: np.ndarray):
        ut = torch.as_tensor(u, dtype=torch.float64)
        p = len(u)
        cols = []
        r0 = None
        try:
            for j in range(p):
                e = torch.zeros(p, dtype=torch.float64)
                e[j] = 1.0
                r, jc = torch.func.jvp(fn, (ut,), (e,))
                r0 = r if r0 is None else r0
                cols.append(jc.detach())
            if r0 is None:
                r0 = fn(ut)
        except (RuntimeError, NotImplementedError):
            with torch.no_grad():
                r0 = fn(ut)
                cols = []
                for j in range(p):
                    h = 1e-4 * max(1.0, abs(u[j]))
                    e = torch.zeros(p, dtype=torch.float64)
                    e[j] = h
                    cols.append((fn(ut + e) - fn(ut - e)) / (2 * h))
        J = torch.stack(cols, dim=1) if cols else torch.zeros((r0.numel(), 0), dtype=torch.float64)
        return r0.detach().numpy(), J.numpy()

    def refit(self, weight: np.ndarray | None = None, max_iter: int = 20, tol: float = 1e-6) -> dict:
        """Levenberg-Marquardt refit of all found scalar parameters (and linear re-solve of lti taps).

        Args:
            weight: (M, N) 0/1 sample weights (None: all measured samples), e.g. a fold's train mask.
        Returns:
            {"chi2": float, "dof": int, "cov_u": ndarray, "free": list} at the optimum.
        """
        targets = self._targets(weight)
        free = self._free()
        self._refit_lti(weight)
        if not free:
            model, run = self.forward_own()
            with torch.no_grad():
                r = self.residual_torch(model, targets, run).numpy()
            return {"chi2": _dot(r, r), "dof": int(np.count_nonzero(r)), "cov_u": np.zeros((0, 0)), "free": free}
        fn = self._resid_of_u(free, targets)
        u = self._get_u(free)
        r, J = self._jacobian(fn, u)
        chi2 = _dot(r, r)
        lam = 1e-3
        for _ in range(max_iter):
            JTJ = _gram(J)
            g = _proj(J, r)
            D = np.diag(np.maximum(np.diag(JTJ), 1e-30))
            try:  # Gauss-Newton predicted decrease g^T (J^T J)^-1 g: stop when it is negligible
                pred = float(g @ np.linalg.solve(JTJ + 1e-12 * D, g))
            except np.linalg.LinAlgError:
                pred = np.inf
            if pred < max(tol * chi2, 1e-6):
                break
            improved = False
            for _try in range(8):
                try:
                    step = -np.linalg.solve(JTJ + lam * D, g)
                except np.linalg.LinAlgError:
                    lam *= 10
                    continue
                u_new = u + step
                with torch.no_grad():
                    r_new = fn(torch.as_tensor(u_new)).numpy()
                chi2_new = _dot(r_new, r_new)
                if np.isfinite(chi2_new) and chi2_new < chi2:
                    improved = True
                    break
                lam *= 10
            if not improved:
                break
            rel = (chi2 - chi2_new) / max(chi2, 1e-300)
            u = u_new
            chi2 = chi2_new
            lam = max(lam / 10, 1e-9)
            self._set_u(free, u)
            r, J = self._jacobian(fn, u)
            if rel < tol:
                break
        self._set_u(free, u)
        if any(f.position == "lti" for f in self.found):
            self._refit_lti(weight)
            fn = self._resid_of_u(free, targets)
            r, J = self._jacobian(fn, u)
            chi2 = _dot(r, r)
        dof = max(
            int(np.count_nonzero(np.concatenate([t[1].numpy().reshape(-1) for t in targets.values()]))) - len(u), 1
        )
        JTJ = _gram(J)
        try:
            cov = np.linalg.pinv(JTJ, rcond=1e-12, hermitian=True) * max(1.0, chi2 / dof)
        except np.linalg.LinAlgError:
            cov = np.full((len(u), len(u)), np.nan)
        cov[np.diag(JTJ) <= 0, :] = np.nan  # a parameter the data do not constrain (e.g. clamped at a bound)
        at_bound = []
        for (i, n, t), ui in zip(free, u):
            lo, hi = self._bounds(t, n)
            if math.isfinite(lo) and not (lo < ui < hi):
                at_bound.append((i, n))
        return {"chi2": chi2, "dof": dof, "cov_u": cov, "free": free, "u": u, "J": J, "r": r, "at_bound": at_bound}

    def heldout_refit(self, fit: dict, weight: np.ndarray) -> None:
        """Refit on the training samples ``weight`` (M, N) by one Gauss-Newton step from the full-data
        optimum ``fit`` (its Jacobian, rows restricted to the training samples; exact for parameters that
        enter linearly, second-order accurate otherwise), then re-solve lti taps on the same samples.
        Leaves the parameters at the training-set estimate (the caller restores them)."""
        free = fit["free"]
        if free:
            rows = np.concatenate([t[1].numpy().reshape(-1) for t in self._targets(weight).values()]) > 0
            J = fit["J"][rows]
            r = fit["r"][rows]
            JTJ = _gram(J)
            D = np.diag(np.maximum(np.diag(JTJ), 1e-30))
            try:
                step = -np.linalg.solve(JTJ + 1e-12 * D, _proj(J, r))
            except np.linalg.LinAlgError:
                step = np.zeros(len(free))
            self._set_u(free, fit["u"] + step)
        self._refit_lti(weight)

    def fold_estimates(self, fit: dict, masks: list) -> tuple[np.ndarray, np.ndarray]:
        """Each scalar parameter estimated on the samples of each mask in ``masks`` alone ((M, N) 0/1, e.g. the
        held-out folds' test samples: disjoint data), by one Gauss-Newton step from the full-data optimum
        ``fit`` (rows of its Jacobian restricted to the mask), with standard errors (J^T J)^-1 x max(1,
        chi2/dof) on those rows.  Parameters stay as they are.

        Returns:
            (est, se), each (len(masks), p) in the refit's transformed units (logs, dt units); NaN where a
            mask does not constrain the parameters.
        """
        free = fit.get("free") or []
        p = len(free)
        est = np.full((len(masks), p), np.nan)
        se = np.full((len(masks), p), np.nan)
        if not p or "J" not in fit:
            return est, se
        for k, w in enumerate(masks):
            rows = np.concatenate([t[1].numpy().reshape(-1) for t in self._targets(w).values()]) > 0
            J = fit["J"][rows]
            r = fit["r"][rows]
            JTJ = _gram(J)
            if rows.sum() <= p or np.any(np.diag(JTJ) <= 0):
                continue
            try:
                inv = np.linalg.inv(JTJ)
            except np.linalg.LinAlgError:
                continue
            step = -inv @ _proj(J, r)
            r1 = r + J @ step
            scale = max(1.0, _dot(r1, r1) / (int(rows.sum()) - p))
            d = np.diag(inv)
            if np.any(d <= 0) or not np.all(np.isfinite(step)):
                continue
            est[k] = fit["u"] + step
            se[k] = np.sqrt(d * scale)
        return est, se

    def set_stderr(self, fit: dict) -> None:
        """Store standard errors (in the parameters' own units) from a full-data :meth:`refit`."""
        for f in self.found:
            f.stderr = {}
        cov = fit["cov_u"]
        for k, (i, n, t) in enumerate(fit["free"]):
            su = math.sqrt(cov[k, k]) if np.isfinite(cov[k, k]) and cov[k, k] >= 0 else float("nan")
            v = float(getattr(self.found[i].effect, n).detach().reshape(()))
            se = v * su if t == "log" else (su * self.data.dt_s if t == "dt" else su)
            self.found[i].stderr[n] = float(se)

    # -- lti taps ---------------------------------------------------------------------------------
    def _refit_lti(self, weight: np.ndarray | None) -> None:
        """Re-solve the taps of found lti effects by linear least squares (they sit last in the chain).

        Each lti acts on its own axis and G/k of different axes are independent, so the normal equations are
        block-diagonal: one (L, L) system per lti effect, built from that axis only.
        """
        from dtoc.identify.data import integrate_k

        ltis = [f for f in self.found if f.position == "lti"]
        if not ltis:
            return
        d = self.data
        others = [f for f in self.found if f.position != "lti"]
        base = self.predict(include=others)
        w = np.ones((d.M, d.N)) if weight is None else weight
        for f in ltis:
            eff: Lti = f.effect
            a = eff._ax
            L = eff.taps.shape[-1]
            j0 = int(round(eff.t0_s / eff.dt_s))
            x = base.G[:, a]  # (M, N)
            cols = np.zeros((L, d.M, d.N))
            for j in range(L):
                lag = j + j0
                if 0 <= lag < d.N:
                    cols[j, :, lag:] = x[:, : d.N - lag]
                elif -d.N < lag < 0:
                    cols[j, :, : d.N + lag] = x[:, -lag:]
            A = np.zeros((L, L))
            b = np.zeros(L)
            for ch in d.channels():
                if ch == "b0":
                    continue
                mask = d.mask(ch)[:, a] * w
                y = d.measured(ch)[:, a]
                pred = x if ch == "G" else integrate_k(x, d.dt_s)
                z = ((y - pred) * mask / self.sigma[ch]).reshape(-1)
                S = ((cols if ch == "G" else integrate_k(cols, d.dt_s)) * mask[None] / self.sigma[ch]).reshape(L, -1)
                A += np.einsum("pn,qn->pq", S, S)
                b += np.einsum("pn,n->p", S, z)
            lam = 1e-12 * max(np.trace(A) / L, 1e-300)
            theta = np.linalg.solve(A + lam * np.eye(L), b)
            try:
                cov = np.linalg.inv(A + lam * np.eye(L))
            except np.linalg.LinAlgError:
                cov = np.full_like(A, np.nan)
            with torch.no_grad():
                eff.taps.copy_(torch.as_tensor(theta).reshape(eff.taps.shape))
            f.stderr = {"taps": [float(math.sqrt(max(cov[j, j], 0.0))) for j in range(L)]}


class _Override(torch.nn.Module):
    """A chain whose listed parameters are replaced by given tensors (functional call)."""

    def __init__(self, model: HardwareModel, over: dict):
        super().__init__()
        self.model = model
        self.over = over

    def forward(self, g, dt_s, b0=None, demand=None):
        return torch.func.functional_call(self.model, self.over, (g, dt_s), {"b0": b0, "demand": demand}, strict=False)

    def __call__(self, g, dt_s, b0=None, demand=None):
        return self.forward(g, dt_s, b0, demand)
