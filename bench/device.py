"""The same jobs on the CPU and on CUDA in one process: time, dispatched operations, equality of results.

    python -m bench.device                  # every job, cpu and (where present) cuda; updates docs/benchmarks.md
    python -m bench.device --quick          # short settings (fewer iterations, fewer dummies) for a smoke run
    python -m bench.device --jobs sim       # only the simulator cases (bench.sim's cases, fwd + bwd)
    python -m bench.device --no-write       # print the table only

Jobs (issue 33): the README job (optimize EPI 64, example 7 T GIRF, B0 7 T); optimize the Figure-5 GRE
at gmax 10 mT/m with the paper's eddy model; optimize EPI 256 (echo spacing 3.0 ms, example GIRF);
simulate the paper's GRE with 300 dummies on a 128x128 phantom; and one forward + backward of every
``bench.sim.run`` case (default simulator settings).  Per job and device: wall time, the number of aten
operations dispatched (counted in a separate run under a ``TorchDispatchMode``: per optimizer iteration
for the optimize jobs = the whole run's count over its iterations, per call for the simulator jobs), and
the result (NRMSE or signal) compared between the devices.  Where CUDA is absent its columns say "not
measured": no projected figure is ever written as measured.  One prepared script, so that a short time
on a GPU machine is enough: ``python -m bench.device --quick`` takes a few minutes on one GPU.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import torch
from torch.utils._python_dispatch import TorchDispatchMode

REPO = Path(__file__).resolve().parents[1]
SECTION = "device"


class _Count(TorchDispatchMode):
    def __init__(self):
        super().__init__()
        self.n = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        self.n += 1
        return func(*args, **(kwargs or {}))


def _sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def _optimize_job(base, quick: bool, *, girf=None, model=None, overrides=None, b0=None):
    def run(device: str, tmp: Path) -> dict:
        import dtoc
        from dtoc.optimize.config import load_config
        from dtoc.seq.load import load_sequence

        ir = load_sequence(base if not isinstance(base, str) else REPO / base)
        ov = dict(overrides or {})
        if quick:
            ov.update(iters=min(ov.get("iters", 4), 4), warm_iters=min(ov.get("warm_iters", 100), 100))
        if b0 is not None:
            ov["b0_T"] = b0
        kind = "epi" if "epi" in str(getattr(ir, "name", "") or base).lower() else "gre"
        cfg = load_config(kind, None, ov)
        res = dtoc.optimize_sequence(
            ir,
            girf=None if girf is None else REPO / girf,
            model=None if model is None else REPO / model,
            out=tmp / f"{device}.seq",
            config=cfg,
            force=True,
            device=device,
        )
        m = res.manifest
        # warm_iters None (the default): the warm start is solved to a tolerance; its evaluations are in the manifest
        warm = cfg.warm_iters if cfg.warm_iters is not None else (m.get("solver") or {}).get("evaluations", 0)
        iters = max(1, int(cfg.iters or 0) + int(warm or 0))
        return {"result": m["after"].get("nrmse_percent"), "iterations": iters}

    return run


def _simulate_gre_dummies(quick: bool):
    def run(device: str, tmp: Path) -> dict:
        import dtoc

        res = dtoc.simulate(
            REPO / "sequences" / "gre_paper.yaml", phantom="brain:128", n_dummies=30 if quick else 300, device=device
        )
        return {"result": res.metrics.get("nrmse_percent"), "iterations": 1}

    return run


def _sim_case(case: str):
    def run(device: str, tmp: Path) -> dict:
        from bench.sim.run import CASES
        from dtoc.seq.load import load_sequence
        from dtoc.seq.spec import load_spec, parse_spec
        from dtoc.sim import pdg
        from dtoc.sim.phantom import brain_phantom

        spec, n, fov = CASES[case][:3]
        sp = load_spec(REPO / "sequences" / spec) if isinstance(spec, str) else parse_spec(dict(spec))
        ir = load_sequence(sp)
        ph = brain_phantom(n, field_T=3.0, fov_m=fov)
        graph = pdg.build_graph(ir, pdg.PDGConfig(), ph)
        g = torch.tensor(ir.grad_mT_per_m, dtype=torch.float64, device=device, requires_grad=True)
        s = pdg.simulate(ir, ph, g, graph=graph, device=device)
        (s.real**2 + s.imag**2).sum().backward()
        _sync(device)
        return {"result": s.detach().cpu(), "iterations": 1}

    return run


def jobs(quick: bool) -> dict[str, tuple[str, Any]]:
    from bench.sim.run import CASES, LABELS

    out: dict[str, tuple[str, Any]] = {
        "readme": (
            "README job: optimize EPI 64 (esp 0.81 ms), example 7 T GIRF, B0 7 T",
            _optimize_job("sequences/epi_esp081.seq", quick, girf="girf/example_7T.npz", b0=7.0),
        ),
        "gre_fig5": (
            "optimize Fig-5 GRE, gmax 10 mT/m, paper eddy model",
            _optimize_job(
                "sequences/gre_paper_fig5.yaml",
                quick,
                model="girf/paper_eddy_both.json",
                overrides={"gmax_mT_per_m": 10.0},
            ),
        ),
        "epi256": (
            "optimize EPI 256 (echo spacing 3.0 ms), example GIRF",
            _optimize_job(_epi256_spec(), quick, girf="girf/example_7T.npz", b0=7.0),
        ),
        "gre_dummies": (
            f"simulate GRE paper, {30 if quick else 300} dummies, 128x128 phantom",
            _simulate_gre_dummies(quick),
        ),
    }
    for case in CASES:
        if quick and case in ("gre_100us_p256", "epi128_10us_p256"):
            continue
        out["sim:" + case] = (f"sim fwd+bwd: {LABELS[case]}", _sim_case(case))
    return out


def _epi256_spec():
    from dtoc.seq.spec import parse_spec

    return parse_spec(
        {"kind": "epi", "name": "epi256", "matrix": 256, "fov_mm": 250, "dwell_us": 10, "echo_spacing_ms": 3.0}
    )


def measure(fn, device: str, tmp: Path, count: bool, second: bool = False) -> dict:
    from dtoc.util.replay import totals

    torch.manual_seed(0)
    _sync(device)
    before = totals()["replays"]
    t0 = time.perf_counter()
    r = fn(device, tmp)
    _sync(device)
    r["time_s"] = time.perf_counter() - t0
    r["replays"] = totals()["replays"] - before
    if second:  # the same job again in this process: what a batch of jobs costs each after the first
        t0 = time.perf_counter()
        fn(device, tmp)
        _sync(device)
        r["time2_s"] = time.perf_counter() - t0
    if count:
        with _Count() as c:
            fn(device, tmp)
        r["ops"] = c.n / max(1, r["iterations"])
    return r


def _same(a, b) -> str:
    if a is None or b is None:
        return "-"
    if isinstance(a, torch.Tensor):
        d = float((a - b).abs().max() / b.abs().max().clamp_min(1e-300))
        return f"max rel diff {d:.1e}"
    return f"{a:.3f} vs {b:.3f}" if isinstance(a, float) else f"{a} vs {b}"


def _fmt(v, unit: str = "") -> str:
    if v is None:
        return "not measured"
    return f"{v:.1f}{unit}" if isinstance(v, float) else f"{v}{unit}"


def run(
    selected: list[str] | None, quick: bool, count: bool, devices: list[str], save: str = "", second: bool = False
) -> list[dict]:
    rows = []
    allj = jobs(quick)
    for key, (label, fn) in allj.items():
        if selected and not any(key == s or key.startswith(s) for s in selected):
            continue
        row: dict[str, Any] = {"job": key, "label": label}
        for dev in devices:
            with tempfile.TemporaryDirectory() as td:
                try:
                    row[dev] = measure(fn, dev, Path(td), count, second and dev.startswith("cuda"))
                except Exception as e:  # one failing job must not lose the others' figures
                    row[dev] = {"error": f"{type(e).__name__}: {e}"[:200]}
        print(
            json.dumps(
                {
                    k: (v if not isinstance(v, dict) else {kk: vv for kk, vv in v.items() if kk != "result"})
                    for k, v in row.items()
                }
            ),
            flush=True,
        )
        rows.append(row)
        if save:  # after every job: a process stopped at its time limit keeps the jobs it finished
            torch.save(rows, save)
    return rows


def table(rows: list[dict], devices: list[str], quick: bool, merged: bool = False) -> str:
    cuda = torch.cuda.is_available()
    name = torch.cuda.get_device_name(0) if cuda else "none"
    lines = [
        f"CUDA device: {name}{' (none on this machine: its columns say not measured)' if not cuda else ''}; "
        f"{'short settings (--quick: 4 full-loss and 100 warm-start iterations, 30 dummies); ' if quick else ''}"
        f"{'each job and device in its own process, side by side on this machine' if merged else 'both devices in one process'}, the same job each.  'ops' = aten operations dispatched, counted in a "
        "second run under a TorchDispatchMode (optimize jobs: the whole run's count over its warm-start + "
        "full-loss iterations; simulator jobs: per call).  'CUDA s': the job's first run in its process (after a "
        "small FFT and matmul made the CUDA context, not timed); '2nd run': the same job again in the same "
        "process (with --second; what each job after the first of a batch costs); 'steps replayed': calls of the "
        "warm start's steps that ran as one CUDA graph each (dtoc.util.replay).  Times on a shared machine are noisy.",
        "",
        "| job | CPU s | CUDA s | CUDA / CPU | CUDA s, 2nd run | steps replayed as CUDA graphs | CPU ops | CUDA ops | results (CUDA vs CPU) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        c = r.get("cpu", {})
        g = r.get("cuda") if "cuda" in devices else None
        ct = c.get("time_s")
        gt = g.get("time_s") if g else None
        ratio = f"{gt / ct:.2f}" if (ct and gt) else "not measured"
        err = c.get("error") or (g or {}).get("error")
        res = err or (_same(g.get("result"), c.get("result")) if g else "not measured")
        cres = c.get("result")
        if g is None and not isinstance(cres, torch.Tensor) and cres is not None:
            res = f"CPU {cres:.3f} %; CUDA not measured"
        g2 = g.get("time2_s") if g else None
        lines.append(
            f"| {r['label']} | {_fmt(ct)} | {_fmt(gt)} | {ratio} | {_fmt(g2) if g2 is not None else '-'} | "
            f"{g.get('replays', '-') if g else 'not measured'} | {_fmt(c.get('ops'))} | "
            f"{_fmt(g.get('ops') if g else None)} | {res} |"
        )
    return "\n".join(lines) + "\n"


def _gre_spec(name: str, n: int):
    from dtoc.seq.spec import load_spec

    return load_spec(REPO / "sequences" / name).model_copy(
        update=dict(matrix=n, repetitions=n, dwell_us=3200.0 / n, te_ms=3.5)
    )


@contextmanager
def _gpu_schedule():
    """The GPU's schedule (fused propagation, batched signal products, the twin's recursion by FFT) selected
    on any device: every ``PDGConfig`` made inside takes it (what ``schedule='auto'`` does off the CPU), and
    :func:`dtoc.hardware.recursion.batched`."""
    from dtoc.hardware import recursion
    from dtoc.sim.pdg_config import PDGConfig

    old, old_rec = PDGConfig.batched, recursion.batched
    PDGConfig.batched = lambda self, device: True
    recursion.batched = lambda device: True
    try:
        yield
    finally:
        PDGConfig.batched, recursion.batched = old, old_rec


def op_counts(device: str, sizes=(16, 32, 64)) -> list[tuple[int, int, int, int]]:
    """(TRs, operations of one ``dtoc.simulate`` of the paper GRE without dummies with the CPU's schedule,
    the same with the GPU's schedule, operations of one full-loss iteration (forward + backward) of the
    Figure-5 GRE with the paper's eddy model and the GPU's schedule) at matrix = repetitions = n
    (tests/test_sim_op_count.py)."""
    import dtoc
    from dtoc.optimize import loss as L
    from dtoc.optimize import optimizer as O
    from dtoc.optimize.config import OptimizeConfig
    from dtoc.optimize.limits import EdgeProjector, Limits
    from dtoc.optimize.run import free_edges, make_phantoms
    from dtoc.optimize.twin import EdgeTwin
    from dtoc.sim.imager import Imager
    from dtoc.sim.pdg import PDGConfig

    out = []
    for n in sizes:
        ir = dtoc.load_sequence(_gre_spec("gre_paper.yaml", n))
        with _Count() as c:
            dtoc.simulate(ir, n_dummies=0, device=device)
        n_cpu = c.n
        with _gpu_schedule():
            with _Count() as c:
                dtoc.simulate(ir, n_dummies=0, device=device)
            n_gpu = c.n
            ir = dtoc.load_sequence(_gre_spec("gre_paper_fig5.yaml", n))
            cfg = OptimizeConfig(n_dummies=0)
            lim = Limits(50.0, 500.0)
            P = EdgeProjector(ir.edge_grad_mT_per_m, free_edges(ir), ir.raster_s, lim)
            model = dtoc.load_model(model=REPO / "girf" / "paper_eddy_both.json")
            tw = EdgeTwin(ir, model, P, device=device)
            ctx = L.build_context(ir, lim, device=device)
            im = Imager(
                ir, make_phantoms(ir, cfg), n_dummies=0, device=device, config=PDGConfig.fast(), dtype=torch.float32
            )
            x = torch.as_tensor(ir.edge_grad_mT_per_m, dtype=torch.float64, device=device).clone().requires_grad_(True)
            w = O.full_weights(cfg)
            O.evaluate(tw, im, ctx, w, x, 0)  # caches warm outside the count
            with _Count() as c:
                total, _, _ = O.evaluate(tw, im, ctx, w, x, 0)
                total.backward()
        out.append((n, n_cpu, n_gpu, c.n))
    return out


def op_table(counts: list[tuple[int, int, int, int]]) -> str:
    lines = [
        "",
        "Operation count (aten operations dispatched, counted on the CPU under a TorchDispatchMode; paper GRE spec "
        "at matrix = repetitions = n, readout 3.2 ms, TE 3.5 ms; no dummy cycles).  'CPU schedule': the public "
        "`dtoc.simulate` with the CPU's default ('per_interval'); 'GPU schedule': the same call with the schedule "
        "that `PDGConfig(schedule='auto')` takes off the CPU ('batched'), selected explicitly.  'iteration': one "
        "full-loss forward + loss + backward of the Figure-5 GRE (fast preset, float32, GPU schedule, paper eddy "
        "model).  Issue 33's bound: at 64 TRs at most 3x the count at 16 and at most 50 per TR.",
        "",
        "| TRs | dtoc.simulate, CPU schedule | dtoc.simulate, GPU schedule | per TR | iteration, GPU schedule | per TR |",
        "|---|---|---|---|---|---|",
    ]
    for n, a, g, b in counts:
        lines.append(f"| {n} | {a} | {g} | {g / n:.0f} | {b} | {b / n:.0f} |")
    return "\n".join(lines) + "\n"


def write_section(text: str, quick: bool) -> None:
    from bench._report import write_section as _write

    _write(
        SECTION, "CPU and CUDA in one process (issue 33)", text, f"python -m bench.device{' --quick' if quick else ''}"
    )


def _load_rows(paths: list[str]) -> list[dict]:
    """Rows saved by ``--save-rows`` in several processes, merged per job (first-seen job order)."""
    merged: dict[str, dict] = {}
    for p in paths:
        for r in torch.load(p, weights_only=False):
            merged.setdefault(r["job"], {"job": r["job"], "label": r["label"]}).update(
                {k: v for k, v in r.items() if k not in ("job", "label")}
            )
    return list(merged.values())


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="short settings (smoke run)")
    ap.add_argument(
        "--jobs", default="", help="comma-separated job keys or prefixes (readme, gre_fig5, epi256, gre_dummies, sim)"
    )
    ap.add_argument("--no-count", action="store_true", help="skip the operation count (one run per job and device)")
    ap.add_argument("--second", action="store_true", help="on CUDA, time each job a second time in the same process")
    ap.add_argument("--no-write", action="store_true", help="print only; do not update docs/benchmarks.md")
    ap.add_argument("--ops-only", action="store_true", help="only the operation-count table (printed, not written)")
    ap.add_argument(
        "--devices", default="", help="comma-separated devices to run (default: cpu, and cuda where present)"
    )
    ap.add_argument(
        "--save-rows", default="", help="save this process's rows (torch.save) for --merge; no table is written"
    )
    ap.add_argument(
        "--merge",
        nargs="+",
        default=None,
        help="build the table from rows saved by several processes (each job on each device in its own process, "
        "one torch thread each, run side by side on one machine) instead of running jobs",
    )
    a = ap.parse_args(argv)
    torch.set_num_threads(1)
    if a.ops_only:
        print(op_table(op_counts("cpu")))
        return 0
    if a.merge:
        rows = _load_rows([p for p in a.merge if Path(p).exists()])
        devices = ["cpu"] + (["cuda"] if any("cuda" in r for r in rows) else [])
    else:
        devices = [d for d in a.devices.split(",") if d] or (["cpu"] + (["cuda"] if torch.cuda.is_available() else []))
        for d in devices:  # the CUDA context and its libraries made before the first timed job (not timed)
            if d.startswith("cuda"):
                z = torch.randn(64, 64, device=d, dtype=torch.complex64)
                (torch.fft.fft(z) @ z).abs().sum().item()
        rows = run([s for s in a.jobs.split(",") if s] or None, a.quick, not a.no_count, devices, a.save_rows, a.second)
        if a.save_rows:
            return 0
    text = table(rows, devices + ([] if "cuda" in devices else ["cuda-absent"]), a.quick, merged=bool(a.merge))
    if not a.no_count:
        text += op_table(op_counts("cpu"))
    print(text)
    if not a.no_write:
        write_section(text, a.quick)
    return 0


if __name__ == "__main__":
    sys.exit(main())
