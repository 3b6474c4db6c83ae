"""Read Pulseq ``.seq`` files (1.4.x, 1.5.x) and pypulseq ``Sequence`` objects into a :class:`SequenceIR`.

The IR holds the demanded gradient exactly as the Pulseq interpreter plays it, on the fine grid
``t_m = m * raster / 2`` (docs/conventions.md):

* trapezoids and extended trapezoids: straight lines between their vertices (on raster edges in any
  valid file, hence even fine samples);
* arbitrary gradients: straight lines through ``first`` (at the gradient start), the samples at raster
  centres (odd fine samples) and ``last`` (at the end of the shape);
* oversampled arbitrary gradients (time shape id -1): samples every half raster, with ``first``/``last``.

Where two blocks meet, the boundary sample takes the value the new block starts with (a valid file has
``last == first`` there; :mod:`dtoc.seq.check` reports jumps).  Vertices off the fine grid cannot be
represented exactly; they are linearly resampled and listed in ``ir.meta['off_grid_vertices']``.

Default ``free_mask`` (what an optimizer may change), documented in docs/sequences.md:

* never inside a block that holds an RF pulse (all axes, including that block's boundary samples:
  changing a boundary sample would put a ramp inside the RF block);  ``rf_guard='pulse'`` narrows this to
  the RF pulse itself (from its start to its end, all axes);
* never on an axis that carries a slice-selection gradient (non-zero demanded gradient at the centre of an
  excitation pulse) unless ``free_slice_axis=True``;
* never on an axis that carries no gradient at all in the sequence (e.g. z of a non-selective 2D GRE)
  unless ``free_unused_axes=True``: the paper optimizes the axes the base sequence uses;
* never the first and last sample of the sequence (gradients start and end at zero);
* never a block boundary that the two blocks do not play as one edge: next to a zero-duration block (labels
  only: the interpreter sees its axes without gradient there), or between blocks of different rotations
  (1.5.1 rotation extension: one played value there is two different logical values).  Such a boundary keeps
  the base's value, so the output is continuous exactly where the base is (a free value there made jumps of
  7-37 Hz/m in the written JEMRIS EPI and in a rotation-extension file).
"""

from __future__ import annotations

import contextlib
import copy
import os
import tempfile
from pathlib import Path

import numpy as np

from dtoc.constants import AXES, mT_per_m_from_hz_per_m
from dtoc.errors import InputError
from dtoc.seq.ir import ADCEvent, RFEvent, SequenceIR, interp_fine
from dtoc.seq.pulseq import quiet
from dtoc.seq.seqtext import parse_seq_text, verify_signature
from dtoc.seq.versions import quaternion_matrix, reader_text, version_str

_TIME_TOL = 1e-9  # s: times closer than this to a grid point are on it


def read_pypulseq(path: str | Path, require_signature: bool = True):
    """Pre-validate a ``.seq`` file and load it with pypulseq.

    Returns:
        (seq, seqtext): the ``pypulseq.Sequence`` and the :class:`dtoc.seq.seqtext.SeqText`.
    Raises:
        InputError: missing / empty / binary / truncated / corrupt / unsigned / bad signature /
            unsupported version, or anything pypulseq cannot read (one line).
    """
    from dtoc.seq.pulseq import import_pypulseq

    pp = import_pypulseq()

    p = Path(path)
    st = parse_seq_text(p)
    if require_signature:
        verify_signature(st, require=False)  # the signature is optional (specification); a present one must match
    # pypulseq reads dtoc's 1.5.0 rendering of the file, whatever its version (dtoc.seq.versions): it
    # always ends with a blank line (pypulseq loops forever on a file ending inside [SHAPES] without one).
    text, st.layout = reader_text(st)
    fd, tmp = tempfile.mkstemp(suffix=".seq")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(text)
        seq = pp.Sequence()
        with quiet():
            seq.read(tmp)
    except InputError:
        raise
    except Exception as e:  # noqa: BLE001 - pypulseq raises anything on bad content
        raise InputError(f"{p}: pypulseq cannot read it: {type(e).__name__}: {e}") from None
    finally:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
    if not seq.shape_library.data:  # no [SHAPES]: pypulseq's reader leaves a library its writer cannot extend
        seq.shape_library = type(seq.shape_library)(numpy_data=True)
    try:  # the rotation extension, played by from_pypulseq (pypulseq itself does not know it)
        seq.dtoc_rotations = st.layout.rotation_matrices()
    except InputError as e:
        raise InputError(f"{p}: {e}") from None
    return seq, st


def read_seq(
    path: str | Path,
    *,
    free_slice_axis: bool = False,
    free_unused_axes: bool = False,
    rf_guard: str = "block",
    require_signature: bool = True,
    rf_use: dict[int, str] | None = None,
) -> SequenceIR:
    """Read a Pulseq ``.seq`` file (format 1.2.0-1.5.2, docs/contracts.md §6) into a :class:`SequenceIR` (see module doc).

    Args:
        path: the ``.seq`` file.
        free_slice_axis: let the optimizer change the slice-select axis too (outside RF).
        free_unused_axes: let the optimizer use axes on which the sequence plays no gradient.
        rf_guard: 'block' (default) or 'pulse': what is fixed around RF pulses.
        require_signature: reject files whose md5 signature does not match (default; the signature itself is
            optional; pass False for hand-edited files).
        rf_use: RF use by the file's [RF] event id, over the file's or the detected one (:mod:`dtoc.seq.rfuse`).
    """
    seq, st = read_pypulseq(path, require_signature=require_signature)
    if b"\r" in st.raw:
        raise InputError(
            f"{path}: CR/CRLF line endings: Pulseq files use LF (convert with dos2unix, then re-sign; "
            "'dtoc check' lists what else differs)"
        )
    lay = st.layout
    ir = from_pypulseq(
        seq,
        free_slice_axis=free_slice_axis,
        free_unused_axes=free_unused_axes,
        rf_guard=rf_guard,
        free_mask=False,
    )
    ir.meta["path"] = str(path)
    ir.meta["format_version"] = version_str(st.version)
    if st.signature_hash is None:
        ir.meta["unsigned"] = True
    if lay.rotations:
        ir.meta["rotations"] = {int(b): list(q) for b, q in lay.rotations.items()}
    if lay.shims:
        ir.meta["rf_shims"] = {int(b): list(q) for b, q in lay.shims.items()}
    if lay.notes:
        ir.meta.setdefault("notes", []).extend(lay.notes)
    from dtoc.seq.rfuse import block_rf_ids_of_text, resolve_rf_use

    resolve_rf_use(ir, st.version, block_rf_ids_of_text(st), rf_use)  # pre-1.5 files: detected (no use field)
    ir.free_mask = None  # the IR's placeholder (3 bytes per fine sample) released before the mask is built
    ir.free_mask = default_free_mask(  # once, where the RF use is known (it fixes the samples around pulses)
        ir, free_slice_axis=free_slice_axis, free_unused_axes=free_unused_axes, rf_guard=rf_guard
    )
    return ir


# --------------------------------------------------------------------------------------------------
def grad_vertices(grad, raster_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (times relative to block start [s], values [Hz/m]) of one pypulseq gradient event."""
    if grad.type == "trap":
        d, r, f, fa, a = grad.delay, grad.rise_time, grad.flat_time, grad.fall_time, grad.amplitude
        t = np.array([d, d + r, d + r + f, d + r + f + fa])
        v = np.array([0.0, a, a, 0.0])
        return t, v
    w = np.asarray(grad.waveform, dtype=np.float64)
    tt = np.asarray(grad.tt, dtype=np.float64)
    first = float(grad.first) if getattr(grad, "first", None) is not None else None
    last = float(grad.last) if getattr(grad, "last", None) is not None else None
    tid = grad.time_id
    if tid == 0:  # arbitrary: first, raster-centre samples, last
        n = len(w)
        t_end = n * raster_s
        first = (1.5 * w[0] - 0.5 * w[1]) if first is None and n > 1 else (first if first is not None else w[0])
        last = (1.5 * w[-1] - 0.5 * w[-2]) if last is None and n > 1 else (last if last is not None else w[-1])
        t = np.concatenate([[0.0], (np.arange(n) + 0.5) * raster_s, [t_end]])
        v = np.concatenate([[first], w, [last]])
    elif tid == -1:  # oversampled: samples every half raster starting at raster/2
        n = len(w)
        t_end = (n + 1) * raster_s / 2
        t = np.concatenate([[0.0], (np.arange(n) + 1) * raster_s / 2, [t_end]])
        v = np.concatenate([[first if first is not None else w[0]], w, [last if last is not None else w[-1]]])
    else:  # extended trapezoid: vertices at tt
        t, v = tt.copy(), w.copy()
        if t[0] > _TIME_TOL:
            t = np.concatenate([[0.0], t])
            v = np.concatenate([[first if first is not None else 0.0], v])
    return t + grad.delay, v


@contextlib.contextmanager
def _shared_rf_decoding(seq, cache: dict):
    """While reading blocks: pypulseq's RF decoding (``rf_from_lib_data``: the magnitude and phase shapes
    expanded and multiplied, 2 million complex samples for a 2 s CEST pulse at 1 us) done once per
    (amplitude, shapes, use) and shared by the events that differ only in delay, centre, frequency and phase
    offsets (a CEST protocol's 34 saturation pulses: one decoding, not 34).  The shared arrays are only read;
    ``cache`` lives as long as the caller's reading (never on the sequence, which writers deep-copy)."""
    orig = type(seq).rf_from_lib_data

    def shared(lib_data, use: str = ""):
        if len(lib_data) < 10:  # (not the 1.5 library layout dtoc reads through: pypulseq's own way)
            return orig(seq, lib_data, use)
        key = (float(lib_data[0]), int(lib_data[1]), int(lib_data[2]), int(lib_data[3]), use)
        if key not in cache:
            cache[key] = orig(seq, lib_data, use)
        rf = copy.copy(cache[key])
        rf.center, rf.delay, rf.freq_ppm, rf.phase_ppm, rf.freq_offset, rf.phase_offset = lib_data[4:10]
        return rf

    seq.rf_from_lib_data = shared
    try:
        yield
    finally:
        del seq.rf_from_lib_data


def from_pypulseq(
    seq,
    *,
    free_slice_axis: bool = False,
    free_unused_axes: bool = False,
    rf_guard: str = "block",
    rotations: dict[int, np.ndarray] | None = None,
    free_mask: bool = True,
) -> SequenceIR:
    """Convert a ``pypulseq.Sequence`` (read or built) into a :class:`SequenceIR`.

    ``rotations``: {block index: 3x3 matrix} of the 1.5.1 rotation extension: that block's gradients are played
    as ``R @ (gx, gy, gz)`` (the IR holds the played, rotated gradients); default: those :func:`read_pypulseq`
    found in the file.  ``free_mask`` False: the caller sets ``ir.free_mask`` (:func:`read_seq` does, once the
    RF use of a pre-1.5 file is known, so the mask is built once).

    Raises:
        InputError: a block duration that is not a whole number of gradient rasters (the fine grid
            could not hold the block boundary).
    """
    if rotations is None:
        rotations = getattr(seq, "dtoc_rotations", None)
    if rf_guard not in ("block", "pulse"):
        raise InputError(f"rf_guard must be 'block' or 'pulse', got {rf_guard!r}")
    raster = float(seq.grad_raster_time)
    dtf = raster / 2
    keys = list(seq.block_events.keys())
    durs = np.array([seq.block_durations[k] for k in keys], dtype=np.float64)
    n_r = durs / raster
    bad = np.flatnonzero(np.abs(n_r - np.round(n_r)) > 1e-6)
    if bad.size:
        b = bad[0]
        raise InputError(
            f"block {keys[b]}: duration {durs[b] * 1e6:.3f} us is not a multiple of the gradient raster {raster * 1e6:g} us"
        )
    edge_idx = np.concatenate([[0], np.cumsum(np.round(n_r).astype(np.int64))])  # in raster units
    edges = edge_idx * raster
    n_fine = 2 * int(edge_idx[-1]) + 1
    g = np.zeros((3, n_fine))
    rf_events: list[RFEvent] = []
    adc_events: list[ADCEvent] = []
    off_grid: list[str] = []
    rf_blocks: list[int] = []
    soft: list[int] = []  # blocks holding a soft delay (their duration is set on the scanner)
    areas: dict[int, float] = {}  # id(signal) -> its area (the RF decoding is shared, _shared_rf_decoding)
    bandwidths: dict[int, float | None] = {}  # id(signal) -> its spectrum's FWHM, Hz
    b0_hz_per_ppm = float(seq.system.gamma) * float(seq.system.B0)  # Hz at 1 ppm x 1e6 (pypulseq: gamma in Hz/T)
    decoded: dict = {}
    for b, key in enumerate(keys):
        with quiet(), _shared_rf_decoding(seq, decoded):
            blk = seq.get_block(key)
        if getattr(blk, "soft_delay", None) is not None:
            soft.append(b)
        t0 = edges[b]
        m0, m1 = 2 * int(edge_idx[b]), 2 * int(edge_idx[b + 1])
        rot = rotations.get(b) if rotations else None
        local = np.zeros((3, m1 - m0 + 1)) if rot is not None else None
        covered = np.zeros(m1 - m0 + 1, dtype=bool)
        for a, ch in enumerate(("gx", "gy", "gz")):
            gr = getattr(blk, ch, None)
            if gr is None:
                continue
            tv, vv = grad_vertices(gr, raster)
            pos = tv / dtf
            if np.any(np.abs(pos - np.round(pos)) > _TIME_TOL / dtf):
                off_grid.append(f"block {key} {AXES[a]}")
            lo = m0 + int(np.clip(np.ceil(pos[0] - 1e-6), 0, m1 - m0))
            hi = m0 + int(np.clip(np.floor(pos[-1] + 1e-6), 0, m1 - m0))
            mm = np.arange(lo, hi + 1)
            vals = mT_per_m_from_hz_per_m(np.interp((mm - m0) * dtf, tv, vv))
            if local is None:
                g[a, mm] = vals
            else:
                local[a, mm - m0] = vals
                covered[mm - m0] = True
        if local is not None and covered.any():  # the rotation acts on the block's gradients as a whole
            idx = np.flatnonzero(covered)
            g[:, m0 + idx] = rot @ local[:, idx]
        if getattr(blk, "rf", None) is not None:
            rf = blk.rf
            rf_blocks.append(b)
            if id(rf.signal) not in areas:
                t_rf = np.asarray(rf.t, dtype=np.float64)
                sig = np.asarray(rf.signal)
                if len(t_rf) > 1 and rf.shape_dur > 0 and not np.allclose(np.diff(t_rf), seq.rf_raster_time):
                    areas[id(rf.signal)] = np.trapezoid(sig, t_rf)
                else:
                    areas[id(rf.signal)] = np.sum(sig) * seq.rf_raster_time
            area = areas[id(rf.signal)]
            if id(rf.signal) not in bandwidths:
                bandwidths[id(rf.signal)] = rf_bandwidth_hz(np.asarray(rf.t, dtype=np.float64), np.asarray(rf.signal))
            rf_events.append(
                RFEvent(
                    block=b,
                    t_start_s=float(t0 + rf.delay),
                    t_center_s=float(t0 + rf.delay + rf.center),
                    duration_s=float(rf.shape_dur),
                    flip_angle_rad=float(2 * np.pi * abs(area)),
                    phase_rad=float(rf.phase_offset),
                    freq_offset_hz=float(rf.freq_offset),
                    use=str(getattr(rf, "use", "undefined") or "undefined"),
                    bandwidth_hz=bandwidths[id(rf.signal)],
                    ppm_offset_hz=float(getattr(rf, "freq_ppm", 0.0) or 0.0) * 1e-6 * b0_hz_per_ppm,
                )
            )
        if getattr(blk, "adc", None) is not None:
            adc = blk.adc
            adc_events.append(
                ADCEvent(
                    block=b,
                    t_start_s=float(t0 + adc.delay),
                    num_samples=int(adc.num_samples),
                    dwell_s=float(adc.dwell),
                    phase_rad=float(adc.phase_offset),
                    freq_offset_hz=float(adc.freq_offset),
                )
            )
    # gradient at RF centres (slice selection)
    at_c = interp_fine(g, np.array([r.t_center_s for r in rf_events], dtype=np.float64), dtf)
    rf_events = [
        RFEvent(**{**r.__dict__, "grad_at_center_mT_per_m": tuple(float(at_c[a, i]) for a in range(3))})
        for i, r in enumerate(rf_events)
    ]
    defs = _plain_definitions(seq.definitions)
    ir = SequenceIR(
        raster_s=raster,
        grad_mT_per_m=g,
        block_edges_s=edges,
        rf=rf_events,
        adc=adc_events,
        definitions=defs,
        source=seq,
        source_grad_mT_per_m=g,  # the same array: the IR's waveform is replaced (with_grad), never written into
    )
    _apply_metadata(ir)
    if soft:
        ir.meta["soft_delay_blocks"] = soft
    if free_mask:
        ir.free_mask = default_free_mask(
            ir, free_slice_axis=free_slice_axis, free_unused_axes=free_unused_axes, rf_guard=rf_guard
        )
    ir.meta["block_ids"] = [int(k) for k in keys]
    n_undef = sum(r.use == "undefined" for r in rf_events)
    if n_undef:
        from dtoc.seq.rfuse import undefined_note

        ir.meta["rf_use_undefined"] = n_undef
        ir.meta.setdefault("notes", []).append(undefined_note(n_undef))
    if off_grid:
        ir.meta["off_grid_vertices"] = off_grid
    return ir


def _plain_definitions(defs) -> dict:
    out = {}
    for k, v in dict(defs).items():
        if isinstance(v, np.ndarray):
            out[k] = [float(x) for x in v.ravel()]
        elif isinstance(v, (np.floating, np.integer)):
            out[k] = float(v)
        else:
            out[k] = v
    return out


def _axis_index(v) -> int | None:
    if isinstance(v, str) and v.strip().lower() in AXES:
        return AXES.index(v.strip().lower())
    return None


#: a FOV definition above this (any axis), m, is taken as millimetres (:func:`_apply_metadata`)
FOV_MAX_M = 2.0


def _apply_metadata(ir: SequenceIR) -> None:
    """fov_m, matrix, kind and axes from the definitions written by dtoc's builder (or guessed)."""
    d = ir.definitions
    fov = d.get("FOV")
    if isinstance(fov, list) and len(fov) >= 2:
        f = list(fov) + [0.0] * (3 - len(fov))
        ir.fov_m = (float(f[0]), float(f[1]), float(f[2]))
    elif isinstance(fov, float):
        ir.fov_m = (fov, fov, 0.0)
    if ir.fov_m is not None and max(ir.fov_m) > FOV_MAX_M:
        # the specification's FOV is in metres; Pulseq MATLAB demos of 2018-2020 and JEMRIS wrote millimetres
        stated = " ".join(f"{x:g}" for x in ir.fov_m)
        ir.fov_m = tuple(x * 1e-3 for x in ir.fov_m)  # type: ignore[assignment]
        ir.meta.setdefault("notes", []).append(
            f"FOV definition {stated}: read as millimetres (assumed: over {FOV_MAX_M:g} m is no scanner's field "
            "of view in metres, the specification's unit; Pulseq MATLAB demos of 2018-2020 and JEMRIS wrote mm)"
        )
    mat = d.get("MatrixSize")
    if isinstance(mat, list):
        ir.matrix = tuple(int(round(x)) for x in mat if x)
    elif isinstance(mat, float):
        ir.matrix = (int(mat), int(mat))
    kind = d.get("Kind")
    ir.kind = kind.strip().lower() if isinstance(kind, str) else None
    ir.readout_axis = _axis_index(d.get("ReadoutAxis"))
    ir.phase_axis = _axis_index(d.get("PhaseAxis"))
    if "EchoSpacing" in d and isinstance(d["EchoSpacing"], float):
        ir.meta["echo_spacing_s"] = d["EchoSpacing"]
    if isinstance(d.get("Name"), str):
        ir.meta["name"] = d["Name"].strip()
    if ir.readout_axis is None and ir.adc:
        # guess: the axis with the largest mean |g| over all ADC samples
        gm = mean_abs_grad_at_adc(ir)
        if gm.max() > 0:
            ir.readout_axis = int(np.argmax(gm))
            ir.meta["axes_guessed"] = True


#: ADC samples per piece where :func:`mean_abs_grad_at_adc` interpolates (its temporaries: a piece's, not the
#: sequence's; a 5-minute 3D file has 5.8 M ADC samples: ~1 GB of whole-length temporaries at once)
ADC_PIECE = 1 << 18


def mean_abs_grad_at_adc(ir: SequenceIR) -> np.ndarray:
    """(3,) the mean |demanded gradient| over every ADC sample, per axis: the numbers of
    ``np.abs(ir.grad_at(ir.adc_times_s)[a]).mean()``, bit for bit (each |g| is elementwise, computed piece by piece
    into one array per axis, then averaged whole as before), without the (3, N_adc) interpolation's temporaries."""
    t = ir.adc_times_s
    out = np.empty(3)
    absg = np.empty(len(t))
    for a in range(3):
        for i in range(0, len(t), ADC_PIECE):
            e = slice(i, i + ADC_PIECE)
            absg[e] = np.abs(interp_fine(ir.grad_mT_per_m[a], t[e], ir.dt_fine_s))
        out[a] = absg.mean()
    return out


#: the most points :func:`rf_bandwidth_hz` zero-pads a waveform to
BANDWIDTH_FFT_MAX = 1 << 20
#: a waveform of more samples is averaged over blocks down to at most this many before its spectrum is taken (a
#: 2 s pulse: 30 us steps, a 16 kHz band: far wider than the band of any pulse that long)
BANDWIDTH_SAMPLES_MAX = 1 << 16


def rf_bandwidth_hz(t_s: np.ndarray, signal: np.ndarray) -> float | None:
    """Full width at half maximum (Hz) of the spectrum of an RF waveform (samples ``signal`` at times ``t_s``):
    the small-tip approximation of the band the pulse acts on (a slice: this width / (gamma |G|)).  The waveform is
    resampled onto a uniform grid of its shortest step (averaged over blocks down to :data:`BANDWIDTH_SAMPLES_MAX`
    samples when longer) and zero-padded to a frequency step of at most 1/64 of 1 / duration (at most
    :data:`BANDWIDTH_FFT_MAX` points: a long pulse's step is coarser); the width is that of the contiguous lobe
    around the spectrum's peak.  None for an empty or all-zero waveform (a block pulse's spectrum is a sinc:
    1.21 / duration)."""
    t = np.asarray(t_s, dtype=np.float64).ravel()
    s = np.asarray(signal).ravel()
    if t.size < 2 or s.size != t.size or not np.any(np.abs(s) > 0):
        return None
    dt = float(np.min(np.diff(t)))
    if not dt > 0:
        return None
    dur = float(t[-1] - t[0]) + dt
    if not np.allclose(np.diff(t), dt, rtol=1e-6, atol=1e-12):
        tu = np.arange(t[0], t[-1] + 0.5 * dt, dt)
        s = np.interp(tu, t, s.real) + 1j * np.interp(tu, t, s.imag) if np.iscomplexobj(s) else np.interp(tu, t, s)
    if s.size > BANDWIDTH_SAMPLES_MAX:  # a long waveform (a 2 s CEST train at 1 us): block means, a narrow band
        k = -(-s.size // BANDWIDTH_SAMPLES_MAX)
        s = np.concatenate([s, np.zeros((-s.size) % k, dtype=s.dtype)]).reshape(-1, k).mean(axis=1)
        dt *= k
    # zero-padded to 64x the duration, to at most BANDWIDTH_FFT_MAX points (2^27 points, 6 GB, for that CEST train)
    n = 1 << int(np.ceil(np.log2(max(min(64 * dur / dt, float(BANDWIDTH_FFT_MAX)), s.size))))
    spec = np.abs(np.fft.fftshift(np.fft.fft(s, n)))
    f = np.fft.fftshift(np.fft.fftfreq(n, dt))
    p = int(np.argmax(spec))
    half = 0.5 * spec[p]
    lo = p
    while lo > 0 and spec[lo - 1] >= half:
        lo -= 1
    hi = p
    while hi < n - 1 and spec[hi + 1] >= half:
        hi += 1
    df = float(f[1] - f[0])
    # half-maximum crossings interpolated linearly between the bins either side
    left = f[lo] - (df * (spec[lo] - half) / (spec[lo] - spec[lo - 1]) if lo > 0 else 0.0)
    right = f[hi] + (df * (spec[hi] - half) / (spec[hi] - spec[hi + 1]) if hi < n - 1 else 0.0)
    return float(right - left)


def slice_axes(ir: SequenceIR, tol_mT_per_m: float = 1e-6) -> list[int]:
    """Axes with a non-zero demanded gradient at the centre of any excitation pulse."""
    out = set()
    for r in ir.rf:
        if r.excites:
            for a in range(3):
                if abs(r.grad_at_center_mT_per_m[a]) > tol_mT_per_m:
                    out.add(a)
    return sorted(out)


def held_boundaries(ir: SequenceIR) -> list[int]:
    """Fine indices of the block boundaries that are not one played edge (module doc): next to a zero-duration
    block, or between two blocks whose rotations (1.5.1 extension) differ."""
    m_edges = np.round(np.asarray(ir.block_edges_s) / ir.dt_fine_s).astype(np.int64)
    rot = {int(b): quaternion_matrix(q) for b, q in (ir.meta.get("rotations") or {}).items()}
    if not rot:  # (from_pypulseq: the reader's matrices, before read_seq records the quaternions)
        rot = {int(b): np.asarray(r) for b, r in (getattr(ir.source, "dtoc_rotations", None) or {}).items()}
    nb = len(m_edges) - 1
    zero = np.flatnonzero(m_edges[1:] == m_edges[:-1])  # zero-duration blocks: both edges are one fine index
    out = {int(m_edges[b]) for b in zero}
    if rot:
        mats = np.broadcast_to(np.eye(3), (nb, 3, 3)).copy()
        for b, r in rot.items():
            if 0 <= b < nb:
                mats[b] = r
        differ = np.abs(mats[1:] - mats[:-1]).max(axis=(1, 2)) > 1e-12  # boundary b + 1 between b and b + 1
        out |= {int(m_edges[b + 1]) for b in np.flatnonzero(differ)}
    return sorted(out)


def default_free_mask(
    ir: SequenceIR, *, free_slice_axis: bool = False, free_unused_axes: bool = False, rf_guard: str = "block"
) -> np.ndarray:
    """(3, 2N+1) bool: where an optimizer may change the demanded gradient (module doc)."""
    n = ir.n_fine
    dtf = ir.dt_fine_s
    mask = np.ones((3, n), dtype=bool)
    mask[:, 0] = False
    mask[:, -1] = False
    for r in ir.rf:
        if rf_guard == "block":
            lo_t, hi_t = ir.block_edges_s[r.block], ir.block_edges_s[r.block + 1]
        else:
            lo_t, hi_t = r.t_start_s, r.t_start_s + r.duration_s
        lo = int(np.floor(lo_t / dtf + 1e-6))
        hi = int(np.ceil(hi_t / dtf - 1e-6))
        mask[:, max(lo, 0) : min(hi, n - 1) + 1] = False
    for b in ir.meta.get("soft_delay_blocks", []):  # its duration changes on the scanner: no gradient may live there
        lo = int(np.floor(ir.block_edges_s[b] / dtf + 1e-6))
        hi = int(np.ceil(ir.block_edges_s[b + 1] / dtf - 1e-6))
        mask[:, max(lo, 0) : min(hi, n - 1) + 1] = False
    for m in held_boundaries(ir):
        mask[:, m] = False
    if not free_slice_axis:
        for a in slice_axes(ir):
            mask[a, :] = False
    if not free_unused_axes:
        for a in range(3):
            if not np.any(ir.grad_mT_per_m[a]):
                mask[a, :] = False
    return mask
