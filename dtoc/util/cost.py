"""Cost estimates before work: memory and time from sizes, against this machine (docs/cli.md, "Cost estimates").

Every estimate a command makes before it works lives here: a simulation (phantom voxels x ADC samples, and its
steady-state dummy train: repetitions x samples per repetition x voxels) and an optimization (the whole solve
from its fine samples, or the windowed solve from the plan's window sizes).  ``.npz`` archives are checked by
their declared sizes in :func:`dtoc.util.validate.check_npz_archive`; the machine (available memory, cores) is
read there too.  A job whose estimated peak memory exceeds 75 % of the available memory is refused in one line
with the estimate and a way out; none of these functions does any of the work it estimates.

The constants are measured: they are rough (a factor of about 2 either way), never a guarantee, and every
printed figure says "estimate".  Where each was measured is stated beside it.
"""

from __future__ import annotations

from dtoc.errors import InputError
from dtoc.util.validate import available_memory_bytes, gib

#: the share of the available memory a job may be estimated to need
FIT_FRACTION = 0.75

# --- the PDG simulation -------------------------------------------------------------------------------
#: bytes per phantom voxel a simulation holds at least (maps, states, the signal's per-voxel factors; the
#: 128x128 EPI on a 256x256 phantom peaks at ~0.97 GB, docs/benchmarks.md "sim": ~15 KB per voxel there)
SIM_BYTES_PER_VOXEL = 4096
#: seconds per (voxel x ADC sample) of one forward simulation (same benchmark: 0.65 s for 1.07e9)
SIM_SECONDS_PER_VOXEL_SAMPLE = 6e-10
#: the signal of a phase distribution graph (:func:`emission_cost`): the same seconds per (emitting state x ADC sample x
#: voxel) -- one emitting state per sample in that EPI -- and, per voxel, this many complex (emitting states x voxels)
#: arrays of the interval with the most emitting states (its spatial phase, amplitudes expanded to voxels, products).
#: Measured 2026-11-27 on the 2-core Xeon (load ~10) on pypulseq's trufi_v141.seq (balanced SSFP, 256 lines; its graph:
#: ~92 emitting states per ADC sample, at most 353 in one TR, at 256x256 voxels): the base's signal alone passed
#: 3.2 GB (and was still growing), the run through its report image 6.3 GB (the bench's cap): ~16 such arrays
SIM_EMIT_ARRAYS = 16
#: the image for the report of a windowed run (k-space solve; the image does not enter it) is simulated only when its
#: estimate is at most this: beyond, its figures are replaced by their reason (dtoc.optimize.run.report_image_reason)
REPORT_IMAGE_MAX_SECONDS = 120.0
#: the dummy train (:func:`dtoc.sim.pdg.steady_state_mz`) grows with every repetition: its time grid and
#: moments (bytes per fine sample of a repetition), its states (per repetition) and the voxels' share.
#: Measured 2026-11-27 on this project's 2-core Intel Xeon machine (peak RSS growth of a process, load ~10):
#: sequences/gre_small.seq (1200 fine samples per repetition) 1.38 MB per dummy at 32x32 voxels, 1.58 MB at
#: 64x64 (200 dummies); KomaMRI's gammaSTAR FID (568,905 fine samples per repetition) 100 MB per dummy.
DUMMY_BYTES_PER_FINE = 180
DUMMY_BYTES_PER_REPETITION = 1.1e6
DUMMY_BYTES_PER_VOXEL = 70
#: seconds per dummy (same runs, loaded machine): 0.39 s (GRE, state-bound), 0.69 s (FID, 1.2 us per sample)
DUMMY_SECONDS_PER_FINE = 1.2e-6
DUMMY_SECONDS_PER_REPETITION = 0.35

# --- reading a base -------------------------------------------------------------------------------------
#: the peak of reading a base (:func:`dtoc.seq.load.load_sequence`: the parsed text and pypulseq's objects, the IR's
#: fine waveform and masks, the nominal k and the grid's inference, both in pieces) as a whole process: a fixed part
#: (Python, torch, pypulseq, the pieces' temporaries) and bytes per gradient raster step and per ADC sample.  The
#: reader's size guard (:func:`dtoc.seq.seqtext._check_sizes`: three quarters of the machine's memory) refuses only
#: what this read cannot hold; a command's own estimate (:func:`optimize_cost`) includes it.  Measured 2026-11-27 on
#: this project's 2-core Intel Xeon machine (``load_sequence`` alone in a process with the CLI's allocator setting,
#: peak RSS from wait4 in bytes; bench.protocols' writers, pypulseq 32 mT/m / 130 T/m/s): the 3D FLASH 1 mm at 24 and
#: 96 partitions (2,995,200 / 11,980,800 raster steps, 1,179,648 / 4,718,592 ADC samples) 0.865 / 1.667 GB, the
#: MPRAGE at 16, 128 and 256 shots (3,680,016 / 29,440,128 / 58,880,256, 720,896 / 5,767,168 / 11,534,336) 0.771 /
#: 2.681 / 4.860 GB.  Fitted to the three largest (0.50 GB + 51 B per raster step + 117 B per ADC sample), the fixed
#: part raised to cover the smaller ones: 1-11 % above each.  Before, the guard counted 528 B per raster step and
#: 400 B per ADC sample (11 whole-sequence fine copies of a long optimize, not the read): the 9.8 min MPRAGE, read in
#: 4.86 GB, was refused at 35.7 GB.
LOAD_BYTES = 0.58e9
LOAD_BYTES_PER_RASTER = 52.0
LOAD_BYTES_PER_ADC = 118.0

# --- the optimizer ------------------------------------------------------------------------------------
#: the process before any work (Python, torch, dtoc, the base read)
PROCESS_BYTES = 0.35e9
#: whole solve (every free edge at once, the twin with autograd over the whole sequence): peak bytes per fine
#: sample and per ADC sample, CPU seconds per fine sample and per squared ADC sample.  Fitted to three runs of
#: docs/benchmarks.md (2 cores): bench.protocols 2026-11-27 (Intel Xeon) EPI 256 (154,000 fine samples, 65,536
#: ADC samples) 3.67 GB, 292 s CPU; EPI 128 (39,000 / 16,384) 0.71 GB, 19 s; bench.long 2026-11-25 MPRAGE 1 s
#: whole (200,000 / 1,024) 0.84 GB, 45 s.  The fit is within 1.7x of each (above it for EPI 128).
WHOLE_BYTES_PER_FINE = 2.4e3
WHOLE_BYTES_PER_ADC = 45e3
WHOLE_SECONDS_PER_FINE = 1.75e-4
WHOLE_SECONDS_PER_ADC2 = 6.2e-8
#: windowed solve (one excitation period at a time): the whole-sequence arrays (bytes per fine sample: the IR's
#: waveform and mask, the limit envelopes, the edges, the export's waveform; bytes per ADC sample: nominal and
#: realized k, their errors and masks, the read-back of the written file's ADC events), the dense matrices of the
#: largest window (this many n_free x n_free float64 matrices: the structures' cache -- J, the normal matrix, its
#: inverse and ADMM's, per structure, every one of them reused by later windows -- and the one being built), the
#: largest window's own arrays (below) and CPU seconds per fine and per ADC sample.  Refitted 2026-11-27 (s8h2) after
#: the window Jacobian's copies across the gap between a window's free runs (1.8 GB on the MPRAGE's longest window)
#: and the inverses' temporaries were cut, to runs on this project's 2-core Intel Xeon machine, peak RSS from wait4 in
#: bytes (the bench tables print KiB / 1e6), the CLI's allocator setting, KCL 7 T GIRF, 32/130, load 5-8:
#: bench.protocols' MPRAGE base at 8 and 16 shots (18.4 / 36.8 s; 3,680,017 / 7,360,033 fine and 360,448 / 720,896
#: ADC samples, at most 4,806 free and 225,659 fine samples a window): 2.84 / 3.21 GB (before the cut 3.82 / 4.02
#: GB); the MPRAGE 5 min row (58,880,257 / 5,767,168, 22,529 windows): 9.47 GB, its peak now in the export's write
#: and read-back (before the cut 9.47-9.67 GB, ~8.1 GB of it in the windows' stage); the 3D FLASH 1 mm row
#: (23,961,601 / 4,718,592, at most 1,608 free and 11,561 fine samples a window): at least 5.87 GB (it ran past
#: its 1,500 s wall limit in the export's read-back; before the cut 5.54-5.81 GB); bench.long's MPRAGE-like 16 s
#: and 64 s (3,151,361 / 12,605,441 fine, 16,384 / 65,536 ADC, at most 3,924 free and 160,681 fine samples a window):
#: 1.89 / 2.41 GB (before 2.47 / 2.89 GB).  The model is
#: 0-15 % above each.
#: The peaks of the long rows are the export's (the written text, pypulseq's objects, the read-back), which grows
#: with the ADC samples of a 3D protocol: hence the bytes per ADC sample.  CPU seconds from the earlier fit: 1,193 s
#: for the MPRAGE 5 min, ~170 s for its 16-shot cut, bench.long's 16 / 64 s 44 / 133 s.
WINDOW_BYTES_PER_FINE = 45
WINDOW_BYTES_PER_ADC = 900
WINDOW_DENSE_MATRICES = 8
#: the window's own arrays, per fine sample of the longest window (its impulse responses over twice its length on
#: every chain channel, their running integrals, its residual): measured 2026-11-27 on the 2-core Xeon (load ~15,
#: freed memory returned to the system) on tests/test_windowed.py's idle GRE periods, Lti eddy kernel: 3 periods of
#: 200,000 / 400,000 fine samples peaked at 1.08 / 1.86 GB, 3.9 KB per fine sample of the window.  An excitation
#: period of a minute (CEST preparations: 6 M fine samples) needs ~24 GB: refused here before any work
WINDOW_BYTES_PER_WINDOW_FINE = 3.9e3
WINDOW_SECONDS_PER_FINE = 9.4e-6
WINDOW_SECONDS_PER_ADC = 1.09e-4
#: fixed seconds of a run (reading, the hardware model, the first evaluations)
RUN_SECONDS = 10.0
#: an optimization whose estimate reaches this many seconds prints its estimate (a windowed one always does)
LONG_RUN_SECONDS = 60.0


def load_bytes(n_raster: float, n_adc: float) -> float:
    """Estimated peak bytes of the process that reads a base of ``n_raster`` gradient raster steps and ``n_adc`` ADC
    samples (constants above: measured, an estimate)."""
    return LOAD_BYTES + LOAD_BYTES_PER_RASTER * float(n_raster) + LOAD_BYTES_PER_ADC * float(n_adc)


def held_bytes() -> int:
    """Resident memory this process already holds (VmRSS, Linux; 0 where unknown)."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return 0


def job_memory_bytes() -> int:
    """Memory this job may use: what the machine has available (MemAvailable, at most the cgroup limit) plus what
    the process already holds.  An estimate is of the process's whole peak (the read base, the plan and the
    process itself included: :data:`PROCESS_BYTES`), and MemAvailable no longer counts what the process holds
    when the estimate is made (a 4.9 min MPRAGE: ~4 GB read and planned by then, its estimate 9.28 GiB, refused
    against 75 % of 12 GiB "available" where 16 GiB were)."""
    return available_memory_bytes() + held_bytes()


def check_fits(
    what: str, need_bytes: float, fraction: float | None = None, way_out: str = "", avail: float | None = None
) -> None:
    """Refuse, before any work, a job whose estimated peak memory exceeds ``fraction`` (None: :data:`FIT_FRACTION`
    read at the call, so a value set at runtime counts) of the available memory (``avail``; default
    :func:`available_memory_bytes`: an estimate of what the job adds; an estimate of the whole process's peak
    passes :func:`job_memory_bytes`).

    Raises:
        InputError: ``"<what>: needs about X GiB ... (estimate, before any work), more than 75 % of the Y GiB
        available here: refused[; way out]"``.
    """
    fraction = FIT_FRACTION if fraction is None else fraction
    avail = available_memory_bytes() if avail is None else avail
    if need_bytes > fraction * avail:
        raise InputError(
            f"{what}: needs about {gib(need_bytes)} of memory (estimate, before any work), more than "
            f"{fraction:.0%} of the {gib(avail)} available here: refused" + (f"; {way_out}" if way_out else "")
        )


def simulation_cost(n_voxels: int, n_samples: int, n_phantoms: int = 1, n_runs: int = 1) -> tuple[float, float]:
    """(bytes, seconds) a lower-bound estimate of simulating ``n_phantoms`` phantoms of ``n_voxels`` each over
    ``n_samples`` ADC samples ``n_runs`` times (constants above; measured on the benchmark machine)."""
    mem = float(n_voxels) * SIM_BYTES_PER_VOXEL * max(1, n_phantoms)
    sec = float(n_voxels) * float(n_samples) * SIM_SECONDS_PER_VOXEL_SAMPLE * max(1, n_phantoms) * max(1, n_runs)
    return mem, sec


def emission_cost(graph, n_voxels: int, n_phantoms: int = 1, n_runs: int = 1) -> tuple[float, float, float]:
    """(bytes, seconds, emitting states per ADC sample) of ``n_runs`` simulations of ``n_phantoms`` phantoms of
    ``n_voxels`` each through a built phase distribution graph (:func:`dtoc.sim.pdg.build_graph`; of a
    ``GroupedGraph``, every slice group's): the work is every interval's emitting states x its ADC samples x the
    voxels.  :func:`simulation_cost` assumes one emitting state
    per sample (a spoiled or single-shot readout); an unspoiled steady state keeps ~100 coherent pathways emitting at
    every sample, and this sees them.  A lower bound like :func:`simulation_cost` (same constant per element)."""
    work = 0.0
    samples = 0
    most = 0
    for g in getattr(graph, "graphs", [graph]):  # a GroupedGraph (slice groups): every group's own intervals
        for iv in g.intervals:
            t = int(iv.adc_stop - iv.adc_start)
            e = int(iv.emit.size)
            work += float(e) * t
            samples += t
            most = max(most, e)
    v = float(n_voxels)
    mem = v * (SIM_BYTES_PER_VOXEL + SIM_EMIT_ARRAYS * 16.0 * most) * max(1, n_phantoms)
    sec = work * v * SIM_SECONDS_PER_VOXEL_SAMPLE * max(1, n_phantoms) * max(1, n_runs)
    return mem, sec, work / max(samples, 1)


def dummy_cost(n_dummies: int, fine_per_repetition: float, n_voxels: int) -> tuple[float, float]:
    """(bytes, seconds) of a steady-state dummy train of ``n_dummies`` repetitions of ``fine_per_repetition``
    fine samples each on ``n_voxels`` voxels (it holds every repetition until its end)."""
    n = max(int(n_dummies), 0)
    per = (
        DUMMY_BYTES_PER_FINE * float(fine_per_repetition)
        + DUMMY_BYTES_PER_REPETITION
        + DUMMY_BYTES_PER_VOXEL * float(n_voxels)
    )
    sec = DUMMY_SECONDS_PER_FINE * float(fine_per_repetition) + DUMMY_SECONDS_PER_REPETITION
    return n * per, n * sec


def fine_per_repetition(ir) -> float:
    """Fine samples of the average repetition a dummy train plays (the span from one excitation to the next)."""
    n_exc = sum(1 for r in ir.rf if r.excites) or len(ir.rf) or 1
    return ir.grad_mT_per_m.shape[1] / n_exc


def check_simulation_cost(
    what: str,
    n_voxels: int,
    n_samples: int,
    n_phantoms: int = 1,
    n_runs: int = 1,
    n_dummies: int = 0,
    fine_per_rep: float = 0.0,
    dummies_option: str = "--dummies",
) -> tuple[str, float]:
    """Refuse (one line, with the estimate) a simulation that cannot fit this machine's memory; returns the
    estimate as text for a note and its seconds.  The dummy train (``n_dummies`` repetitions of
    ``fine_per_rep`` fine samples) runs before the simulation, once per phantom; its memory is freed after."""
    mem, sec = simulation_cost(n_voxels, n_samples, n_phantoms, n_runs)
    dmem, dsec = dummy_cost(n_dummies, fine_per_rep, n_voxels)
    peak = max(mem, PROCESS_BYTES + dmem)
    text = f"{n_phantoms} phantom(s) x {n_voxels} voxels x {n_samples} ADC samples"
    if n_dummies > 0:
        text += f", {n_dummies} dummies x {fine_per_rep:.0f} samples per repetition"
    text += f": at least {gib(peak)} and ~{sec + dsec * max(1, n_phantoms):.3g} s of simulation (estimate)"
    way_out = ""
    if n_dummies > 0 and dmem > mem:
        each = dmem / n_dummies
        way_out = f"give fewer dummy repetitions ({dummies_option}; each ~{each / 2**20:.3g} MiB here)"
    else:
        way_out = "give a smaller phantom (brain:N) or fewer augmentations"
    check_fits(f"{what}: {text}", peak, way_out=way_out)
    return text, sec + dsec * max(1, n_phantoms)


def optimize_cost(n_fine: int, n_adc: int, window: dict | None = None) -> tuple[float, float, str]:
    """(bytes, seconds, what it is from) of an optimization's solve of ``n_fine`` fine samples and ``n_adc``
    ADC samples.

    ``window``: None (whole solve) or the windowed plan's sizes: ``{"n_windows", "max_free", "max_fine"}``
    (windows, the most free variables of one window, the most fine samples of one window); the windowed
    memory is the whole-sequence arrays plus the largest window's dense matrices and its own arrays, so it
    follows the plan's window sizes and not the duration alone; the whole-sequence arrays grow with the fine and
    the ADC samples (a 3D protocol's millions of ADC samples weigh as much as its fine grid)."""
    n, a = float(n_fine), float(n_adc)
    if window is None:
        mem = PROCESS_BYTES + WHOLE_BYTES_PER_FINE * n + WHOLE_BYTES_PER_ADC * a
        mem = max(mem, load_bytes(n / 2, a))  # the process reads the base first: never less than its read
        sec = RUN_SECONDS + WHOLE_SECONDS_PER_FINE * n + WHOLE_SECONDS_PER_ADC2 * a * a
        return mem, sec, f"whole solve of {n_fine} fine and {n_adc} ADC samples"
    mf = float(window["max_free"])
    mem = PROCESS_BYTES + WINDOW_BYTES_PER_FINE * n + WINDOW_BYTES_PER_ADC * a + WINDOW_DENSE_MATRICES * 8.0 * mf * mf
    mem += WINDOW_BYTES_PER_WINDOW_FINE * float(window.get("max_fine", 0))
    mem = max(mem, load_bytes(n / 2, a))
    sec = RUN_SECONDS + WINDOW_SECONDS_PER_FINE * n + WINDOW_SECONDS_PER_ADC * a
    return (
        mem,
        sec,
        (
            f"{window['n_windows']} windows of at most {int(mf)} free variables and {window['max_fine']} fine samples, "
            f"{n_fine} fine and {n_adc} ADC samples"
        ),
    )


def check_optimize_cost(
    what: str,
    n_fine: int,
    n_adc: int,
    window: dict | None,
    sim: tuple[float, float] = (0.0, 0.0),
    notes=None,
    whole_why: str | None = None,
) -> tuple[float, float]:
    """Estimate an optimization from its sizes (``sim``: the image term's (bytes, seconds), if any); print one
    line through ``notes`` for a long run (estimated time, peak memory, the machine's available memory) and
    refuse (InputError, one line with the estimate) one that cannot fit the available memory; ``whole_why``: why a
    long sequence is solved whole (its way out then does not offer the windowed solve).  Returns (bytes, seconds)."""
    mem, sec, src = optimize_cost(n_fine, n_adc, window)
    mem, sec = mem + sim[0], sec + sim[1]
    avail = job_memory_bytes()
    line = (
        f"estimate ({src}): ~{_duration(sec)} and {gib(mem)} peak memory; {gib(avail)} available on this machine "
        "(rough: docs/cli.md, Cost estimates)"
    )
    if window is not None:
        way_out = "a shorter file, or fewer free variables per excitation period, or shorter excitation periods"
    elif whole_why:  # the windowed solve would be refused too: say why instead of offering it
        way_out = f"a shorter file (it cannot be solved period by period: {whole_why})"
    else:
        way_out = "the windowed solve holds less (windowed: on in --config)"
    check_fits(f"{what}: {line}", mem, way_out=way_out, avail=avail)
    if notes is not None and (sec >= LONG_RUN_SECONDS or window is not None):
        notes(line)
    return mem, sec


def _duration(sec: float) -> str:
    if sec < 120:
        return f"{sec:.0f} s"
    if sec < 7200:
        return f"{sec / 60:.0f} min"
    return f"{sec / 3600:.1f} h"


__all__ = [
    "check_fits",
    "check_optimize_cost",
    "check_simulation_cost",
    "dummy_cost",
    "emission_cost",
    "fine_per_repetition",
    "held_bytes",
    "job_memory_bytes",
    "load_bytes",
    "optimize_cost",
    "simulation_cost",
]
