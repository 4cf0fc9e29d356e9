"""The run engine: many independent tasks (a study's reconstructions, a sweep's
points, a batch's scenes), run serially in this process or on a Dask cluster,
with each finished task's row written at once and a killed run resumable.

A Lib describes its work as data (:class:`Task` and the :class:`Shared` inputs
they need); nothing here is imported by a Lib to run serially, and Dask is
imported only when a cluster is asked for.

Modules
-------
- ``tasks``: Task and Shared (what to compute, described as data; stable task ids).
- ``grid``: value lists from the command line, study files (JSON/YAML), grid products.
- ``store``: the run folder: one record per task, table.csv, resuming a killed run.
- ``engine``: run_tasks: the serial loop and the Dask executor, progress, failures.
- ``cluster``: which Dask cluster (local sized to the machine, --scheduler, FLUO_SCHEDULER).
"""

from fluoguide.lazy import attach

__getattr__, __dir__, __all__ = attach(__name__, {
    "tasks": ["Task", "Shared", "task_id"],
    "grid": ["parse_values", "load_study_file", "grid_product"],
    "store": ["RunStore", "read_table", "stable_columns"],
    "engine": ["run_tasks", "SerialExecutor"],
    "cluster": ["dask_executor", "executor", "scheduler_address", "scheduler_timeout",
                "probe_scheduler", "SCHEDULER_ENV", "SCHEDULER_TIMEOUT_ENV"],
})
