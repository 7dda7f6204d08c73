"""Fleet runs and Monte Carlo studies on ``dask.distributed``: one task per recording (or per block of seeds).

A production line calibrates many devices (patent 000, claim 29); a Monte Carlo study repeats one estimator
over many noise realisations.  Both are embarrassingly parallel, so both go through the same small engine:
:func:`dask_client` (a ``LocalCluster`` sized for this machine by default, or an existing scheduler by address)
and :func:`submit_ordered` (submit, report progress as results arrive, return them in submission order).

Fleet
-----
A **task** is a plain function ``(recording_path, options) -> dict`` of flat result columns (scalars and
strings; :func:`flat_columns` flattens nested results).  Each system with ``fleet`` in :mod:`selfcal.registry`
registers its tasks in its own pipeline module with one line (the audit's task is in :mod:`selfcal.pipelines.audit`)::

    register_task("calibrate-encoder", calibrate_encoder_task, options=("reference",), help="...")

and :func:`tasks` finds them all through the registry.

:func:`run_fleet` runs one task per recording; an exception in a task becomes that recording's ``error``
column (``"TypeName: one-line message"``) and the fleet goes on.  :func:`write_table` writes the table as CSV
and Parquet atomically, :func:`write_fleet_report` a short HTML or Markdown report.

Input: a folder (every sub-folder that is a recording, in name order; the folder itself if it is one) or a
manifest listing recordings and per-recording options, in YAML::

    options: {system: imu}            # optional: defaults for every recording
    recordings:
      - line1/unit_0001               # a path (relative to the manifest's folder)
      - path: line1/unit_0002
        name: SN-0002                 # optional row label (default: the folder name)
        options: {imu: imu1}          # optional: this recording's options

(a bare YAML list of paths or of such entries works too), or in CSV: a ``path`` (or ``recording``) column,
an optional ``name`` column, and every other column an option (empty cell: not set; cells are read as YAML
scalars, so ``true``, ``5.0`` and ``imu0`` get their natural types).  Options merge as: command-line options,
then the manifest's ``options``, then the recording's own (the most specific wins).

Monte Carlo
-----------
A system registers a study (``register_study(name, block, combine)``, e.g. ``imu-pair-rotation`` in
:mod:`selfcal.pipelines.imu_pair`): a block function ``(n_runs, first_seed, **params) -> partial result`` and a
``combine`` that joins the blocks in seed order.  Every run is
seeded by its own seed (``first_seed + run``) and the blocks are joined in seed order, so the same seeds give
bit-identical estimates whatever the number of workers or the block size (timings differ, of course).
"""
from selfcal.pipelines.fleet.engine import (FleetResult, Task, dask_client, fleet_plan, register_task, run_fleet,
                                           run_task, sensor_option, submit_ordered, tasks)
from selfcal.pipelines.fleet.manifest import FleetError, FleetItem, fleet_items, is_recording
from selfcal.pipelines.fleet.outputs import flat_columns, numeric_summary, write_fleet_report, write_table
from selfcal.pipelines.fleet.studies import Study, register_study, run_study, studies

__all__ = ["FleetError", "FleetItem", "FleetResult", "Study", "Task", "dask_client", "fleet_items", "fleet_plan",
           "flat_columns", "is_recording", "numeric_summary", "register_study", "register_task", "run_fleet",
           "run_study", "run_task", "sensor_option", "studies", "submit_ordered", "tasks", "write_fleet_report",
           "write_table"]
