"""Slice groups: which RF pulses of a sequence act on which spins (2D multi-slice sequences).

The simulator's object is one 2D sheet of spins (docs/simulator.md).  A 2D multi-slice sequence excites and
refocuses *different* spins in each slice; played on one sheet, every slice's pulses would act on the same
magnetisation and make echo pathways the acquisition does not have.  Each pulse is therefore placed in a band of
resonance offsets from the facts the sequence gives it (:class:`dtoc.seq.ir.RFEvent`: the offset
``f = freq_offset_hz + ppm_offset_hz``, ``bandwidth_hz``, ``grad_at_center_mT_per_m``):

* *slice-selective* (demanded gradient ``G`` at its centre, ``|G| > 1e-6`` mT/m): the spins at position ``r`` with
  ``gamma G . r`` in ``f +- bandwidth_hz / 2``, a slab of centre ``f / (gamma |G|)`` and
  thickness ``bandwidth_hz / (gamma |G|)`` along ``G / |G|``;
* *not slice-selective* with the water resonance inside its band (``|f| <= bandwidth_hz / 2``): every
  spin of the sheet (acts on every slice group);
* *spectrally selective* (no gradient, water outside the band, e.g. a fat-saturation pulse): no spin of the sheet
  (the phantom's spins all resonate at the water frequency: dtoc's phantoms have no chemical shift; the B0 map's
  offsets are assumed small against the distance from the band); played as a no-op;
* *unknown* (``bandwidth_hz`` None, synthetic IRs): every spin, as a non-selective pulse.

Slice-selective pulses form one *slice group* when their slabs share spins: same direction (within 1 degree) and
centres closer than 0.9 x the sum of their half-thicknesses (assumed: adjacent slices whose half-maximum slabs
overlap by less than 10 % of their thickness do not share spins -- the cross-talk of real slice profiles is
neglected), or different directions (their slabs cross); groups are the connected components of that relation.

A sequence with one slice group and no spectrally selective pulse is simulated as before (bit for bit).  Otherwise
each group is simulated apart on its own copy of the sheet -- its own pulses and the non-selective ones; the
others' pulses are no-ops (removed: relaxation, gradients and B0 continue) -- at the ADC events it is read out
by (:func:`dtoc.sim.pdg.simulate`): an ADC event belongs to the group of the last slice-selective pulse before it
(to every group, summed, when none precedes it).  Assumed: every slice holds the same phantom, and a slice's
residual transverse magnetisation is dephased across its slab by the time another slice is read out (the
slice-select, crusher and spoiler gradients played since; a 2D sheet has no thickness to dephase it).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from dtoc.constants import GAMMA_HZ_PER_T
from dtoc.seq.ir import SequenceIR

#: |G| at an RF centre above which the pulse is slice-selective, mT/m (as :func:`dtoc.seq.read.slice_axes`).
SELECTIVE_GRAD_MT_PER_M = 1e-6
#: two selective pulses share spins when their centres are closer than this fraction of the sum of their
#: half-thicknesses (assumed: adjacent contiguous slices do not).
OVERLAP_FRACTION = 0.9
_SAME_DIRECTION_COS = float(np.cos(np.radians(1.0)))


@dataclass(frozen=True)
class SliceGroups:
    """The spins each RF pulse acts on (module doc).

    Attributes:
        groups: one tuple per slice group: indices into ``ir.rf`` of the pulses acting on its spins (its own
            selective pulses, the non-selective ones and those of unknown band), ascending.
        inert: indices of the pulses that act on no spin of the sheet (spectrally selective).
        kinds: per pulse, 'selective', 'global', 'inert' or 'unknown'.
        adc: one tuple per slice group: indices into ``ir.adc`` of the ADC events it is read out by.
    """

    groups: tuple[tuple[int, ...], ...]
    inert: tuple[int, ...]
    kinds: tuple[str, ...]
    adc: tuple[tuple[int, ...], ...]

    @property
    def trivial(self) -> bool:
        """True when every pulse acts on the one sheet (one group, no inert pulse): the plain simulation."""
        return len(self.groups) <= 1 and not self.inert

    def irs(self, ir: SequenceIR) -> list[SequenceIR]:
        """One copy of ``ir`` per slice group holding only the pulses that act on its spins and the ADC events it
        is read out by (the same gradient)."""
        return [
            dataclasses.replace(ir, rf=[ir.rf[i] for i in g], adc=[ir.adc[i] for i in a])
            for g, a in zip(self.groups, self.adc, strict=True)
        ]

    def sample_index(self, ir: SequenceIR) -> list[np.ndarray]:
        """Per slice group, the positions of its ADC samples in the signal of ``ir`` (ADC events concatenated)."""
        start = np.concatenate([[0], np.cumsum([a.num_samples for a in ir.adc])]).astype(np.int64)
        return [
            np.concatenate([np.arange(start[i], start[i + 1]) for i in a]) if a else np.zeros(0, dtype=np.int64)
            for a in self.adc
        ]


def _band(r) -> tuple[str, np.ndarray | None, float, float]:
    """(kind, unit direction, centre along it m, half-thickness m) of one pulse (direction None unless selective)."""
    bw = r.bandwidth_hz
    if bw is None or not np.isfinite(bw) or bw <= 0:
        return "unknown", None, 0.0, 0.0
    g = np.asarray(r.grad_at_center_mT_per_m, dtype=np.float64)
    gn = float(np.linalg.norm(g))
    if gn <= SELECTIVE_GRAD_MT_PER_M:
        return ("global" if abs(r.freq_offset_hz + r.ppm_offset_hz) <= 0.5 * bw else "inert"), None, 0.0, 0.0
    n = g / gn
    sign = 1.0 if n[int(np.argmax(np.abs(n)))] > 0 else -1.0  # a canonical direction: -G with -f is the same slab
    hz_per_m = GAMMA_HZ_PER_T * gn * 1e-3
    return "selective", sign * n, sign * (r.freq_offset_hz + r.ppm_offset_hz) / hz_per_m, 0.5 * bw / hz_per_m


def slice_groups(ir: SequenceIR) -> SliceGroups:
    """The slice groups of ``ir`` (module doc)."""
    bands = [_band(r) for r in ir.rf]
    kinds = tuple(b[0] for b in bands)
    sel = [i for i, k in enumerate(kinds) if k == "selective"]
    # the distinct slabs (a protocol repeats a few slabs many times), compared pairwise
    keys: dict[tuple, int] = {}
    slab_of = {}
    for i in sel:
        _, n, c, h = bands[i]
        assert n is not None
        slab_of[i] = keys.setdefault((*np.round(n, 9).tolist(), round(c, 12), round(h, 12)), len(keys))
    slabs = [(np.array(k[:3]), k[3], k[4]) for k in keys]
    parent = list(range(len(slabs)))

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for a, (na, ca, ha) in enumerate(slabs):
        for b in range(a + 1, len(slabs)):
            nb, cb, hb = slabs[b]
            if float(na @ nb) < _SAME_DIRECTION_COS or abs(ca - cb) < OVERLAP_FRACTION * (ha + hb):
                ra, rb = find(a), find(b)
                if ra != rb:
                    parent[max(ra, rb)] = min(ra, rb)
    roots = sorted({find(slab_of[i]) for i in sel})
    shared = [i for i, k in enumerate(kinds) if k in ("global", "unknown")]
    if roots:
        groups = tuple(tuple(sorted(shared + [i for i in sel if find(slab_of[i]) == r])) for r in roots)
    else:
        groups = (tuple(shared),)
    inert = tuple(i for i, k in enumerate(kinds) if k == "inert")
    # each ADC event: the group of the last slice-selective pulse before it (every group when none is)
    sel_t = np.array([ir.rf[i].t_center_s for i in sel], dtype=np.float64)
    sel_g = [roots.index(find(slab_of[i])) for i in sel]
    adc: list[list[int]] = [[] for _ in groups]
    for j, ev in enumerate(ir.adc):
        p = int(np.searchsorted(sel_t, float(ev.t_start_s), side="right")) - 1 if sel_t.size else -1
        for g in (sel_g[p],) if p >= 0 else range(len(groups)):
            adc[g].append(j)
    return SliceGroups(groups, inert, kinds, tuple(tuple(a) for a in adc))
