"""Cost estimates before work (issue 35 point 4, issue 36 point 5): the dummy train's memory is in the
simulation estimate, a long optimization prints its estimate, and what cannot fit the machine's memory is
refused in one line before any work (dtoc.util.cost)."""

from __future__ import annotations

from pathlib import Path

import pytest
from cli_helpers import run_cli

import dtoc.util.cost as cost
from dtoc.errors import InputError
from dtoc.seq.load import load_sequence

REPO = Path(__file__).resolve().parents[1]
GRE = REPO / "sequences" / "gre_small.seq"


WORK = "the work started"


@pytest.fixture(autouse=True)
def _holds_nothing(monkeypatch):
    """The machine's memory is what each test says: none held by this (pytest) process on top of it."""
    monkeypatch.setattr(cost, "held_bytes", lambda: 0)


class NoWork(Exception):
    pass


def _no_work(*_a, **_k):
    raise NoWork(WORK)  # the CLI reports it as an internal error (exit 3) naming it


def test_the_dummy_train_grows_the_estimate_with_dummies_samples_and_voxels():
    ir = load_sequence(GRE)
    fpr = cost.fine_per_repetition(ir)
    assert fpr == pytest.approx(ir.grad_mT_per_m.shape[1] / 16)  # 16 excitations
    m1, s1 = cost.dummy_cost(100, fpr, 1024)
    m2, s2 = cost.dummy_cost(200, fpr, 1024)
    assert m2 == pytest.approx(2 * m1) and s2 == pytest.approx(2 * s1)
    assert cost.dummy_cost(100, 100 * fpr, 1024)[0] > 5 * m1  # a long repetition (an FID's) costs more
    assert cost.dummy_cost(100, fpr, 4096)[0] > m1
    assert cost.dummy_cost(0, fpr, 1024) == (0.0, 0.0)
    # measured here: 200 dummies of gre_small at 32x32 grew the process by 275 MB; the estimate is within 2x
    assert 0.5 * 275e6 < cost.dummy_cost(200, fpr, 1024)[0] < 2 * 275e6


def test_a_normal_simulation_is_not_refused(monkeypatch):
    monkeypatch.setattr(cost, "available_memory_bytes", lambda: 8 << 30)
    ir = load_sequence(GRE)
    text, sec = cost.check_simulation_cost(
        "x", 32 * 32, ir.n_adc_samples, n_runs=2, n_dummies=300, fine_per_rep=cost.fine_per_repetition(ir)
    )
    assert "300 dummies" in text and sec > 0


def test_a_dummy_train_beyond_memory_is_refused_without_simulating(capsys, tmp_path, monkeypatch):
    import dtoc.sim.comparison as comparison
    import dtoc.sim.pdg_dummies as pdg_dummies

    monkeypatch.setattr(cost, "available_memory_bytes", lambda: 1 << 30)  # a 1 GiB machine
    monkeypatch.setattr(pdg_dummies, "run_dummies", _no_work)
    monkeypatch.setattr(comparison, "compare_ideal_realized", _no_work)
    out = tmp_path / "s.json"
    code, _, err = run_cli(capsys, "simulate", GRE, "--dummies", "2000", "--json", out, "-q")
    lines = [x for x in err.splitlines() if x.startswith("dtoc: error")]
    assert code == 2 and len(lines) == 1, err
    assert "2000 dummies" in lines[0] and "estimate" in lines[0] and "fewer dummy repetitions (--dummies" in lines[0]
    assert not out.exists()
    # the same machine takes the default train (300 dummies of this GRE: ~0.5 GB): the work starts
    code, _, err = run_cli(capsys, "simulate", GRE, "--json", out, "-q")
    assert WORK in err and "needs about" not in err, err


def test_an_optimize_whose_image_term_cannot_fit_is_refused_with_its_dummies(capsys, tmp_path, monkeypatch):
    monkeypatch.setattr(cost, "available_memory_bytes", lambda: 1 << 30)
    cfg = tmp_path / "c.yaml"
    cfg.write_text("n_dummies: 5000\n")
    code, _, err = run_cli(
        capsys, "optimize", GRE, "--ideal", "--config", cfg, "-o", tmp_path / "o.seq", "--allow-worse", "-q"
    )
    assert code == 2 and "5000 dummies" in err and "n_dummies in --config" in err, err
    assert not (tmp_path / "o.seq").exists()


@pytest.fixture(scope="module")
def long_seq(tmp_path_factory):
    """A 5 s MPRAGE-like file (5 shots of 1 s): windowed by default."""
    from foreign.writers import mprage

    p = tmp_path_factory.mktemp("long") / "mprage5.seq"
    p.write_bytes(mprage(shots=5))
    return p


def _optimize_until_work(capsys, monkeypatch, argv):
    import dtoc.optimize.run as run

    monkeypatch.setattr(run, "quality", _no_work)  # the first evaluation of the base: the work starts there
    code, _, err = run_cli(capsys, *argv)
    return (None if WORK in err else code), err


def test_a_long_file_gets_the_estimate_line(capsys, tmp_path, monkeypatch, long_seq):
    monkeypatch.setattr(cost, "available_memory_bytes", lambda: 64 << 30)
    argv = ["optimize", long_seq, "--ideal", "--gmax", "32", "--smax", "130", "-o", tmp_path / "o.seq", "-q"]
    code, err = _optimize_until_work(capsys, monkeypatch, argv)
    assert code is None, err  # reached the work
    est = [x for x in err.splitlines() if "estimate (" in x]
    assert len(est) == 1, err
    # from the plan's window sizes: 161 windows (excitation periods), the largest window's free variables
    assert "windows of at most" in est[0] and "peak memory" in est[0] and "64 GiB available" in est[0]


def test_a_long_run_beyond_memory_is_refused_before_work(capsys, tmp_path, monkeypatch, long_seq):
    monkeypatch.setattr(cost, "available_memory_bytes", lambda: 1 << 30)
    out = tmp_path / "o.seq"
    argv = ["optimize", long_seq, "--ideal", "--gmax", "32", "--smax", "130", "-o", out, "-q"]
    code, err = _optimize_until_work(capsys, monkeypatch, argv)
    lines = [x for x in err.splitlines() if x.startswith("dtoc: error")]
    assert code == 2 and len(lines) == 1, err
    assert "estimate (" in lines[0] and "GiB peak memory" in lines[0] and "refused" in lines[0]
    assert not out.exists()


@pytest.mark.parametrize("solve", ["windowed", "whole"])
def test_a_long_run_beyond_memory_is_refused_before_the_projector_and_the_twin(
    capsys, tmp_path, monkeypatch, long_seq, solve
):
    """The cost decision needs sizes only (the IR, the free mask, the window plan): nothing of the run's setup
    (nominal k for the reachability check, projector, twin, loss context, phantoms, simulations) is built for a
    file that is refused (issue 36)."""
    import dtoc.optimize.loss as loss
    import dtoc.optimize.run as run
    import dtoc.optimize.windowed as windowed

    monkeypatch.setattr(cost, "available_memory_bytes", lambda: 1 << 30)
    for mod, name in ((run, "EdgeProjector"), (run, "EdgeTwin"), (loss, "build_context"), (run, "make_phantoms"),
                      (run, "Imager"), (run, "quality"), (run, "check_area_reachable")):  # fmt: skip
        monkeypatch.setattr(mod, name, _no_work)
    if solve == "whole":  # the Skope EPI's case: a period with more free variables than a dense window holds
        monkeypatch.setattr(windowed, "DENSE_MAX", 100)
    out = tmp_path / "o.seq"
    argv = ["optimize", long_seq, "--ideal", "--gmax", "32", "--smax", "130", "-o", out, "-q"]
    code, _, err = run_cli(capsys, *argv)
    lines = [x for x in err.splitlines() if x.startswith("dtoc: error")]
    assert WORK not in err and code == 2 and len(lines) == 1, err
    assert "estimate (" in lines[0] and "refused" in lines[0]
    if solve == "whole":
        assert "whole solve of" in lines[0] and "cannot be solved period by period: a single block has" in err
    else:
        assert "windows of at most" in lines[0]
    assert not out.exists()


class PreflightReached(Exception):
    pass


def _preflight_raises(*_a, **_k):
    raise PreflightReached("the output format's pre-flight ran")


@pytest.mark.parametrize("fits", [False, True])
def test_the_cost_refusal_comes_before_the_output_formats_preflight(capsys, tmp_path, monkeypatch, long_seq, fits):
    """The pre-flight (the base written in the output's format and read back: 15 of the 19 s the 187 s CEST
    protocol took to be refused) waits until the run is known to fit: a run refused by its estimate never reaches
    it; a run that fits reaches it before any of the run's work (issue 36 point 5)."""
    import dtoc.optimize.run as run

    monkeypatch.setattr(cost, "available_memory_bytes", lambda: (64 << 30) if fits else (1 << 30))
    monkeypatch.setattr(run, "preflight_write", _preflight_raises)
    out = tmp_path / "o.seq"
    argv = ["optimize", long_seq, "--ideal", "--gmax", "32", "--smax", "130", "-o", out, "-q"]
    code, err = _optimize_until_work(capsys, monkeypatch, argv)
    lines = [x for x in err.splitlines() if x.startswith("dtoc: error")]
    assert len(lines) == 1 and not out.exists(), err
    if fits:  # the pre-flight still runs, before the first evaluation of the base
        assert code == 3 and "the output format's pre-flight ran" in lines[0], err
    else:
        assert code == 2 and "estimate (" in lines[0] and "refused" in lines[0], err
        assert "pre-flight" not in err


def test_the_optimize_estimate_follows_the_window_sizes():
    whole = cost.optimize_cost(200_000, 1024)
    win = {"n_windows": 33, "max_free": 5700, "max_fine": 300_000}
    small = cost.optimize_cost(200_000, 1024, {**win, "max_free": 1000})
    big = cost.optimize_cost(200_000, 1024, win)
    assert big[0] > small[0] + 1e9  # the largest window's dense matrices
    assert cost.optimize_cost(2_000_000, 1024, win)[0] > big[0]  # the whole-sequence arrays
    # the longest window's own arrays: a minute-long excitation period (6 M fine samples) needs ~24 GB more
    long_period = cost.optimize_cost(200_000, 1024, {**win, "max_fine": 6_000_000})
    assert long_period[0] - big[0] == pytest.approx(cost.WINDOW_BYTES_PER_WINDOW_FINE * 5_700_000)
    assert long_period[0] > 2e10
    assert whole[2].startswith("whole solve") and "33 windows" in big[2]
    with pytest.raises(InputError, match="refused; the windowed solve holds less"):
        cost.check_optimize_cost("x", 10**9, 10**6, None)
    # a long sequence that cannot be windowed: the way out says why instead of offering the windowed solve
    with pytest.raises(InputError, match=r"refused; a shorter file \(it cannot be solved period by period: no exc\)$"):
        cost.check_optimize_cost("x", 10**9, 10**6, None, whole_why="no exc")


#: measured windowed runs (dtoc/util/cost.py, where each was run): fine samples, ADC samples, the most free
#: variables and fine samples of one window, CPU s (the time constants' fit)
MEASURED_WINDOWED_CPU = {
    "MPRAGE 5 min (bench.protocols mprage5)": (58_880_257, 5_767_168, 4806, 225_659, 1193),
    "MPRAGE 36.8 s (its 16-shot cut)": (7_360_001, 720_896, 4806, 225_659, 170),
    "bench.long 16 s": (3_151_361, 16_384, 3924, 160_681, 44),
    "bench.long 64 s": (12_605_441, 65_536, 3924, 160_681, 133),
}
#: the same for the memory constants' fit, after the windows' memory cut: ..., peak RSS (bytes)
MEASURED_WINDOWED_PEAK = {
    "MPRAGE 5 min (bench.protocols mprage5)": (58_880_257, 5_767_168, 4806, 225_659, 9.474e9),
    "MPRAGE 18.4 s (its 8-shot cut)": (3_680_017, 360_448, 4806, 225_659, 2.843e9),
    "MPRAGE 36.8 s (its 16-shot cut)": (7_360_033, 720_896, 4806, 225_659, 3.212e9),
    "bench.long 16 s": (3_151_361, 16_384, 3924, 160_681, 1.889e9),
    "bench.long 64 s": (12_605_441, 65_536, 3924, 160_681, 2.406e9),
    # ran past its wall limit in the export's read-back: its peak so far
    "3D FLASH 1 mm (bench.protocols gre3d_1mm)": (23_961_601, 4_718_592, 1608, 11_561, 5.866e9),
}


@pytest.mark.parametrize("name", list(MEASURED_WINDOWED_PEAK))
def test_the_windowed_estimate_is_within_its_stated_band_of_the_measured_runs(name):
    """The windowed estimate against the runs its constants were fitted to: never below the measured peak (it
    must not let through a run that does not fit) and at most 15 % above it (nor refuse one that fits: the 4.9 min
    MPRAGE, refused at 12 GiB where it peaked at 9.67 GB).  A 3D protocol's ADC samples count: without them the
    MPRAGE's estimate falls 3.4 GB short of its peak."""
    n, a, mf, mx, peak = MEASURED_WINDOWED_PEAK[name]
    mem, _, src = cost.optimize_cost(n, a, {"n_windows": 1, "max_free": mf, "max_fine": mx})
    assert peak <= mem <= 1.15 * peak, (name, mem / peak)
    assert f"{n} fine and {a} ADC samples" in src


@pytest.mark.parametrize("name", list(MEASURED_WINDOWED_CPU))
def test_the_windowed_time_estimate_is_within_its_band_of_the_measured_runs(name):
    """CPU within 15 % of the runs the time constants were fitted to."""
    n, a, mf, mx, cpu = MEASURED_WINDOWED_CPU[name]
    _, sec, _ = cost.optimize_cost(n, a, {"n_windows": 1, "max_free": mf, "max_fine": mx})
    assert abs(sec / cpu - 1) <= 0.15, (name, sec / cpu)


def test_what_the_process_already_holds_counts_as_memory_the_job_may_use(monkeypatch):
    """The estimate is of the whole process's peak, the read base included; MemAvailable no longer counts what
    the process holds when the estimate is made: the 4.9 min MPRAGE's 9.82 GiB, 13 GiB available and 4 GiB held fit
    (75 % of 17 GiB); with nothing held it is refused.  The process's own resident memory is read."""
    sizes = (58_880_257, 5_767_168, {"n_windows": 22529, "max_free": 4806, "max_fine": 225_659})  # the MPRAGE's
    assert cost.optimize_cost(*sizes)[0] == pytest.approx(9.82 * 2**30, rel=2e-3)
    monkeypatch.setattr(cost, "available_memory_bytes", lambda: 13 << 30)
    monkeypatch.setattr(cost, "held_bytes", lambda: 4 << 30)
    cost.check_optimize_cost("x", *sizes)
    monkeypatch.setattr(cost, "held_bytes", lambda: 0)
    with pytest.raises(InputError, match=r"more than 75% of the 13 GiB available here: refused"):
        cost.check_optimize_cost("x", *sizes)
    # an estimate of what a job adds (a simulation's) is not credited with what the process holds
    monkeypatch.setattr(cost, "held_bytes", lambda: 4 << 30)
    with pytest.raises(InputError, match=r"more than 75% of the 13 GiB available here: refused"):
        cost.check_fits("x", 9.82 * 2**30)
    monkeypatch.undo()
    assert cost.held_bytes() > 50 << 20  # this test process (Python, numpy, dtoc): tens of MB at least


def test_the_fit_fraction_is_read_when_the_check_runs(monkeypatch):
    """``cost.FIT_FRACTION`` set at runtime counts (it was bound when ``check_fits`` was defined)."""
    cost.check_fits("x", 0.6e9, avail=1e9)  # 60 % of the available memory: within 75 %
    monkeypatch.setattr(cost, "FIT_FRACTION", 0.5)
    with pytest.raises(InputError, match=r"more than 50% of the .* available here: refused"):
        cost.check_fits("x", 0.6e9, avail=1e9)
    cost.check_fits("x", 0.6e9, fraction=0.7, avail=1e9)  # an explicit fraction still wins


def test_the_readers_guard_refuses_by_the_load_estimate(monkeypatch):
    """One estimate of the read: the reader's size guard (dtoc.seq.seqtext) refuses exactly where
    ``cost.load_bytes`` of the file's raster steps and ADC samples exceeds three quarters of the memory (its
    ``max_file_bytes`` x 30), in one line that says it is an estimate of the read."""
    import dtoc.seq.seqtext as seqtext

    ir = load_sequence(GRE)
    need = cost.load_bytes(round(ir.duration_s / ir.raster_s), ir.n_adc_samples)
    assert need > cost.LOAD_BYTES
    monkeypatch.setattr(seqtext, "max_file_bytes", lambda: int(need * 1.001 / 30))
    load_sequence(GRE)  # within the budget: read
    monkeypatch.setattr(seqtext, "max_file_bytes", lambda: int(need * 0.999 / 30))
    with pytest.raises(InputError, match=r"ADC samples need ~.* GB to be read \(estimate\); this machine allows"):
        load_sequence(GRE)


#: measured reads (dtoc.seq.load.load_sequence alone, a process's peak RSS; dtoc/util/cost.py says where): gradient
#: raster steps, ADC samples, peak RSS (bytes)
MEASURED_LOADS = {
    "3D FLASH 1 mm, 24 partitions": (2_995_200, 1_179_648, 0.8648e9),
    "3D FLASH 1 mm, 96 partitions (bench.protocols gre3d_1mm)": (11_980_800, 4_718_592, 1.6667e9),
    "MPRAGE 16 shots": (3_680_016, 720_896, 0.7714e9),
    "MPRAGE 128 shots (mprage5)": (29_440_128, 5_767_168, 2.6811e9),
    "MPRAGE 256 shots (mprage10)": (58_880_256, 11_534_336, 4.8597e9),
}


@pytest.mark.parametrize("name", list(MEASURED_LOADS))
def test_the_load_estimate_is_within_its_band_of_the_measured_reads(name):
    """Never below the measured peak of the read (the guard must not let through a file that cannot be read) and
    at most 15 % above it (nor refuse one that can: the 9.8 min MPRAGE, refused at 35.7 GB)."""
    n, a, peak = MEASURED_LOADS[name]
    assert peak <= cost.load_bytes(n, a) <= 1.15 * peak, (name, cost.load_bytes(n, a) / peak)


def test_the_runs_estimate_includes_the_read():
    """The optimization's estimate is of the whole process: never below the read of the same base."""
    for n_fine, n_adc in ((23_961_601, 4_718_592), (117_760_513, 11_534_336), (200_000, 1024)):
        win = {"n_windows": 1, "max_free": 100, "max_fine": 1000}
        assert cost.optimize_cost(n_fine, n_adc, win)[0] >= cost.load_bytes(n_fine // 2, n_adc)
        assert cost.optimize_cost(n_fine, n_adc)[0] >= cost.load_bytes(n_fine // 2, n_adc)
