"""Long sequences: time and peak memory of `dtoc optimize` against the sequence's duration.

Run: ``python -m bench.long [--durations 1 4 16 ...] [--whole-up-to S]`` (writes its section of
docs/benchmarks.md).  The sequence: the corpus's 3D MPRAGE-like writer (tests/foreign/writers.py, 32 GRE
readouts per 1 s shot, one shot per second of sequence); the hardware: the KCL 7 T 2024 GIRF from
``../shared/data`` (a self-made exponential model when absent); limits 32 mT/m, 130 T/m/s.  Each run is
its own process (``python -m dtoc optimize``), its peak RSS read from ``wait4``; the windowed solve
(``windowed: on``) and, up to ``--whole-up-to`` seconds, the whole-sequence solve (``windowed: off``) side
by side, with the k error of each output (re-read, played through the model) and the difference between
the two.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
from pathlib import Path

from bench._proc import run_step

REPO = Path(__file__).resolve().parents[1]


def _run(argv: list[str]) -> tuple[float, float, float, int]:
    """(wall s, CPU s, peak RSS GB, exit code) of one ``python -m dtoc`` process (no time limit)."""
    r = run_step([sys.executable, "-m", "dtoc", *argv], math.inf)
    if r["rc"]:
        sys.stderr.write(r["err"][-2000:])
    return r["wall_s"], r["cpu_s"], r["peak_mb"] * 1024 / 1e6, r["rc"]


def _k_err_dk(seq: Path, base: Path, girf: Path | None) -> float:
    import numpy as np
    import torch

    from dtoc.hardware.model import resolve_model
    from dtoc.seq.load import load_sequence

    ir = load_sequence(base)
    o = load_sequence(seq)
    hw = resolve_model(girf=girf).frozen() if girf is not None else _model()
    with torch.no_grad():
        G = hw(torch.as_tensor(o.grad_mT_per_m)[None], o.dt_fine_s)[0][0]
        k = ir.kspace_rad_per_m(G).numpy()
    dk = 2 * np.pi / 0.22
    return float(np.abs(k[:2] - ir.nominal_kspace_rad_per_m()[:2]).max() / dk)  # readout and phase axes


def _model():
    from dtoc.hardware.effects import Delay, ExpEddy
    from dtoc.hardware.model import HardwareModel

    return HardwareModel([ExpEddy(0.01, 2e-3), Delay(4e-6)]).frozen()


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--durations", type=float, nargs="+", default=[1, 4, 16, 64, 300])
    ap.add_argument("--whole-up-to", type=float, default=4.0)
    ap.add_argument("--no-write", action="store_true")
    ap.add_argument("--horizons", type=float, nargs="*", default=None, help="instead: the error of a capped horizon, s")
    ap.add_argument("--horizon-duration", type=float, default=4.0)
    a = ap.parse_args(argv)
    if a.horizons:
        return horizons(a.horizons, a.horizon_duration, a.no_write)
    sys.path.insert(0, str(REPO))
    from bench.foreign import corpus_girf
    from tests.foreign.writers import mprage

    rows = []
    with tempfile.TemporaryDirectory() as td:
        d = Path(td)
        girf = corpus_girf(d, None)
        model_args = ["--girf", str(girf)] if girf is not None else None
        if model_args is None:
            from dtoc.hardware.model import save_model

            save_model(_model(), d / "model.json")
            model_args = ["--model", str(d / "model.json")]
        for mode in ("on", "off"):
            (d / f"{mode}.yaml").write_text(f'windowed: "{mode}"\n')
        for dur in a.durations:
            base = d / f"mprage_{dur:g}.seq"
            base.write_bytes(mprage(shots=int(round(dur))))
            row = {"duration_s": dur}
            for mode in ("on", "off"):
                if mode == "off" and dur > a.whole_up_to:
                    continue
                out = d / f"out_{mode}_{dur:g}.seq"
                man = d / f"out_{mode}_{dur:g}.json"
                argv = ["optimize", str(base), *model_args, "--gmax", "32", "--smax", "130", "-o", str(out)]
                argv += ["--json", str(man), "--config", str(d / f"{mode}.yaml"), "--force"]
                wall, cpu, rss, code = _run(argv)
                row[mode] = {"wall_s": wall, "cpu_s": cpu, "rss_gb": rss, "code": code}
                if code == 0:
                    m = json.loads(man.read_text())
                    row[mode]["k_after_dk"] = _k_err_dk(out, base, girf)
                    row[mode]["k_before_dk"] = m["before"]["kspace_max_error_dk"]
                    row[mode]["windowed"] = m.get("windowed")
                    row[mode]["n_free"] = m["sequence"]["n_free_variables"]
                    row[mode]["n_adc"] = m["sequence"]["n_adc_samples"]
                print(json.dumps(row), flush=True)
            rows.append(row)
    text = render(rows, "KCL 7 T Terra 2024 3x3 GIRF" if girf is not None else "exp_eddy 1 % / 2 ms + 4 us delay")
    print(text)
    if not a.no_write:
        from bench._report import write_section

        write_section("long", "Long sequences: windowed optimize vs duration", text, "python -m bench.long")


def horizons(caps: list[float], duration: float, no_write: bool) -> None:
    """k error of the windowed solve when its history/lookahead is capped below the hardware's memory."""
    sys.path.insert(0, str(REPO))
    from bench.foreign import corpus_girf
    from tests.foreign.writers import mprage

    rows = []
    with tempfile.TemporaryDirectory() as td:
        d = Path(td)
        girf = corpus_girf(d, None)
        if girf is None:
            raise SystemExit("the KCL 2024 GIRF is absent (../shared/data)")
        base = d / "mprage.seq"
        base.write_bytes(mprage(shots=int(round(duration))))
        for cap in caps:
            cfg = d / f"h{cap:g}.yaml"
            cfg.write_text(f'windowed: "on"\nwindow_horizon_max_s: {cap!r}\n')
            out, man = d / f"h{cap:g}.seq", d / f"h{cap:g}.json"
            argv = ["optimize", str(base), "--girf", str(girf), "--gmax", "32", "--smax", "130", "-o", str(out)]
            wall, cpu, rss, code = _run(argv + ["--json", str(man), "--config", str(cfg), "--force"])
            m = json.loads(man.read_text())
            rows.append(
                {"cap_s": cap, "horizon_s": m["windowed"]["horizon_s"], "lookahead_s": m["windowed"]["lookahead_s"],
                 "memory_s": m["windowed"]["memory_s"], "wall_s": wall, "k_after_dk": _k_err_dk(out, base, girf)}
            )  # fmt: skip
            print(json.dumps(rows[-1]), flush=True)
    mem = rows[0]["memory_s"]
    text = (
        f"The same MPRAGE-like sequence ({duration:g} s), KCL GIRF (memory {mem[0] * 1e3:.3g} ms causal / "
        f"{mem[1] * 1e3:.3g} ms acausal), windowed with history and lookahead capped at "
        "`window_horizon_max_s`; k after: the output played through the whole model (all taps), as above.\n\n"
        "| cap (ms) | history (ms) | lookahead (ms) | k after (dk) | wall (s) |\n|---|---|---|---|---|\n"
        + "\n".join(
            f"| {r['cap_s'] * 1e3:g} | {r['horizon_s'] * 1e3:.3g} | {r['lookahead_s'] * 1e3:.3g} | "
            f"{r['k_after_dk']:.3g} | {r['wall_s']:.1f} |"
            for r in rows
        )
        + "\n"
    )
    print(text)
    if not no_write:
        from bench._report import write_section

        write_section(
            "long_horizon", "Long sequences: the error of the horizon", text, "python -m bench.long --horizons ..."
        )


def render(rows: list[dict], hw: str) -> str:
    head = (
        f"3D MPRAGE-like (tests/foreign/writers.py `mprage`, 1 s shots of 32 readouts), hardware {hw}, "
        "--gmax 32 --smax 130. One process per run; peak RSS from wait4. k after: max over ADC samples of the "
        "readout/phase k error of the re-read output played through the model, in dk = 2 pi / 0.22 m.\n\n"
        "| duration (s) | ADC samples | free variables | solve | wall (s) | CPU (s) | peak RSS (GB) | k before (dk) | "
        "k after (dk) | windows (solved directly) | structures | Jacobians (s) | window solves (s) |\n"
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|\n"
    )
    lines = []
    for r in rows:
        for mode, name in (("on", "windowed"), ("off", "whole")):
            x = r.get(mode)
            if x is None:
                continue
            if x["code"] != 0:
                lines.append(
                    f"| {r['duration_s']:g} | | | {name} | failed (exit {x['code']}) | | {x['rss_gb']:.2f} | | | | | | |"
                )
                continue
            w = x.get("windowed") or {}
            t = w.get("times_s", {})
            nw = f"{w['windows']} ({w['windows_solved_directly']})" if w else "-"
            lines.append(
                f"| {r['duration_s']:g} | {x['n_adc']} | {x['n_free']} | {name} | {x['wall_s']:.1f} | {x['cpu_s']:.1f} | "
                f"{x['rss_gb']:.2f} | {x['k_before_dk']:.3g} | {x['k_after_dk']:.3g} | {nw} | "
                f"{w.get('distinct_structures', '-')} | {t.get('jacobian', '-')} | {t.get('solve', '-')} |"
            )
    return head + "\n".join(lines) + "\n" + _ratios(rows)


def _ratios(rows: list[dict]) -> str:
    """Side-by-side ratios: whole / windowed wall time per duration, and each solve's growth between durations."""
    ok = [r for r in rows if r.get("on", {}).get("code") == 0]
    vs = [
        f"{r['off']['wall_s'] / r['on']['wall_s']:.1f}x at {r['duration_s']:g} s"
        for r in ok
        if r.get("off", {}).get("code") == 0
    ]
    out = []
    if vs:
        out.append("Whole / windowed wall time: " + ", ".join(vs) + ".")
    for mode, name in (("on", "windowed"), ("off", "whole")):
        rr = [r for r in rows if r.get(mode, {}).get("code") == 0]
        g = [
            f"{b['duration_s'] / a['duration_s']:g}x duration -> {b[mode]['wall_s'] / a[mode]['wall_s']:.2f}x wall, "
            f"{b[mode]['rss_gb'] / a[mode]['rss_gb']:.2f}x peak RSS ({a['duration_s']:g} -> {b['duration_s']:g} s)"
            for a, b in zip(rr[:-1], rr[1:])
        ]
        if g:
            out.append(f"{name.capitalize()} growth: " + "; ".join(g) + ".")
        m = [
            f"{(b[mode]['wall_s'] - a[mode]['wall_s']) / (b['duration_s'] - a['duration_s']):.2f} s and "
            f"{(b[mode]['rss_gb'] - a[mode]['rss_gb']) / (b['duration_s'] - a['duration_s']) * 1e3:.0f} MB "
            f"({a['duration_s']:g} -> {b['duration_s']:g} s)"
            for a, b in zip(rr[:-1], rr[1:])
        ]
        if m and mode == "on":  # the marginal cost, free of the one-off structure factorisations
            out.append("Windowed, per second of sequence (wall, peak RSS): " + "; ".join(m) + ".")
    return ("\n" + "\n\n".join(out) + "\n") if out else ""


if __name__ == "__main__":
    main()
