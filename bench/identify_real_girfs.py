"""`dtoc identify` where the undeclared part is a REAL gradient response (measured GIRFs of real scanners).

    python -m bench.identify_real_girfs [--write-docs]

Not field-camera measurements (none can be fetched here): the "true scanner" is a measured GIRF from
``../shared/data/girf`` played on random probe waveforms (8 x 3 x 5000 samples of 10 us, 30 mT/m,
150 T/m/s) with white noise 0.02 mT/m (not given to identify); the declared model is ideal hardware or an
older measurement of the same scanner.  What the real responses contain (group delays, low-pass edges,
cross terms, ripples) is what identify must describe with physically plausible effects, never making the
held-out error worse and naming what it cannot model.

Cases:
- ``ideal_vs_kcl2024``: declared ideal, truth = KCL 7 T Terra GIRF 2024 (``7T_GIRF.mat``);
- ``kcl2023_vs_kcl2024``: declared = the same scanner's 2023 GIRF (``7T_1pcterms.mat``; it has x and y only,
  z is declared ideal), truth = 2024: a real re-measurement / drift between two years;
- ``ideal_vs_prisma``: declared ideal, truth = Siemens Prisma 3 T GIRF 2020 (``GIRF_X/Y/Z.mat``).

``--write-docs`` writes the section ``identify_real_girfs`` of docs/identify.md.  Skips (exit 0, one line) when
``../shared/data`` is absent.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch

from dtoc.hardware.girf_import import import_girf
from dtoc.hardware.model import HardwareModel, girf_effect
from dtoc.identify import adopt
from dtoc.identify.search import identify
from dtoc.identify.synth import probe_waveforms, simulate_measurement

DT = 10e-6
SIGMA = 0.02
DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "girf"


def _girf(*rel: str, partial: bool = False) -> HardwareModel:
    return HardwareModel([girf_effect(import_girf([DATA / r for r in rel], allow_partial=partial))])


def cases() -> list[tuple[str, str, HardwareModel, HardwareModel]]:
    kcl24 = _girf("kcl_7T_terra_2024/7T_GIRF.mat")
    kcl23 = _girf("kcl_7T_terra_2023/7T_1pcterms.mat", partial=True)  # x and y only: z declared ideal
    prisma = _girf(*(f"siemens_prisma_3T_2020/GIRF_{a}.mat" for a in "XYZ"))
    ideal = HardwareModel([])
    return [
        ("ideal_vs_kcl2024", "ideal hardware declared; truth KCL 7 T Terra 2024 GIRF", ideal, kcl24),
        (
            "kcl2023_vs_kcl2024",
            "KCL 2023 GIRF declared (x, y measured; z ideal); truth the same scanner's 2024 GIRF",
            kcl23,
            kcl24,
        ),
        ("ideal_vs_prisma", "ideal hardware declared; truth Siemens Prisma 3 T 2020 GIRF", ideal, prisma),
    ]


def main(argv=None) -> None:
    from bench._report import DOC, write_section
    from bench.identify_corpus import fmt_found

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--write-docs", action="store_true")
    a = ap.parse_args(argv)
    if not DATA.is_dir():
        print(f"skipped: {DATA} not found")
        return
    torch.set_num_threads(1)
    g = probe_waveforms(8, 5000, DT, seed=7)
    rows = [
        "| case | adopted effects (± stderr) | not adopted | held-out G / noise: declared -> updated | every "
        "adopted parameter physical and identified | explained | notes | s |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, what, declared, truth in cases():
        data = simulate_measurement(truth, g, DT, sigma_G=SIGMA, seed=3)
        t0 = time.perf_counter()
        r = identify(data, declared)
        sec = time.perf_counter() - t0
        ok = not adopt.bound_problems(r.twin.found, DT) and not adopt.identification_problems(r.twin.found, [])
        notes = [n for n in r.remaining if not n.startswith("not adopted")]
        rej = "; ".join(f"{x['effect']}: {x['reasons'][0].split(': ', 1)[-1]}" for x in r.rejected) or "none"
        rows.append(
            f"| {name}: {what} | {fmt_found(r, lti_features=True)} | {rej} | {r.heldout_before['G'] / SIGMA:.2f} -> "
            f"{r.heldout_after['G'] / SIGMA:.2f} | {'yes' if ok else 'NO'} | {'yes' if r.explained else 'no'} | "
            f"{' / '.join(notes) or '-'} | {sec:.1f} |"
        )
        print(rows[-1], flush=True)
        assert r.heldout_after["G"] <= r.heldout_before["G"] and np.isfinite(r.heldout_after["G"])
    text = (
        "Real measured GIRFs as the undeclared part (see the module docstring of `bench/identify_real_girfs.py`): "
        f"8 probe waveforms x 3 axes x 5000 samples of 10 us, noise {SIGMA} mT/m estimated from the data, "
        "identify with its defaults.\n\n" + "\n".join(rows) + "\n"
    )
    if a.write_docs:
        write_section(
            "identify_real_girfs",
            "Real gradient responses as the undeclared part",
            text,
            "python -m bench.identify_real_girfs --write-docs",
            doc=DOC.parent / "identify.md",
        )


if __name__ == "__main__":
    main()
