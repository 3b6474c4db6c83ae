"""One RF split of the PDG pre-pass (:func:`dtoc.sim.pdg_graph.build_graph`): the children of every state, their
merge by (type, rounded nominal k, rounded tau), their probe amplitudes, the representative edges and the cap.

The recursion over intervals is sequential (which children exist depends on the merged amplitudes of the
previous interval), so the cost of the pre-pass is this step times the number of RF pulses.  The step is a fixed
number of numpy calls whatever the number of states, and every array it returns is bit for bit what the
per-column formulation gave (tests/test_prepass_golden.py, tests/test_prepass_equivalence.py):

* the merge keys are computed per *parent* (S rows) instead of per candidate edge (3 S rows): a child's key is
  its parent's rounded end-of-interval (k, tau), negated for a conjugating edge (``round(-x / q) = -round(x / q)``
  exactly), with the child's type in front;
* the keys are packed into one int64 per row in lexicographic order (a column too wide for the product to fit is
  replaced by its dense rank over the parents' values and their negatives, one sort of S values), so one argsort
  of the kept edges gives the merged states in the same order and with the same inverse as
  :func:`dtoc.sim.pdg_graph.unique_rows` of the explicit key rows (which remains the fallback when even the ranks
  do not fit);
* the children's amplitude sums add every edge's complex value in edge order from zero
  (:func:`dtoc.sim.pdg_graph.add_rows_by_index`: one ``np.bincount`` over the interleaved real and imaginary parts,
  the same additions in the same order as ``np.add.at``).

Where a C compiler was there at install, an optional compiled core (``dtoc/sim/_pdg_split.c``, see
:func:`native_available`) does the merge, the survivors and the cap of each split, the prune pass's per-interval
index work (:func:`prune_native`) and the emission bound's per-sample work (:func:`emission_native`); it does only
exactly rounded operations, so the graph is this module's numpy one bit for bit (tests/test_prepass_native.py).
"""

from __future__ import annotations

import contextlib
import os
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np

from dtoc.sim.pdg_rows import CONJ, add_rows_by_index, first_max_by_group, top_k_mask, unique_rows

#: largest packed key range (the keys stay below 2**62)
_KEY_LIMIT = 2**62

try:  # the optional compiled core (setup.py builds it when a C compiler is there); else the numpy steps below
    from dtoc.sim import _pdg_split as _native  # type: ignore[attr-defined]
except ImportError:  # pragma: no cover - depends on the install
    _native = None
_state = {"native": _native is not None and os.environ.get("DTOC_PREPASS_NATIVE", "1") != "0"}


def native_available() -> bool:
    """True when the compiled core of the pre-pass (``dtoc/sim/_pdg_split.c``) was built at install."""
    return _native is not None


def native_in_use() -> bool:
    """True when the pre-pass runs its compiled core (built, and not switched off by ``DTOC_PREPASS_NATIVE=0`` or
    :func:`prepass_backend`)."""
    return bool(_state["native"])


@contextlib.contextmanager
def prepass_backend(name: str) -> Iterator[None]:
    """Within the block (process-wide, not per thread), the pre-pass runs with ``name``: 'numpy' (always there) or
    'native' (the compiled core; ValueError when it was not built).  The graphs are the same bit for bit either way."""
    if name not in ("numpy", "native"):
        raise ValueError(f"prepass backend {name!r}: expected 'numpy' or 'native'")
    if name == "native" and _native is None:
        raise ValueError("prepass backend 'native': the compiled merge was not built at install")
    old = _state["native"]
    _state["native"] = name == "native"
    try:
        yield
    finally:
        _state["native"] = old


@dataclass
class SplitResult:
    """The states of the next interval and the edges into them (see :class:`dtoc.sim.pdg_graph.IntervalGraph`)."""

    is_z: np.ndarray
    k: np.ndarray
    tau: np.ndarray
    mag: np.ndarray
    amp: np.ndarray
    eq: int
    e_child: np.ndarray
    e_par: np.ndarray
    e_kind: np.ndarray
    e_cand: np.ndarray


def _signed_rank(v: np.ndarray) -> tuple[np.ndarray, int]:
    """Order-preserving dense rank of ``v`` (S,) int64 over the set {v} | {-v} | {0}: (rank of each v, rank of 0).
    The rank of -v is ``2 * centre - rank(v)``; the set has ``2 * centre + 1`` values."""
    a = np.abs(v)
    ua, ia = np.unique(a, return_inverse=True)
    z0 = 1 if ua.size and ua[0] == 0 else 0
    centre = ua.size - z0
    return centre + np.sign(v) * (ia.reshape(-1) + 1 - z0), centre


def packed_parent_keys(cols: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray, int, int] | None:
    """Pack the parents' key columns (each (S,) int64: rounded kx, ky, kz, tau) into one int64 per parent for the
    child with the same sign and one for the conjugated child, in lexicographic order of the columns over the set
    of both signs and zero.  Returns (same, conjugated, key of all-zero columns, number of packed values) or None
    when the columns do not fit below 2**62 even as ranks.  A column is used as it is (offset by its largest
    absolute value) when the product fits, else replaced by its rank, widest first."""
    pos: list[np.ndarray] = []
    neg: list[np.ndarray] = []
    zero: list[int] = []
    span: list[int] = []
    for c in cols:
        m = int(np.abs(c).max()) if c.size else 0
        pos.append(c + m)
        neg.append(m - c)
        zero.append(m)
        span.append(2 * m + 1)
    ranked = [False] * len(cols)
    while np.prod(span, dtype=object) * 2 >= _KEY_LIMIT:
        j = max((i for i in range(len(cols)) if not ranked[i]), key=lambda i: span[i], default=None)
        if j is None:
            return None
        r, centre = _signed_rank(cols[j])
        pos[j], neg[j], zero[j], span[j], ranked[j] = r, 2 * centre - r, centre, 2 * centre + 1, True
    same = pos[0]
    conj = neg[0]
    z = zero[0]
    for j in range(1, len(cols)):
        same = same * span[j] + pos[j]
        conj = conj * span[j] + neg[j]
        z = z * span[j] + zero[j]
    return same, conj, z, int(np.prod(span, dtype=object))


def split_step(
    is_z: np.ndarray,
    k_end: np.ndarray,
    tau_end: np.ndarray,
    amp_end: np.ndarray,
    pc: np.ndarray,
    qk: float,
    qt: float,
    tau_ignored: bool,
    min_magnitude: float,
    max_states: int,
    estimate: Callable[[np.ndarray], np.ndarray],
    fallback_keys,
) -> SplitResult:
    """Split every state (``is_z`` (S,), end-of-interval ``k_end`` (S, 3), ``tau_end`` (S,), probe amplitudes
    ``amp_end`` (S, P)) by one RF pulse of probe edge coefficients ``pc`` (6, P), merge, prune by amplitude and
    cap (see :func:`dtoc.sim.pdg_graph.build_graph`).  ``estimate``: (R, P) probe amplitudes -> (R,) amplitude
    estimate (:meth:`dtoc.sim.pdg_graph._Bounds.amp_estimate`).  ``fallback_keys(is_z, k, tau)``: the explicit key rows,
    used when the packed keys do not fit."""

    S, P = amp_end.shape
    # the three children of every parent, slot-major within the parent (kinds 0-2 or 3-5): slot 1 conjugates
    coef = pc.reshape(2, 3, P)[is_z.astype(np.intp)]  # (S, 3, P)
    ccand = np.multiply(coef, amp_end[:, None, :])
    np.multiply(coef[:, 1], np.conjugate(amp_end), out=ccand[:, 1])
    ccand = ccand.reshape(3 * S, P)
    cand = estimate(ccand)
    if _state["native"] and max_states >= 1:
        return _split_native(
            is_z, k_end, tau_end, cand, ccand, qk, qt, tau_ignored, min_magnitude, max_states, estimate
        )
    kept = np.flatnonzero(cand >= min_magnitude)  # candidate edges in (parent, slot) order
    par = kept // 3
    slot = kept - 3 * par
    kind = slot + 3 * is_z[par]
    cand = cand[kept]
    ccand = ccand[kept]
    E = kept.size

    # merge keys: per parent, the rounded (k, tau) of the same-sign and the conjugated child; the type in front
    kq = np.round(k_end / qk).astype(np.int64)
    tq = np.zeros(S, dtype=np.int64) if tau_ignored else np.round(tau_end / qt).astype(np.int64)
    packed = packed_parent_keys([kq[:, 0], kq[:, 1], kq[:, 2], tq])
    if packed is not None:
        same, conj, zkey, span = packed
        per_parent = np.stack([same, conj, same + span], axis=1).reshape(-1)  # slot 2: the longitudinal child
        key = np.empty(E + 1, dtype=np.int64)
        np.take(per_parent, kept, out=key[:E])
        key[E] = zkey + span  # the equilibrium state (longitudinal, k = 0, tau = 0) always exists
        order = np.argsort(key)
        sk = key[order]
        new = np.empty(E + 1, dtype=bool)
        new[0] = True
        np.not_equal(sk[1:], sk[:-1], out=new[1:])
        inv = np.empty(E + 1, dtype=np.int64)
        inv[order] = np.cumsum(new) - 1
        child_z = sk[new] >= span
    else:  # keys too wide to pack even as ranks: the explicit rows
        sgn = np.where(CONJ[kind], -1.0, 1.0)
        kk = fallback_keys(slot == 2, k_end[par] * sgn[:, None], tau_end[par] * sgn)
        eq_key = fallback_keys(np.array([True]), np.zeros((1, 3)), np.zeros(1))
        uniq, inv = unique_rows(np.concatenate([kk, eq_key]))
        inv = inv.reshape(-1)
        child_z = uniq[:, 0].astype(bool)
    nU = child_z.size
    inv_e, eq_new = inv[:E], int(inv[E])
    camp = add_rows_by_index(inv_e, ccand, nU)
    cmag = estimate(camp)
    rep_e = first_max_by_group(inv_e, cand, nU)  # representative edge per child: largest cand; -1 when none
    alive = (cmag >= min_magnitude) & (rep_e >= 0)
    alive[eq_new] = True
    if alive.sum() > max_states:
        score = np.where(alive, cmag, -1.0)
        score[eq_new] = np.inf
        alive = top_k_mask(score, max_states)
    new_idx = np.cumsum(alive) - 1
    ekeep = alive[inv_e]
    sel = np.flatnonzero(alive)
    r = rep_e[sel]
    has = r >= 0
    rp = par[r[has]]
    rs = np.where(slot[r[has]] == 1, -1.0, 1.0)
    k = np.zeros((sel.size, 3))
    tau = np.zeros(sel.size)
    k[has] = k_end[rp] * rs[:, None]
    tau[has] = tau_end[rp] * rs
    eq = int(new_idx[eq_new])
    k[eq] = 0.0
    tau[eq] = 0.0
    z = child_z[sel]
    z[eq] = True
    return SplitResult(
        is_z=z,
        k=k,
        tau=tau,
        mag=cmag[sel],
        amp=camp[sel],
        eq=eq,
        e_child=new_idx[inv_e[ekeep]],
        e_par=par[ekeep],
        e_kind=kind[ekeep],
        e_cand=cand[ekeep],
    )


_local = threading.local()


def _scratch(E3: int, P: int) -> tuple:
    """The merge's temporaries for up to ``E3`` candidate edges of ``P`` probes: views of this thread's buffers,
    grown when needed and reused from one RF split to the next (fresh arrays of this size would be fresh pages,
    zeroed by the kernel, at every split); nothing that outlives the split is kept in them."""
    buf = getattr(_local, "merge", None)
    if buf is None or buf[0].size < E3 or buf[6].shape[1] != P:
        n = max(E3, 1024)
        buf = (
            np.empty(n, dtype=np.int64),
            np.empty(n, dtype=np.int64),
            np.empty(n, dtype=np.int64),
            np.empty(n),
            np.empty(n + 1, dtype=np.int64),
            np.empty(n + 1, dtype=bool),
            np.empty((n + 1, P), dtype=np.complex128),
            np.empty(n + 1, dtype=np.int64),
        )
        _local.merge = buf
    return tuple(b[:E3] for b in buf[:4]) + tuple(b[: E3 + 1] for b in buf[4:])


def _split_native(
    is_z: np.ndarray,
    k_end: np.ndarray,
    tau_end: np.ndarray,
    cand: np.ndarray,
    ccand: np.ndarray,
    qk: float,
    qt: float,
    tau_ignored: bool,
    min_magnitude: float,
    max_states: int,
    estimate: Callable[[np.ndarray], np.ndarray],
) -> SplitResult:
    """The rest of :func:`split_step` (from the candidates' estimates ``cand`` (3 S,) and probe amplitudes ``ccand``
    (3 S, P)) with the compiled merge: the same arrays bit for bit.  The children's amplitude estimate (complex abs,
    whose bits depend on the numpy build) stays ``estimate``, in numpy."""
    assert _native is not None
    S = is_z.size
    P = ccand.shape[1]
    E3 = 3 * S
    par, slot, kind, cand_k, inv, child_z, camp, rep = _scratch(E3, P)
    ins = (
        np.ascontiguousarray(cand, dtype=np.float64),
        np.ascontiguousarray(is_z, dtype=bool),
        np.ascontiguousarray(k_end, dtype=np.float64),
        np.ascontiguousarray(tau_end, dtype=np.float64),
        np.ascontiguousarray(ccand, dtype=np.complex128),
    )
    E, nU, eq_new = _native.merge(
        S,
        P,
        float(min_magnitude),
        float(qk),
        float(qt),
        bool(tau_ignored),
        (*ins, par, slot, kind, cand_k, inv, child_z, camp, rep),
    )
    camp = camp[:nU]
    cmag = np.ascontiguousarray(estimate(camp), dtype=np.float64)
    z = np.empty(nU, dtype=bool)
    k = np.empty((nU, 3))
    tau = np.empty(nU)
    mag = np.empty(nU)
    amp = np.empty((nU, P), dtype=np.complex128)
    e_child = np.empty(E, dtype=np.int64)
    e_par = np.empty(E, dtype=np.int64)
    e_kind = np.empty(E, dtype=np.int64)
    e_cand = np.empty(E)
    nS, nE, eq = _native.finish(
        nU,
        P,
        E,
        eq_new,
        S,
        float(min_magnitude),
        int(max_states),
        (
            cmag,
            rep,
            inv,
            par,
            slot,
            kind,
            cand_k,
            ins[2],
            ins[3],
            child_z,
            camp,
            z,
            k,
            tau,
            mag,
            amp,
            e_child,
            e_par,
            e_kind,
            e_cand,
        ),
    )
    return SplitResult(
        is_z=z[:nS],
        k=k[:nS],
        tau=tau[:nS],
        mag=mag[:nS],
        amp=amp[:nS],
        eq=int(eq),
        e_child=e_child[:nE],
        e_par=e_par[:nE],
        e_kind=e_kind[:nE],
        e_cand=e_cand[:nE],
    )


def unique_bits(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(distinct values of the float64 array ``x`` by their bits, in order of first occurrence; the index of each
    value among them), with the compiled core (:func:`native_in_use` must be true)."""
    assert _native is not None
    v = np.ascontiguousarray(x, dtype=np.float64).reshape(-1)
    u = np.empty(v.size)
    inv = np.empty(v.size, dtype=np.int64)
    U = _native.unique_bits(v.size, (v, u, inv))
    return u[:U], inv


def emission_native(pass_: int, params: tuple, arrays: tuple) -> int:
    """One pass of the compiled emission bound (``emission`` in ``dtoc/sim/_pdg_split.c``; the caller is
    :meth:`dtoc.sim.pdg_graph._Emission.exact`): ``params`` its scalars, ``arrays`` its arrays (C-contiguous)."""
    assert _native is not None
    return int(_native.emission(pass_, *params, arrays))


def prune_native(R: dict, latent: np.ndarray, restrict, prev_keep, prev_newi, emit_b, thr_latent, thr_emit, has_adc):
    """One interval (not the first) of :func:`dtoc.sim.pdg_graph._prune` with the compiled core (``prune`` in
    ``dtoc/sim/_pdg_split.c``; only comparisons, products and index work): (keep mask over the raw states, their new
    indices, and the interval's arrays: is_z, tau, k, eq, edge child/parent/kind, representative parent and
    conjugation, emitters, mag), bit for bit those of the numpy formulation."""
    assert _native is not None
    c = np.ascontiguousarray
    S = R["is_z"].size
    E = R["e_child"].size
    keep = np.empty(S, dtype=bool)
    newi = np.empty(S, dtype=np.int64)
    ec, ep, ek = (np.empty(E, dtype=np.int64) for _ in range(3))
    rep = np.empty(S, dtype=np.int64)
    rconj = np.empty(S, dtype=bool)
    emit = np.empty(S, dtype=np.int64)
    z = np.empty(S, dtype=bool)
    k = np.empty((S, 3))
    tau = np.empty(S)
    mag = np.empty(S)
    nS, nE, nem, eqn = _native.prune(
        S,
        E,
        prev_keep.size,
        int(R["eq"]),
        float(thr_latent),
        float(thr_emit),
        bool(has_adc),
        (
            c(R["mag"], dtype=np.float64),
            c(latent, dtype=np.float64),
            None if restrict is None else c(restrict, dtype=bool),
            c(R["e_child"], dtype=np.int64),
            c(R["e_par"], dtype=np.int64),
            c(R["e_kind"], dtype=np.int64),
            c(R["e_cand"], dtype=np.float64),
            c(prev_keep, dtype=bool),
            c(prev_newi, dtype=np.int64),
            c(emit_b, dtype=np.float64),
            c(R["is_z"], dtype=bool),
            c(R["k"], dtype=np.float64),
            c(R["tau"], dtype=np.float64),
            keep,
            newi,
            ec,
            ep,
            ek,
            rep,
            rconj,
            emit,
            z,
            k,
            tau,
            mag,
        ),
    )
    arrays = dict(
        is_z=z[:nS],
        tau_s=tau[:nS],
        k_nom_rad_per_m=k[:nS],
        eq_index=int(eqn),
        edge_child=ec[:nE],
        edge_parent=ep[:nE],
        edge_kind=ek[:nE],
        rep_parent=rep[:nS],
        rep_conj=rconj[:nS],
        emit=emit[:nem] if has_adc else np.zeros(0, dtype=np.int64),
        mag=mag[:nS],
    )
    return keep, newi, arrays
