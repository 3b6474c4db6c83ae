"""optimize_sequence is a composition of typed stages (docs/optimize.md): run by hand, they write the same file."""

from dtoc.optimize.config import load_config
from dtoc.optimize.run import (
    RunIO,
    discard_stage,
    export_stage,
    full_loss_stage,
    optimize_sequence,
    plan_run,
    start_solution,
    warm_start_stage,
)


def test_stages_by_hand_write_the_same_file_as_optimize_sequence(tmp_path):
    cfg = load_config("epi", None, {"warm_iters": 40, "iters": 2, "threads": 1, "b0_T": 7.0})
    girf = "girf/example_7T.npz"
    a = tmp_path / "a.seq"
    optimize_sequence("sequences/epi_small.yaml", out=a, girf=girf, config=cfg, trajectory_path=None)
    b = tmp_path / "b.seq"
    io = RunIO(out=b, girf=girf, base_path="sequences/epi_small.yaml")
    plan = plan_run("sequences/epi_small.yaml", io, config=cfg)
    assert plan.free.any() and plan.window is None and plan.imager is not None
    sol = start_solution(plan, io)
    sol.x = warm_start_stage(plan, sol, lambda *_: None)
    assert plan.projector.is_feasible(sol.x.numpy())
    sol.x = full_loss_stage(plan, sol, io, lambda *_: None)
    discard_stage(plan, sol)
    res = export_stage(plan, sol, io, 0.0)
    assert res.manifest["after"]["kspace_max_error_dk"] < res.manifest["before"]["kspace_max_error_dk"]
    assert a.read_bytes() == b.read_bytes()
