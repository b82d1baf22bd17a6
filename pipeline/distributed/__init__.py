"""Sweeps beyond one machine: the DVC pipeline's stage items as Ray tasks, a shared DVC remote
as the artifact store (issue 12; user guide: docs/sweeps.md).

How a grid maps onto DVC
------------------------
A grid file lists envs, seeds and named param override sets. One *cell* is one (env, override
set): its params.yaml is the base params (or the env's preset) with the env's and the override
set's values merged in and the grid's seeds. dvc.yaml already fans a params.yaml out over seeds,
objectives and variants, so a cell is one ordinary DVC workspace (a clone of the project's HEAD
commit with the cell's params.yaml, dvc.lock removed) and its stage items (`train_specialist@0`,
`extract@0-td3-mapex`, ..., `report`) are exactly what `dvc repro` would run there.

Tasks: one Ray task per stage item, from DVC's own DAG (`Repo.index.graph` of the cell
workspace). A task's arguments are the results of its direct upstream tasks, so Ray runs it only
after them; a result carries the upstream item's dvc.lock entry. The task clones the commit into
a scratch directory, writes the cell's params.yaml and the upstream entries into the clone's
dvc.lock, runs `dvc repro --single-item --pull <item>` (a missing input is pulled from the
remote; the stage is restored from the remote's run-cache if this exact run was published
before, else computed), publishes outputs and run-cache entry with `dvc push --run-cache <item>`
and deletes the clone. Workers never write the driver's files.

Items shared between cells: two cells whose item has the same command, the same values of the
params it declares in dvc.yaml and the same upstream (e.g. the specialists of two override sets
that change only `extract`) are one computation for DVC (one run-cache key). The driver submits
it once and hands its result to both cells, so the remote never holds two different runs under
one key (which would make the lock's restore ambiguous).

The lock: when every task of a cell succeeded, the driver runs `dvc repro --pull` once in the
cell's workspace. Every stage is restored from the remote's run-cache; `mapex` is shadowed by
a stub that fails, so nothing can be recomputed there. The resulting dvc.lock is the one a serial
`dvc repro` of the cell writes (tested byte for byte).

Dead workers: Ray retries a task whose worker process or node died (`max_retries`); a stage that
exits with an error raises `StageFailed`, which is not retried (`retry_exceptions=False`). A
retry starts from a fresh clone and redoes only its own stage: upstream outputs come from the
remote. A second sweep with nothing changed runs no stage: a cell whose workspace is at the
commit with its params and a dvc.lock that `dvc status` finds up to date submits no task, and a
task whose run is in the remote's run-cache restores instead of computing.

Provenance: artifacts record the commit with `git_dirty: true`, as for any run whose
params.yaml differs from the commit's; the code is exactly the commit (the driver refuses to
start from uncommitted code changes).

Modules: `grid` (the grid file and its cells), `workspace` (the cells' git + DVC workspaces and
stage items), `task` (the Ray task a worker runs), `driver` (`run_sweep`), `errors`.

Ray is optional (`pip install -e .[sweep]`) and imported only by the driver functions.
"""
