"""`dtoc identify-plan`: proposed test waveforms identify the candidate set, checked by the identifiability test
(dtoc/identify/plan.py, docs/identify.md "Planning a measurement")."""

from __future__ import annotations

import json

import numpy as np
from cli_helpers import run_cli

from dtoc.identify.plan import check, propose

DT = 10e-6


def test_proposed_waveforms_identify_every_candidate():
    g, labels = propose(DT, record_s=20e-3)
    assert g.shape == (9, 3, 2000) and len(labels) == 9
    assert all(np.count_nonzero(np.abs(w).sum(-1)) == 1 for w in g)  # one axis at a time
    slew = np.abs(np.diff(g, axis=-1)).max() / DT * 1e-3
    assert slew <= 150.0 + 1e-9 and np.abs(g).max() <= 30.0 + 1e-9
    v = check(g, DT)
    assert v and all(x.identifiable for x in v), [x.reason for x in v if not x.identifiable]


def test_one_waveform_on_all_axes_is_named_degenerate():
    """The same waveform on all three axes: every eddy cross term is degenerate with another effect driven by
    the same slew; per-axis delays stay identifiable (each axis is measured on its own)."""
    g, _ = propose(DT, record_s=20e-3, axes=("x",))
    same = np.repeat(g[:, :1], 3, axis=1)
    v = {x.name: x for x in check(same, DT, kinds=["delay", "exp_eddy", "cross_eddy"])}
    for name in ("cross_eddy[y]<-x", "cross_eddy[y]<-z", "exp_eddy[y]"):
        assert not v[name].identifiable and "degenerate with" in v[name].reason, v[name]
    assert all(v[f"delay[{a}]"].identifiable for a in "xyz")


def test_cli_writes_waveforms_and_check(capsys, tmp_path):
    out, js = tmp_path / "plan.npz", tmp_path / "plan.json"
    code, stdout, err = run_cli(
        capsys, "identify-plan", "--kinds", "delay,cross_eddy", "--record-ms", "10", "-o", out, "--json", js
    )
    assert code == 0, err
    rep = json.loads(js.read_text())
    assert rep["all_identifiable"] and len(rep["candidates"]) == 9 and rep["dt_s"] == 1e-5
    with np.load(out) as z:
        assert z["g"].shape == (9, 3, 1000) and float(z["dt"]) == 1e-5
    assert "cross_eddy[y]<-x: identifiable" in stdout
    code, _, err = run_cli(capsys, "identify-plan", "--kinds", "bogus")
    assert code == 2 and "--kinds" in err and "Traceback" not in err
    code, _, err = run_cli(capsys, "identify-plan", "-o", out)  # exists, no --force
    assert code == 2 and "Traceback" not in err
