"""The RF split of the PDG main pass as one autograd function (gather, scale, scatter-add).

At an RF pulse every child state c of the next interval receives

    A_new[c, v] = sum_{edges e -> c} coef[kind_e, v] * op_e(A_end[parent_e, v]),   op_e = identity or conj,

with per-voxel edge coefficients ``coef`` (6, V) (flip scaled by B1, RF phase; see
:func:`dtoc.sim.pdg_main.rf_coefficients`).  Generic autograd would save the gathered (E, V)
coefficient rows and run five elementwise passes in backward; this function saves only the
(6, V) coefficients and the index arrays, and its backward is the adjoint map: one gather of the
incoming gradient at the children, one multiply by conj(coef), one scatter-add into the parents
(conjugated for the conjugating edges: d/dx of c conj(x) gives conj(c g) under PyTorch's convention
grad_x = conj(dL/dx) for real L).  Not differentiable w.r.t. the coefficients (use the generic
path when the RF parameters require a gradient).
"""

from __future__ import annotations

import torch


def _groups(kind, parent, child, conj_np, device):
    out = []
    cj = conj_np[kind]
    for is_conj in (False, True):
        sel = cj if is_conj else ~cj
        if sel.any():
            out.append((is_conj, torch.as_tensor(kind[sel], device=device), torch.as_tensor(parent[sel], device=device),
                        torch.as_tensor(child[sel], device=device)))
    return out


def _split(A, coefs, groups, n_out):
    out = torch.zeros((n_out, A.shape[1]), dtype=A.dtype, device=A.device)
    for is_conj, kind, par, child in groups:
        src = A.index_select(0, par)
        if is_conj:
            src = src.conj()
        src = src * coefs.index_select(0, kind)
        out.index_add_(0, child, src)
    return out


def _split_adjoint(G, coefs, groups, n_in):
    out = torch.zeros((n_in, G.shape[1]), dtype=G.dtype, device=G.device)
    cc = coefs.conj()
    for is_conj, kind, par, child in groups:
        g = G.index_select(0, child) * cc.index_select(0, kind)
        if is_conj:
            g = g.conj()
        out.index_add_(0, par, g)
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
        return _split(A, coefs, groups, n_out)  # generic autograd (RF parameters differentiated)
    return _RFSplit.apply(A, coefs, groups, n_out)
