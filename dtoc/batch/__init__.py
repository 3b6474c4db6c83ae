"""``dtoc batch``: a protocol library x scanners x orientations x option sets, each job one ``dtoc optimize``,
on an existing engine (local process pool or Dask), cached by content and resumable (docs/batch.md).

plan (pydantic plan, jobs, keys) -> engines (where jobs run) -> worker (one job) -> store (output folder) ->
run (orchestration and report).
"""
