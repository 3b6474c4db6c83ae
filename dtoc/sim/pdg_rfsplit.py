"""The RF split of the PDG main pass as one autograd function (gather, scale, scatter-add).

At an RF pulse every child state c of the next interval receives

    A_new[c, v] = sum_{edges e -> c} coef[kind_e, v] * op_e(A_end[parent_e, v]),   op_e = identity or conj,

with per-voxel edge coefficients ``coef`` (6, V) (flip scaled by B1, RF phase; see
:func:`dtoc.sim.pdg_main.rf_coefficients`).  Generic autograd would save the gathered (E, V)
coefficient rows and run five elementwise passes in backward; this function saves only the
(6, V) coefficients and the index arrays (edges sorted by kind, so each kind's coefficient row
scales a contiguous block in place: no (E, V) coefficient gather), and its backward is the adjoint
map: one gather of the incoming gradient at the children, scaling by conj(coef), one scatter-add
into the parents
(conjugated for the conjugating edges: d/dx of c conj(x) gives conj(c g) under PyTorch's convention
grad_x = conj(dL/dx) for real L).  Not differentiable w.r.t. the coefficients (use the generic
path when the RF parameters require a gradient).
"""

from __future__ import annotations

import numpy as np
import torch


def _groups(kind, parent, child, conj_np, device):
    """Edges split into plain / conjugating groups, each sorted by kind: (is_conj, kind, parent, child, kind ranges)."""
    out = []
    cj = conj_np[kind]
    for is_conj in (False, True):
        sel = np.where(cj == is_conj)[0]
        if sel.size:
            sel = sel[np.argsort(kind[sel], kind="stable")]
            k = kind[sel]
            cuts = np.flatnonzero(np.diff(k)) + 1
            starts = np.concatenate([[0], cuts])
            ends = np.concatenate([cuts, [k.size]])
            ranges = [(int(k[a]), int(a), int(b)) for a, b in zip(starts, ends)]
            out.append(
                (
                    is_conj,
                    torch.as_tensor(k, device=device),
                    torch.as_tensor(parent[sel], device=device),
                    torch.as_tensor(child[sel], device=device),
                    ranges,
                )
            )
    return out


def add_rows_(out: torch.Tensor, index: torch.Tensor, src: torch.Tensor) -> torch.Tensor:
    """``out.index_add_(0, index, src)``; complex tensors through their real views (the same additions,
    bit-identical: on CPU torch's complex index_add_ takes a generic scatter path ~6x slower than the
    real one).  Not for autograd-tracked tensors (used inside the hand-written adjoints)."""
    if out.is_complex() and out.is_contiguous() and not out.is_conj() and not src.is_conj() and out.dim() >= 1:
        torch.view_as_real(out).reshape(out.shape[0], -1).index_add_(
            0, index, torch.view_as_real(src).reshape(src.shape[0], -1)
        )
        return out
    return out.index_add_(0, index, src)


def take_rows(X: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """``X.index_select(0, index)`` (a fresh tensor); complex through the real view (same values,
    ~1.7x faster on CPU).  Not for autograd-tracked tensors (used inside the hand-written adjoints)."""
    if X.is_complex() and X.is_contiguous() and not X.is_conj() and X.dim() >= 1:
        r = torch.view_as_real(X).reshape(X.shape[0], -1).index_select(0, index)
        return torch.view_as_complex(r.reshape((index.shape[0],) + tuple(X.shape[1:]) + (2,)))
    return X.index_select(0, index)


def _split_generic(A, coefs, groups, n_out):
    """Plain autograd version (used when the coefficients require a gradient)."""
    out = torch.zeros((n_out, A.shape[1]), dtype=A.dtype, device=A.device)
    for is_conj, kind, par, child, _ in groups:
        src = A.index_select(0, par)
        if is_conj:
            src = src.conj()
        out = out.index_add(0, child, src * coefs.index_select(0, kind))
    return out


def _scaled_gather(X, rows, coefs, ranges, is_conj):
    """op(X[rows] * coefs[kind]) with one coefficient row per kind range; op = conj for conjugating groups."""
    src = take_rows(X, rows)  # fresh tensor: scaled in place, one coefficient row per kind range
    for q, a, b in ranges:
        src[a:b].mul_(coefs[q])
    if is_conj:
        src.conj_physical_()
    return src


def _split(A, coefs, groups, n_out):
    out = torch.zeros((n_out, A.shape[1]), dtype=A.dtype, device=A.device)
    cc = coefs.conj()
    for is_conj, _kind, par, child, ranges in groups:
        # c conj(x) = conj(conj(c) x)
        add_rows_(out, child, _scaled_gather(A, par, cc if is_conj else coefs, ranges, is_conj))
    return out


def _split_adjoint(G, coefs, groups, n_in):
    out = torch.zeros((n_in, G.shape[1]), dtype=G.dtype, device=G.device)
    cc = coefs.conj()
    for is_conj, _kind, par, child, ranges in groups:
        # y = c x: grad_x = conj(c) g;  y = c conj(x): grad_x = conj(conj(c) g)
        add_rows_(out, par, _scaled_gather(G, child, cc, ranges, is_conj))
    return out


class _RFSplit(torch.autograd.Function):
    @staticmethod
    def forward(ctx, A, coefs, groups, n_out):
        ctx.groups = groups
        ctx.n_in = A.shape[0]
        ctx.save_for_backward(coefs)
        return _split(A, coefs, groups, n_out)

    @staticmethod
    def backward(ctx, G):
        (coefs,) = ctx.saved_tensors
        return _split_adjoint(G, coefs, ctx.groups, ctx.n_in), None, None, None


def rf_split(A, coefs, kind, parent, child, conj_np, n_out):
    """(n_out, V) amplitudes after the RF split of A (S, V) along the edges (kind, parent, child) (numpy int arrays)."""
    groups = _groups(kind, parent, child, conj_np, A.device)
    if coefs.requires_grad:
        return _split_generic(A, coefs, groups, n_out)  # generic autograd (RF parameters differentiated)
    return _RFSplit.apply(A, coefs, groups, n_out)


def rf_coefficients(
    flip_rad: float, phase_rad: float, b1: torch.Tensor, cdtype, cache: dict | None = None
) -> torch.Tensor:
    """(6, V) complex edge coefficients of one RF pulse per voxel (kinds of the pdg_graph table).

    ``cache``: optional dict; the phase-free rows (trigonometry of the B1-scaled flip, (6, V)) are
    kept there per flip angle and each pulse only multiplies them by its 6 phase factors (RF spoiling
    gives every pulse its own phase, not its own flip).
    """
    if cache is not None:
        key = ("rf_base", float(flip_rad))
        base = cache.get(key)
        if base is None:
            base = cache[key] = rf_coefficients(flip_rad, 0.0, b1, cdtype)
        e1 = complex(np.cos(phase_rad), np.sin(phase_rad))
        e2 = complex(np.cos(2 * phase_rad), np.sin(2 * phase_rad))
        ph = torch.tensor([1.0, e2, e1.conjugate(), e1, e1, 1.0], dtype=cdtype, device=base.device)
        return base * ph[:, None]
    a = flip_rad * b1
    s = torch.sin(a)
    c = torch.cos(a)
    s2 = torch.sin(0.5 * a) ** 2
    c2 = torch.cos(0.5 * a) ** 2
    e1 = complex(np.cos(phase_rad), np.sin(phase_rad))
    e2 = complex(np.cos(2 * phase_rad), np.sin(2 * phase_rad))
    em1 = e1.conjugate()
    rows = [
        c2.to(cdtype),
        e2 * s2.to(cdtype),
        (-1j * em1) * s.to(cdtype),
        (-0.5j * e1) * s.to(cdtype),
        (-0.5j * e1) * s.to(cdtype),
        c.to(cdtype),
    ]
    return torch.stack(rows)
