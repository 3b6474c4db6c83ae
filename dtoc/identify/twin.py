"""The model being identified: the declared chain plus the effects found, and its non-linear refit.

Order of the chain (``dtoc.hardware.model.HardwareModel``): ``slew_limit`` effects first (the amplifier
cannot follow the demand; they act on the demanded input), then the declared effects (fixed: they are
what the user declared), then the found parametric effects in the order they were added, then found
``lti`` corrections last.  Every found parametric effect is then refitted jointly by Levenberg-Marquardt
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

_LOG_PARAMS = {"tau_s", "max_slew_T_per_m_per_s"}


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
    def chain(self, include=None) -> HardwareModel:
        """The full chain (optionally only the found effects in ``include``)."""
        fs = self.found if include is None else include
        pre = [f.effect for f in fs if f.position == "pre"]
        post = [f.effect for f in fs if f.position == "post"]
        lti = [f.effect for f in fs if f.position == "lti"]
        return HardwareModel([*pre, *self.declared.effects, *post, *lti])

    def add(self, kind: str, axis, input_axis, params: dict, score: float, position: str, notes=None) -> Found:
        eff = build_effect(kind, params, axis=axis, input_axis=input_axis)
        pos = "lti" if kind == "lti" else position
        f = Found(eff, score, pos, notes=notes or {})
        self.found.append(f)
        return f

    def updated_model(self) -> HardwareModel:
        m = self.chain()
        m.description = (self.declared.description or "declared model") + " + identified effects"
        return m

    # -- prediction -------------------------------------------------------------------------------
    @torch.no_grad()
    def predict(self, g: np.ndarray | None = None, include=None) -> Prediction:
        gt = self.g if g is None else torch.as_tensor(g, dtype=torch.float64)
        G, b0 = self.chain(include)(gt, self.data.dt_s)
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

    def residual_torch(self, model: HardwareModel, targets) -> torch.Tensor:
        G, b0 = model(self.g, self.data.dt_s)
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

    def _to_value(self, t, u):
        return torch.exp(u) if t == "log" else (u * self.data.dt_s if t == "dt" else u)

    def _set_u(self, free, u) -> None:
        for (i, n, t), ui in zip(free, u):
            p = getattr(self.found[i].effect, n)
            with torch.no_grad():
                p.copy_(self._to_value(t, torch.as_tensor(float(ui), dtype=torch.float64)).reshape(p.shape))

    def _resid_of_u(self, free, targets):
        model = self.chain()
        names = {}
        for j, f in enumerate(model.effects):
            names[id(f)] = j

        def fn(u: torch.Tensor) -> torch.Tensor:
            over = {}
            for k, (i, n, t) in enumerate(free):
                eff = self.found[i].effect
                key = f"effects.{names[id(eff)]}.{n}"
                over[key] = self._to_value(t, u[k]).reshape(getattr(eff, n).shape)
            return self.residual_torch(_Override(model, over), targets)

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
            with torch.no_grad():
                r = self.residual_torch(self.chain(), targets).numpy()
            return {"chi2": float(r @ r), "dof": int(np.count_nonzero(r)), "cov_u": np.zeros((0, 0)), "free": free}
        fn = self._resid_of_u(free, targets)
        u = self._get_u(free)
        r, J = self._jacobian(fn, u)
        chi2 = float(r @ r)
        lam = 1e-3
        for _ in range(max_iter):
            JTJ = J.T @ J
            g = J.T @ r
            D = np.diag(np.maximum(np.diag(JTJ), 1e-30))
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
                chi2_new = float(r_new @ r_new)
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
            chi2 = float(r @ r)
        dof = max(int(np.count_nonzero(np.concatenate([t[1].numpy().reshape(-1) for t in targets.values()]))) - len(u), 1)
        JTJ = J.T @ J
        try:
            cov = np.linalg.inv(JTJ) * max(1.0, chi2 / dof)
        except np.linalg.LinAlgError:
            cov = np.full((len(u), len(u)), np.nan)
        return {"chi2": chi2, "dof": dof, "cov_u": cov, "free": free}

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
        """Re-solve the taps of found lti effects by linear least squares (they sit last in the chain)."""
        ltis = [f for f in self.found if f.position == "lti"]
        if not ltis:
            return
        d = self.data
        others = [f for f in self.found if f.position != "lti"]
        base = self.predict(include=others)
        cols = []
        for f in ltis:
            eff: Lti = f.effect
            a = eff._ax
            L = eff.taps.shape[-1]
            j0 = int(round(eff.t0_s / eff.dt_s))
            x = base.G[:, a]
            for j in range(L):
                lag = j + j0
                c = np.zeros_like(base.G)
                if lag >= 0:
                    c[:, a, lag:] = x[:, : d.N - lag]
                else:
                    c[:, a, : d.N + lag] = x[:, -lag:]
                cols.append(c)
        w = np.ones((d.M, d.N)) if weight is None else weight
        from dtoc.identify.data import integrate_k

        rows_A = 0
        rows_b = 0
        for ch in d.channels():
            if ch == "b0":
                continue
            mask = d.mask(ch) * w[:, None, :]
            y = d.measured(ch)
            pred = base.G if ch == "G" else integrate_k(base.G, d.dt_s)
            z = ((y - pred) * mask / self.sigma[ch]).reshape(-1)
            S = np.stack([((c if ch == "G" else integrate_k(c, d.dt_s)) * mask / self.sigma[ch]).reshape(-1) for c in cols])
            rows_A = rows_A + S @ S.T
            rows_b = rows_b + S @ z
        A = np.asarray(rows_A)
        lam = 1e-12 * max(np.trace(A) / len(A), 1e-300)
        theta = np.linalg.solve(A + lam * np.eye(len(A)), np.asarray(rows_b))
        try:
            cov = np.linalg.inv(A + lam * np.eye(len(A)))
        except np.linalg.LinAlgError:
            cov = np.full_like(A, np.nan)
        k = 0
        for f in ltis:
            L = f.effect.taps.shape[-1]
            with torch.no_grad():
                f.effect.taps.copy_(torch.as_tensor(theta[k : k + L]).reshape(f.effect.taps.shape))
            f.stderr = {"taps": [float(math.sqrt(max(cov[k + j, k + j], 0.0))) for j in range(L)]}
            k += L


class _Override(torch.nn.Module):
    """A chain whose listed parameters are replaced by given tensors (functional call)."""

    def __init__(self, model: HardwareModel, over: dict):
        super().__init__()
        self.model = model
        self.over = over

    def forward(self, g, dt_s):
        return torch.func.functional_call(self.model, self.over, (g, dt_s), strict=False)

    def __call__(self, g, dt_s):
        return self.forward(g, dt_s)
