"""The front of the sequence layer: a base sequence from whatever the user gives (``.seq`` file, spec file, spec).

Every command that takes a base sequence (simulate, predict, optimize) calls :func:`load_sequence`.
"""

from __future__ import annotations

from pathlib import Path

from dtoc.errors import InputError
from dtoc.seq.build import build_ir
from dtoc.seq.ir import SequenceIR
from dtoc.seq.read import read_seq
from dtoc.seq.spec import BaseSpec, load_spec


def load_sequence(path_or_spec, **kwargs) -> SequenceIR:
    """A base sequence from a ``.seq`` file, a spec ``.yaml``/``.yml`` file or a spec object.

    This is what every command that takes a base sequence (simulate, predict, optimize) calls.
    Keyword arguments go to :func:`read_seq` / :func:`from_pypulseq`.
    """
    rf_use = kwargs.pop("rf_use", None)
    if rf_use and (isinstance(path_or_spec, BaseSpec) or Path(path_or_spec).suffix.lower() != ".seq"):
        raise InputError("--rf-use applies to .seq files (a spec states each pulse's use)")
    if isinstance(path_or_spec, BaseSpec):
        return build_ir(path_or_spec, **kwargs)
    p = Path(path_or_spec)
    if p.suffix.lower() in (".yaml", ".yml"):
        ir = build_ir(load_spec(p), **kwargs)
        ir.meta["spec_path"] = str(p)
        return ir
    if p.suffix.lower() != ".seq" and p.exists():
        raise InputError(f"{p}: expected a .seq file or a spec .yaml")
    ir = read_seq(p, rf_use=rf_use, **kwargs)
    infer_missing_geometry(ir)
    return ir


def infer_missing_geometry(ir: SequenceIR) -> None:
    """For a file without FOV/matrix definitions (most pypulseq and Pulseq MATLAB files): read the Cartesian
    grid off the nominal k of its ADC samples (:func:`dtoc.seq.geometry.infer_cartesian_grid`) and guess the
    kind (several readouts per excitation with alternating polarity: EPI; one: GRE), each with a note.
    Non-Cartesian files keep no geometry (k-space figures only)."""
    if not ir.adc:
        return
    from dtoc.seq.geometry import infer_cartesian_grid, infer_cartesian_grid_3d

    sizes = [a.num_samples for a in ir.adc]
    if ir.fov_m is not None and ir.matrix is not None:
        if len(ir.matrix) == 3 and ir.matrix[2] > 1:  # a 3D file with definitions: its 3D grid from the k positions
            g3 = infer_cartesian_grid_3d(ir.nominal_kspace_rad_per_m(), sizes)
            if g3 is not None:
                ir.meta["grid3d"] = g3.as_meta()
                ir.meta.setdefault("notes", []).append(g3.describe())
        return
    k0 = ir.nominal_kspace_rad_per_m()  # (3, N_adc), computed once for every inference below
    notes = ir.meta.setdefault("notes", [])
    if float(abs(k0).max(initial=0.0)) < 1e-6:  # rad/m: every sample at the k-space centre
        notes.append(
            "every ADC sample sits at k = 0 (the file plays no encoding gradient: an FID or spectroscopy "
            "acquisition): k-space figures only, no image"
        )
        return
    g = infer_cartesian_grid(k0, sizes)
    declared = declared_geometry(ir)
    if g is None:
        _free_encoded_slice_axes(ir, k0, notes)
        _note_kind(ir, notes)
        g3 = infer_cartesian_grid_3d(k0, sizes)
        if g3 is not None:
            ir.meta["grid3d"] = g3.as_meta()
            note = g3.describe()
            if declared is not None and (declared[1] is None or len(declared[1]) < 3 or declared[1][2] <= 1):
                note += (
                    f"; the file defines {declared[2]} (2D): the readouts step along z between excitations, as "
                    "blocks whose z gradient area is not rewound (e.g. field-camera sync blocks) make them"
                )
            notes.append(note)
            return
        if not _non_cartesian_image_grid(ir, k0, notes):
            head = "no FOV/matrix definitions and" if declared is None else f"the file defines {declared[2]}, but"
            notes.append(
                f"{head} the ADC samples are not on a 2D Cartesian grid, nor on straight radial or Cartesian lines, "
                f"nor a 2D trajectory with a FOV definition ({why_not_cartesian(k0, sizes)}): k-space figures only, "
                "no image"
            )
        return
    ir.fov_m = g.fov_m
    ir.matrix = g.matrix_readout_phase
    ir.readout_axis, ir.phase_axis = g.readout_axis, g.phase_axis
    ir.meta["grid_inferred"] = True
    ir.meta["grid_offset_dk"] = list(g.offset_dk)
    note = g.describe(None if declared is None else declared[2])
    if declared is not None:
        note += _disagreement(declared, g.fov_m, g.matrix_readout_phase, g.readout_axis, g.phase_axis)
    notes.append(note)
    _note_kind(ir, notes)


def declared_geometry(ir: SequenceIR):
    """The file's own in-plane FOV (m, per axis x, y, z) and matrix definitions, as ``(fov or None, matrix or None,
    text)``; None when it defines neither.  FOV: the ``FOV`` definition (pypulseq and Pulseq MATLAB write it in m);
    matrix: ``MatrixSize`` (dtoc) or ``Matrix``."""
    fov = ir.fov_m if ir.fov_m is not None and any(f > 0 for f in ir.fov_m[:2]) else None
    mat = ir.matrix
    if mat is None:
        v = ir.definitions.get("Matrix")
        vals = v if isinstance(v, list) else [v] if isinstance(v, float) else []
        mat = tuple(int(round(x)) for x in vals if x) or None
        if mat is not None and len(mat) == 1:
            mat = (mat[0], mat[0])
    if fov is None and mat is None:
        return None
    parts = []
    if fov is not None:
        parts.append("FOV " + " x ".join(f"{1e3 * f:.4g}" for f in fov if f) + " mm")
    if mat is not None:
        parts.append("matrix " + " x ".join(str(m) for m in mat))
    return fov, mat, " and ".join(parts)


def _disagreement(declared, fov_m, matrix_ro_pe, ro: int, pe: int) -> str:
    """Where the file's definitions and the grid the ADC k positions sit on disagree, and what that means (the
    images use the ADC grid: an iFFT reconstructs what was sampled)."""
    fov_d, mat_d, _ = declared
    out = []
    if fov_d is not None:
        for a, what in ((ro, "readout"), (pe, "phase")):
            d, g = fov_d[a], fov_m[a]
            if d > 0 and g > 0 and abs(g / d - 1) > 0.01:
                r = g / d
                why = f" (oversampled {r:.3g}x)" if what == "readout" and r > 1 else ""
                out.append(
                    f"the ADC positions step by 2 pi / {1e3 * g:.4g} mm along {'xyz'[a]} ({what}), not 2 pi / the "
                    f"defined {1e3 * d:.4g} mm{why}"
                )
    if mat_d is not None and len(mat_d) >= 2:
        n_ro, n_pe = matrix_ro_pe
        want = {ro: mat_d[0] if ro == 0 else mat_d[1], pe: mat_d[1] if pe == 1 else mat_d[0]}
        for a, n, what in ((ro, n_ro, "readout"), (pe, n_pe, "phase")):
            if want[a] != n:
                out.append(
                    f"the ADC positions span {n} points along {'xyz'[a]} ({what}), the matrix definition {want[a]}"
                )
    if not out:
        return "; they agree with the definitions"
    return "; " + "; ".join(out) + ": images on the ADC grid"


def why_not_cartesian(k, sizes) -> str:
    """The reason, in the user's words, why the ADC samples are not on a 2D Cartesian grid."""
    import numpy as np

    from dtoc.seq.geometry import spread_within_between

    k = np.asarray(k, dtype=np.float64)
    edges = np.cumsum([0, *sizes])
    scale = max(float(np.abs(k).max()), 1e-12)
    within, between = spread_within_between(k, edges)
    moving = [a for a in range(3) if within[a] > 1e-4 * scale]
    if not moving:
        return "k does not move within any readout: no readout gradient"
    if len(moving) > 1:
        return f"k moves along {' and '.join('xyz'[a] for a in moving)} within a readout (radial, spiral or oblique)"
    stepped = [a for a in range(3) if a != moving[0] and between[a] > 1e-4 * scale]
    if 2 in stepped and len(stepped) > 1:
        return (
            f"k steps along z too, by up to {between[2]:.4g} rad/m between readouts: blocks whose z gradient area is "
            "not rewound (e.g. field-camera sync blocks, spoilers) accumulate kz"
        )
    if len(stepped) > 1:
        return f"k steps along {' and '.join('xyz'[a] for a in stepped)} between readouts (3D or oblique encoding)"
    return "the readout or phase positions are not on one uniform grid"


def _non_cartesian_image_grid(ir: SequenceIR, k, notes: list) -> bool:
    """A 2D in-plane (x, y) non-Cartesian trajectory gets an image grid for the non-uniform DFT reconstruction
    (:mod:`dtoc.sim.ndft`): FOV from the file's FOV definition, else 2 pi / step for radial readouts (straight,
    constant step); N = the even number of grid steps that covers the largest |k|.  True when set."""
    import math

    import numpy as np

    from dtoc.seq.geometry import radial_like_step

    scale = max(float(np.abs(k).max()), 1e-12)
    if np.ptp(k[2]) > 1e-4 * scale or ir.fov_m is not None and ir.matrix is not None:
        return False  # 3D (or already defined)
    if _line_cartesian_image_grid(ir, k, notes):  # ramp-sampled Cartesian lines, the file's FOV where it has one
        return True
    if ir.fov_m is not None and ir.fov_m[0] > 0 and ir.fov_m[1] > 0:
        fov, src = float(min(ir.fov_m[0], ir.fov_m[1])), "the file's FOV definition"
    else:
        sizes = [a.num_samples for a in ir.adc]
        step = radial_like_step(k, sizes)
        if step is not None:
            fov, src = 2 * math.pi / step, "2 pi / the radial sampling step"
        else:
            step = radial_like_step(k, sizes, constant=False)  # radial/UTE with ramp sampling
            if step is None:
                return False
            fov, src = 2 * math.pi / step, "2 pi / the radial flat-top step; ramp samples regridded"
    kmax = float(np.max(np.hypot(k[0], k[1])))
    n = 2 * max(int(math.ceil(kmax * fov / (2 * math.pi) - 1e-6)), 4)
    _set_ndft_grid(
        ir, (fov, fov, 0.0), (n, n), 0, 1, notes,
        f"non-Cartesian 2D: images by a non-uniform DFT on the nominal trajectory, {n} x {n} over "
        f"{1e3 * fov:.4g} mm ({src})",
    )  # fmt: skip
    return True


def _set_ndft_grid(ir: SequenceIR, fov_m, matrix, readout_axis: int, phase_axis: int, notes: list, note: str):
    """Give ``ir`` the image grid of the non-uniform DFT reconstruction (:mod:`dtoc.sim.ndft`), with its note."""
    ir.fov_m = fov_m
    ir.matrix = matrix
    ir.readout_axis, ir.phase_axis = readout_axis, phase_axis
    ir.meta["recon"] = "ndft"
    notes.append(note)


def _line_cartesian_image_grid(ir: SequenceIR, k, notes: list) -> bool:
    """Ramp-sampled Cartesian readouts (:func:`dtoc.seq.geometry.line_cartesian`): FOV 2 pi / step per axis (the
    readout's mean step), N the samples per readout and the phase lines spanned, images by the non-uniform
    DFT (the ramp samples regridded).  True when set."""
    import math

    from dtoc.seq.geometry import line_cartesian

    lc = line_cartesian(k, [a.num_samples for a in ir.adc])
    if lc is None:
        return False
    ro, pe, s_ro, s_pe, n_ro, n_pe = lc
    fov = [0.0, 0.0, 0.0]
    fov[ro], fov[pe] = 2 * math.pi / s_ro, 2 * math.pi / s_pe
    src = "2 pi / the readout's mean step, 2 pi / the phase step"
    declared = declared_geometry(ir)
    if declared is not None and declared[0] is not None and declared[0][ro] > 0:
        # the file's FOV: ramp sampling makes the readout's step non-uniform, so no step is "the" dk; a mean step
        # inflates the FOV when the ADC also samples the ramps at the flat top's dwell
        fd, mean_fov = declared[0], fov[ro]
        fov[ro] = fd[ro]
        kmax = float(max(abs(k[ro].min()), abs(k[ro].max())))
        n_ro = 2 * max(int(math.ceil(kmax * fov[ro] / (2 * math.pi) - 1e-6)), 2)
        src = (
            f"the file's FOV definition along {'xyz'[ro]}; 2 pi / the readout's mean step would give "
            f"{1e3 * mean_fov:.4g} mm"
        )
        if fd[pe] > 0 and abs(fov[pe] / fd[pe] - 1) > 0.01:
            src += f"; the phase lines step by 2 pi / {1e3 * fov[pe]:.4g} mm, not the defined {1e3 * fd[pe]:.4g} mm"
    _set_ndft_grid(
        ir, (fov[0], fov[1], 0.0), (n_ro, n_pe), ro, pe, notes,
        f"ramp-sampled Cartesian readouts along {'xyz'[ro]}: images by a non-uniform DFT on the nominal trajectory "
        f"(ramp samples regridded), {n_ro} (readout) x {n_pe} (phase) over {1e3 * fov[ro]:.4g} x "
        f"{1e3 * fov[pe]:.4g} mm ({src})",
    )  # fmt: skip
    return True


def _free_encoded_slice_axes(ir: SequenceIR, k, notes: list) -> None:
    """A slab-selective 3D sequence encodes k along its slab axis: that axis must be optimized too (outside RF)."""
    import numpy as np

    from dtoc.seq.read import default_free_mask, slice_axes

    scale = max(float(np.abs(k).max()), 1e-12)
    enc = [a for a in slice_axes(ir) if np.ptp(k[a]) > 1e-4 * scale]
    if enc:
        ir.free_mask = default_free_mask(ir, free_slice_axis=True)
        notes.append(
            f"k is encoded along the slice-select axis {','.join('xyz'[a] for a in enc)} (3D): optimized outside RF"
        )


def _note_kind(ir: SequenceIR, notes: list) -> None:
    if ir.kind is None:
        ir.kind = _guess_kind(ir)
        if ir.kind is not None:
            notes.append(f"kind guessed from the readout pattern: {ir.kind}")


def _guess_kind(ir: SequenceIR) -> str | None:
    """'epi' when an excitation is followed by several readouts of alternating readout polarity, 'gre' when
    every excitation has one readout, 'tse' (turbo / fast spin echo, HASTE) when an excitation is followed by a
    train of refocusing pulses with a readout between them (:func:`_is_spin_echo_train`); None otherwise."""
    import numpy as np

    exc = sorted(r.t_center_s for r in ir.rf if r.excites)
    if not exc:
        return None
    t_adc = np.array([a.t_start_s for a in ir.adc])
    per = np.bincount(np.searchsorted(exc, t_adc, side="right"), minlength=len(exc) + 1)[1:]
    if per.max() == 1:
        return "gre"
    ro = ir.readout_axis if ir.readout_axis is not None else 0
    mid = np.array([a.t_start_s + 0.5 * a.num_samples * a.dwell_s for a in ir.adc])
    sign = np.sign(np.interp(mid, ir.t_fine_s, ir.grad_mT_per_m[ro]))
    if per.max() > 1 and np.mean(sign[1:] * sign[:-1] < 0) > 0.5:
        return "epi"
    if _is_spin_echo_train(ir, exc, t_adc):
        return "tse"
    return None


def _is_spin_echo_train(ir: SequenceIR, exc: list[float], t_adc) -> bool:
    """An excitation followed by at least two refocusing pulses (Pulseq use 'refocusing') with a readout
    (ADC event) in every interval between consecutive refocusing pulses of the train and after its last one --
    in most of the excitation periods that hold a refocusing pulse."""
    import numpy as np

    t_ref = np.array(sorted(r.t_center_s for r in ir.rf if r.use == "refocusing"))
    if t_ref.size < 2:
        return False
    period = np.searchsorted(exc, t_ref, side="right")  # 0: before the first excitation
    trains = good = 0
    for p in np.unique(period[period > 0]):
        tr = t_ref[period == p]
        end = exc[p] if p < len(exc) else ir.duration_s + 1.0
        trains += 1
        good += int(tr.size >= 2 and np.all(np.histogram(t_adc, bins=np.r_[tr, end])[0] > 0))
    return trains > 0 and good > trains / 2
