"""The engine: a dask client, ordered results with progress, tasks by name, one row per recording."""
from __future__ import annotations

import contextlib
import importlib
import logging
import math
import time
import traceback
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

from selfcal import registry
from selfcal.core.progress import quiet
from selfcal.pipelines.fleet.manifest import FleetError, FleetItem, fleet_items

log = logging.getLogger(__name__)

BASE_COLUMNS = ("name", "recording", "task", "ok", "error", "seconds")
DEFAULT_WORKERS = 2  # this machine has 2 cores: one single-threaded worker process per core


@contextlib.contextmanager
def dask_client(scheduler: str | None = None, workers: int | None = None) -> Iterator:
    """A ``dask.distributed.Client``: on an existing scheduler, or on a new ``LocalCluster``.

    Parameters
    ----------
    scheduler : str, optional
        Address of a running scheduler (``tcp://host:8786``); its workers are used as they are.
    workers : int, optional
        Worker processes of the local cluster (default 2), one thread each: the estimators hold the GIL in
        GTSAM's Python callbacks, so processes, not threads, run in parallel.

    Yields
    ------
    distributed.Client
    """
    from dask.distributed import Client, LocalCluster
    if scheduler:
        if workers:
            log.info("--workers is ignored with an existing scheduler (%s)", scheduler)
        with Client(scheduler) as client:
            yield client
        return
    # the scheduler's HTTP server on a free port: several fleets (or test runs) share this machine
    with LocalCluster(n_workers=workers or DEFAULT_WORKERS, threads_per_worker=1, processes=True,
                      dashboard_address=":0") as cluster, Client(cluster) as client:
        yield client


def submit_ordered(client, function: Callable, arguments: list[tuple], progress: Callable = quiet,
                   keys: list[str] | None = None, what: str = "tasks") -> list:
    """Run ``function(*args)`` for every tuple of ``arguments`` on ``client``; results in the same order.

    ``progress(what, done, total)`` is called as each one finishes (:mod:`selfcal.core.progress`).
    An exception raised by a task (or a lost worker) is returned in its place, never raised: the caller
    decides what a failure means.
    """
    from dask.distributed import as_completed
    if not arguments:
        return []
    futures = [client.submit(function, *args, key=key, pure=False)
               for args, key in zip(arguments, keys or [None] * len(arguments))]
    index = {future.key: i for i, future in enumerate(futures)}
    results: list = [None] * len(futures)
    progress(what, 0, len(futures))
    for done, future in enumerate(as_completed(futures), start=1):
        try:
            value = future.result()
        except Exception as err:  # a task error or a lost worker: recorded, the rest goes on
            value = err
        results[index[future.key]] = value
        progress(what, done, len(futures))
        future.release()
    return results


@dataclass(frozen=True)
class Task:
    """A fleet task: ``function(recording_path, options) -> dict of flat columns``."""

    name: str
    function: Callable[[Path, dict], dict]
    options: tuple[str, ...] = ()  # option names it reads; anything else is refused before the fleet starts
    help: str = ""
    required: tuple[str, ...] = ()  # options without which it cannot run (checked before the fleet starts)


TASKS: dict[str, Task] = {}


def register_task(name: str, function: Callable[[Path, dict], dict], options: tuple[str, ...] = (),
                  help: str = "", required: tuple[str, ...] = ()) -> Task:
    """Make ``function`` runnable as ``selfcal fleet ... --task name``.

    ``function`` must be importable by module and name (a module-level function), since worker processes
    receive it by reference.  ``options``: the option names it reads; ``required``: those it cannot do without.
    """
    TASKS[name] = Task(name, function, tuple(options), help, tuple(required))
    return TASKS[name]


def one_line(err: BaseException) -> str:
    """``TypeName: message`` on one line (what the table's error column holds)."""
    message = " ".join(str(err).split())
    return f"{type(err).__name__}: {message}" if message else type(err).__name__


def tasks() -> dict[str, Task]:
    """Every task by name: the audit's and those of each system with fleet tasks (found through the registry)."""
    importlib.import_module("selfcal.pipelines.audit")
    for system in registry.SYSTEMS:
        if system.fleet:
            system.load("pipelines")
    return TASKS


def sensor_option(recording, options: dict, key: str, index: int) -> str:
    """The IMU a task uses: option ``key`` if given, else the recording's ``index``-th IMU."""
    names = recording.imu_names()
    if options.get(key):
        return str(options[key])
    if len(names) <= index:
        raise FleetError(f"{recording.path}: needs {index + 1} IMU sensor folder(s), found {names}")
    return names[index]


def run_task(task: Task, item: FleetItem) -> dict:
    """One row: the task's columns, or the error of this recording (never raised)."""
    start = time.perf_counter()
    row = {"name": item.name, "recording": str(item.path), "task": task.name}
    try:
        columns = task.function(item.path, dict(item.options))
        row.update(ok=True, error=None)
        row.update({k: v for k, v in columns.items() if k not in BASE_COLUMNS})
    except Exception as err:  # any failure of one recording is that row's result; the fleet goes on
        log.debug("%s failed:\n%s", item.path, traceback.format_exc())
        row.update(ok=False, error=one_line(err))
    row["seconds"] = time.perf_counter() - start
    return row


@dataclass
class FleetResult:
    """The fleet's table (one row per recording, in input order) and how long it took."""

    table: object  # pandas.DataFrame
    task: str
    seconds: float
    workers: int

    @property
    def n_failed(self) -> int:
        return int((~self.table["ok"].astype(bool)).sum())


def fleet_plan(source, task: str, options: dict | None = None) -> tuple[Task, list[FleetItem]]:
    """The task and the recordings of a fleet, checked before any cluster starts: an unknown task, an option the
    task does not take or a required one missing is a :class:`FleetError`."""
    known = tasks()
    if task not in known:
        raise FleetError(f"unknown task {task!r}; known: {', '.join(sorted(known))}")
    spec = known[task]
    items = fleet_items(source, options)
    for item in items:
        unknown = set(item.options) - set(spec.options)
        if unknown:
            raise FleetError(f"{item.name}: task {task} takes no option {', '.join(sorted(unknown))} "
                             f"(it takes: {', '.join(spec.options) or 'none'})")
        missing = [name for name in spec.required if item.options.get(name) in (None, "")]
        if missing:
            raise FleetError(f"{item.name}: task {task} needs the option(s) {', '.join(missing)} "
                             f"(e.g. --{missing[0].replace('_', '-')} ...)")
    return spec, items


def run_fleet(source, task: str, options: dict | None = None, scheduler: str | None = None,
              workers: int | None = None, progress: Callable = quiet, client=None) -> FleetResult:
    """Run ``task`` on every recording of ``source`` (folder or manifest) on dask; see the module docstring.

    Parameters
    ----------
    source : str or Path
        Folder of recordings, a recording, or a manifest (YAML / CSV).
    task : str
        A name in :func:`tasks`.
    options : dict, optional
        Options for every recording (the manifest's own override them).
    scheduler, workers :
        See :func:`dask_client`; ignored when ``client`` is given.
    progress : callable, optional
        ``progress("recordings", done, total)`` as each recording finishes (:mod:`selfcal.core.progress`).
    client : distributed.Client, optional
        An open client to use (and leave open).

    Returns
    -------
    FleetResult
    """
    import pandas as pd
    spec, items = fleet_plan(source, task, options)
    start = time.perf_counter()
    with contextlib.ExitStack() as stack:
        if client is None:
            client = stack.enter_context(dask_client(scheduler, workers))
        n_workers = len(client.scheduler_info().get("workers", {}))
        run_id = uuid.uuid4().hex[:8]  # keys unique per run: a client may run the same fleet twice
        keys = [f"{task}-{run_id}-{i}-{item.name}" for i, item in enumerate(items)]
        values = submit_ordered(client, run_task, [(spec, item) for item in items], progress, keys, "recordings")
    rows = [value if isinstance(value, dict) else
            {"name": item.name, "recording": str(item.path), "task": task, "ok": False, "error": one_line(value),
             "seconds": math.nan}  # the task itself never returned: the worker died or the task was lost
            for item, value in zip(items, values)]
    table = pd.DataFrame(rows)
    columns = list(BASE_COLUMNS) + [c for c in table.columns if c not in BASE_COLUMNS]
    table = table.reindex(columns=columns)
    return FleetResult(table, task, time.perf_counter() - start, n_workers)
