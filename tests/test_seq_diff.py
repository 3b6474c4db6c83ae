"""dtoc diff: semantic comparison with tolerances; exit 0 same / 1 different."""

import json
from pathlib import Path

import pytest

from dtoc.seq.diff import diff_files, diff_ir
from dtoc.seq.ir import edges_to_fine
from dtoc.seq.read import read_seq
from dtoc.seq.write import write_seq

REPO = Path(__file__).resolve().parents[1]
SMALL = REPO / "sequences" / "epi_small.seq"


def test_same_file_is_same():
    r = diff_files(SMALL, SMALL)
    assert r.same and r.differences == []


def test_gradient_change_found_and_tolerated(tmp_path):
    ir = read_seq(SMALL)
    e = ir.edge_grad_mT_per_m.copy()
    e[1, 400:420] += 0.01  # 10 uT/m on y
    out = tmp_path / "m.seq"
    write_seq(ir.with_grad(edges_to_fine(e)), out)
    r = diff_files(SMALL, out)
    assert not r.same
    (d,) = [x for x in r.differences if x["what"] == "gradient"]
    assert d["where"].startswith("y:") and abs(d["b"] - d["a"]) == pytest.approx(0.01, rel=1e-3)
    # 0.01 mT/m against the 3.1 mT/m peak of the y blips: within rtol 5e-3, not within 2e-3
    assert diff_files(SMALL, out, rtol=5e-3).same
    assert not diff_files(SMALL, out, rtol=2e-3).same


def test_event_and_definition_changes():
    a = read_seq(SMALL)
    b = read_seq(SMALL)
    b.definitions = dict(b.definitions, FOV=[0.25, 0.25, 0.004], Name="other")
    from dataclasses import replace

    b.adc = [replace(b.adc[0], phase_rad=0.1)] + b.adc[1:]
    b.rf = [replace(b.rf[0], flip_angle_rad=1.0)]
    r = diff_ir(a, b)
    what = {(d["what"], d["where"].split(" ")[0]) for d in r.differences}
    assert ("definition", "FOV") in what and ("definition", "Name") in what
    assert any(d["what"] == "adc" and "phase_rad" in d["where"] for d in r.differences)
    assert any(d["what"] == "rf" and "flip_angle_rad" in d["where"] for d in r.differences)


def test_different_sequences():
    r = diff_files(SMALL, REPO / "sequences" / "epi_esp081.seq")
    assert not r.same and any(d["what"] in ("block_count", "gradient_grid") for d in r.differences)


def test_cli_diff(capsys, tmp_path):
    from dtoc.cli.main import run

    with pytest.raises(SystemExit) as e:
        run(["diff", str(SMALL), str(SMALL)])
    assert e.value.code in (0, None)
    assert "same" in capsys.readouterr().out
    with pytest.raises(SystemExit) as e:
        run(["diff", str(SMALL), str(REPO / "sequences" / "gre_small.seq"), "--json", "-"])
    assert e.value.code == 1
    d = json.loads(capsys.readouterr().out)
    assert d["same"] is False and d["n_differences"] > 0
    with pytest.raises(SystemExit) as e:
        run(["diff", str(SMALL), str(tmp_path / "nope.seq")])
    assert e.value.code == 2 and "no such file" in capsys.readouterr().err
