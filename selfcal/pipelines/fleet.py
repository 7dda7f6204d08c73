"""Fleet runs and Monte Carlo studies on ``dask.distributed``: one task per recording (or per block of seeds).

A production line calibrates many devices (patent 000, claim 29); a Monte Carlo study repeats one estimator
over many noise realisations.  Both are embarrassingly parallel, so both go through the same small engine:
:func:`dask_client` (a ``LocalCluster`` sized for this machine by default, or an existing scheduler by address)
and :func:`submit_ordered` (submit, report progress as results arrive, return them in submission order).

Fleet
-----
A **task** is a plain function ``(recording_path, options) -> dict`` of flat result columns (scalars and
strings; :func:`flat_columns` flattens nested results).  :data:`TASKS` maps task names to them; a system adds
its own with one line::

    register_task("calibrate-encoder", encoder_task, options=("array",), help="...")

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
:data:`STUDIES` maps study names to a block function ``(n_runs, first_seed, **params) -> partial result`` from
:mod:`selfcal.pipelines.imu_pair` and a ``combine`` that joins the blocks in seed order.  Every run is
seeded by its own seed (``first_seed + run``) and the blocks are joined in seed order, so the same seeds give
bit-identical estimates whatever the number of workers or the block size (timings differ, of course).
"""
from __future__ import annotations

import contextlib
import io
import logging
import math
import time
import traceback
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from selfcal.core.errors import SelfcalError
from selfcal.io.atomic import atomic_write_bytes, atomic_write_text
from selfcal.io.recording import read_recording

log = logging.getLogger(__name__)

BASE_COLUMNS = ("name", "recording", "task", "ok", "error", "seconds")
DEFAULT_WORKERS = 2  # this machine has 2 cores: one single-threaded worker process per core


class FleetError(SelfcalError):
    """A fleet that cannot start (bad manifest, unknown task or option, no recordings): one line, exit 1."""


# --- the engine: a dask client and ordered results with progress ----------------------------------------------

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


def submit_ordered(client, function: Callable, arguments: list[tuple], progress: Callable | None = None,
                   keys: list[str] | None = None) -> list:
    """Run ``function(*args)`` for every tuple of ``arguments`` on ``client``; results in the same order.

    ``progress(done, total, result_or_exception)`` is called as each one finishes (in completion order).
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
    for done, future in enumerate(as_completed(futures), start=1):
        try:
            value = future.result()
        except Exception as err:  # a task error or a lost worker: recorded, the rest goes on
            value = err
        results[index[future.key]] = value
        if progress:
            progress(done, len(futures), value)
        future.release()
    return results


# --- tasks ----------------------------------------------------------------------------------------------------

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


_AXES = "xyz"


def flat_columns(value, prefix: str = "") -> dict:
    """Nested dicts and lists as flat scalar columns: ``{"a": {"b": [1, 2, 3]}}`` -> ``a_b_x, a_b_y, a_b_z``.

    Vectors of 3 get ``x, y, z`` suffixes, 3x3 matrices ``xx, xy, ... zz`` (row, column), other lists their
    index; ``None`` stays a (null) column, lists of strings are joined with ``"; "``.
    """
    out: dict = {}
    if isinstance(value, dict):
        for key, item in value.items():
            out.update(flat_columns(item, f"{prefix}_{key}" if prefix else str(key)))
        return out
    if isinstance(value, (list, tuple, np.ndarray)):
        items = list(np.asarray(value).tolist()) if isinstance(value, np.ndarray) else list(value)
        if all(isinstance(v, str) for v in items):
            return {prefix: "; ".join(items)}
        arr = np.asarray(items, dtype=object)
        if arr.shape == (3, 3):
            return {f"{prefix}_{_AXES[i]}{_AXES[j]}": _scalar(arr[i, j]) for i in range(3) for j in range(3)}
        names = _AXES if len(items) == 3 else [str(i) for i in range(len(items))]
        for name, item in zip(names, items):
            out.update(flat_columns(item, f"{prefix}_{name}"))
        return out
    return {prefix: _scalar(value)}


def _scalar(value):
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, (list, tuple, np.ndarray)):
        return str(np.asarray(value).tolist())
    return value


def _sensor(recording, options: dict, key: str, index: int) -> str:
    names = recording.imu_names()
    if options.get(key):
        return str(options[key])
    if len(names) <= index:
        raise FleetError(f"{recording.path}: needs {index + 1} IMU sensor folder(s), found {names}")
    return names[index]


def calibrate_imu_task(recording_path, options: dict) -> dict:
    """IMU intrinsics (``selfcal calibrate imu``) of one IMU (option ``imu``, default the first), flattened."""
    from selfcal.pipelines.imu import calibrate_imu
    rec = read_recording(recording_path)
    sensor = _sensor(rec, options, "imu", 0)
    d = calibrate_imu(rec, sensor, gravity_m_s2=options.get("gravity")).to_dict()
    d.pop("units")
    return {"sensor": sensor, **flat_columns(d)}


def calibrate_imu_pair_task(recording_path, options: dict) -> dict:
    """Rotation (time offset, lever arm) between two IMUs (``selfcal calibrate imu-pair``), flattened.

    Options as the command: ``imu0``, ``imu1`` (default the first two), ``lever_arm``, ``time_offset``,
    ``gains`` (true / false / unset = where the data determine it), ``lowpass_hz`` (default 5, 0: none).
    """
    from selfcal.core import so3
    from selfcal.pipelines.imu_pair import calibrate_imu_pair
    rec = read_recording(recording_path)
    imu0, imu1 = _sensor(rec, options, "imu0", 0), _sensor(rec, options, "imu1", 1)
    lowpass = options.get("lowpass_hz", 5.0)
    cal = calibrate_imu_pair(rec, imu0, imu1, lever_arm=options.get("lever_arm"),
                             time_offset=options.get("time_offset"), lowpass_hz=float(lowpass) or None,
                             gains=options.get("gains", False))
    d = cal.to_dict()
    for key in ("rotation_convention", "time_offset_convention"):
        d.pop(key)
    for gain in d["relative_gain_imu1"].values():
        gain.pop("meaning")
    rotation_vector = so3.log(np.asarray(cal.estimate.R_imu0_imu1))
    return {"rotation_angle_deg": float(np.degrees(np.linalg.norm(rotation_vector))),
            **flat_columns({"rotation_vector_rad": rotation_vector}), **flat_columns(d)}


def audit_task(recording_path, options: dict) -> dict:
    """``selfcal audit`` (option ``system``: imu or imu-pair; ``base``, ``imu``, ``imu1``) as columns.

    Columns: ``findings`` (count), ``effects`` (``effect@target`` in the order found), ``final_model``, and per
    residual family the RMS of the base model (``rms_before_<family>``) and of the final one (``rms_after_``).
    """
    from selfcal.pipelines.audit import audit_recording
    if not options.get("system"):
        raise FleetError("task audit needs the option system (imu or imu-pair): --system imu")
    rec = read_recording(recording_path)
    sensors = [options[k] for k in ("imu", "imu1") if options.get(k)] or None
    run = audit_recording(rec, options["system"], options.get("base"), sensors)
    contract = run.to_json()
    out = {"system": contract["system"], "base_model": contract["base_model"],
           "findings": len(contract["findings"]),
           "effects": "; ".join(f"{f['effect']}@{f.get('target', f.get('sensor', ''))}"
                                for f in contract["findings"]),
           "final_model": "; ".join(contract["final_model"])}
    for fam in run.result.base_fit.families:
        out[f"rms_before_{_column(fam.label)}"] = float(fam.rms)
    for fam in run.result.final_fit.families:
        out[f"rms_after_{_column(fam.label)}"] = float(fam.rms)
    return out


def calibrate_encoder_task(recording_path, options: dict) -> dict:
    """``selfcal calibrate encoder`` as columns: per array the geometry, aperture and dark level with their
    sigmas and the residual; the graduation error's RMS and largest value, the median edge sigma, frames."""
    from selfcal.pipelines.encoder import calibrate_encoder
    cal = calibrate_encoder(read_recording(recording_path), use_reference=options.get("reference", True))
    d = cal.to_dict()
    graduation = np.asarray(d["graduation_error_rad"])
    sigma = np.array([np.nan if s is None else s for s in d["edges_sigma_rad"]], dtype=float)
    return {"edges": d["code"]["n_edges"], "graduation_rms_rad": float(np.sqrt(np.mean(graduation**2))),
            "graduation_max_rad": float(np.max(np.abs(graduation))),
            "edge_sigma_median_rad": float(np.nanmedian(sigma)),
            "frames_used": d["frames"]["used"], "frames_flagged": len(d["frames"]["flagged"]),
            "seconds": d["seconds"], **flat_columns({"arrays": d["arrays"]})}


def _column(label: str) -> str:
    return "".join(c if c.isalnum() else "_" for c in label).strip("_")


register_task("calibrate-imu", calibrate_imu_task, ("imu", "gravity"),
              "IMU intrinsics from a multi-position recording")
register_task("calibrate-imu-pair", calibrate_imu_pair_task,
              ("imu0", "imu1", "lever_arm", "time_offset", "gains", "lowpass_hz"),
              "rotation (time offset, lever arm) between two IMUs")
register_task("calibrate-encoder", calibrate_encoder_task, ("reference",),
              "encoder self-calibration from the diode array's own images")
register_task("audit", audit_task, ("system", "base", "imu", "imu1"),
              "residual audit: findings, effect names, residual RMS before/after", required=("system",))


# --- inputs ---------------------------------------------------------------------------------------------------

@dataclass
class FleetItem:
    """One recording of the fleet and its options."""

    path: Path
    name: str
    options: dict = field(default_factory=dict)


def is_recording(folder: Path) -> bool:
    """A folder with at least one sensor sub-folder holding a ``data.csv``."""
    return folder.is_dir() and any((sub / "data.csv").is_file() for sub in folder.iterdir() if sub.is_dir())


def fleet_items(source, options: dict | None = None) -> list[FleetItem]:
    """The recordings of a folder or a manifest (YAML or CSV; see the module docstring), options merged."""
    source = Path(source)
    options = {k: v for k, v in (options or {}).items() if v is not None}
    if source.is_dir():
        if is_recording(source):
            return [FleetItem(source, source.name, dict(options))]
        folders = sorted(p for p in source.iterdir() if not p.name.startswith(".") and is_recording(p))
        if not folders:
            raise FleetError(f"{source}: no recording in this folder (a recording holds <sensor>/data.csv)")
        return [FleetItem(p, p.name, dict(options)) for p in folders]
    if not source.is_file():
        raise FileNotFoundError(f"{source}: no such folder or manifest")
    suffix = source.suffix.lower()
    if suffix in (".yaml", ".yml"):
        entries, defaults = _yaml_manifest(source)
    elif suffix == ".csv":
        entries, defaults = _csv_manifest(source), {}
    else:
        raise FleetError(f"{source}: a manifest is a .yaml/.yml or .csv file")
    if not entries:
        raise FleetError(f"{source}: the manifest lists no recording")
    items = []
    for entry in entries:
        path = Path(str(entry["path"])).expanduser()
        path = path if path.is_absolute() else source.parent / path
        items.append(FleetItem(path, str(entry.get("name") or path.name),
                               {**options, **defaults, **(entry.get("options") or {})}))
    return items


def _yaml_manifest(source: Path) -> tuple[list[dict], dict]:
    try:
        doc = yaml.safe_load(source.read_text())
    except yaml.YAMLError as err:
        raise FleetError(f"{source}: not valid YAML ({' '.join(str(err).split())})") from err
    defaults = {}
    if isinstance(doc, dict):
        unknown = set(doc) - {"recordings", "options"}
        if unknown:
            raise FleetError(f"{source}: unknown manifest keys {sorted(unknown)} (known: recordings, options)")
        defaults = doc.get("options") or {}
        doc = doc.get("recordings") or []
    if not isinstance(doc, list) or not isinstance(defaults, dict):
        raise FleetError(f"{source}: a manifest is a list of recordings or {{recordings: [...], options: {{}}}}")
    entries = []
    for i, entry in enumerate(doc):
        if isinstance(entry, str):
            entry = {"path": entry}
        if not isinstance(entry, dict) or "path" not in entry:
            raise FleetError(f"{source}: recording {i + 1} has no path")
        if not isinstance(entry.get("options") or {}, dict):
            raise FleetError(f"{source}: recording {i + 1}: options must be a mapping")
        unknown = set(entry) - {"path", "name", "options"}
        if unknown:
            raise FleetError(f"{source}: recording {i + 1}: unknown keys {sorted(unknown)} (known: path, name, "
                             "options)")
        entries.append(entry)
    return entries, defaults


def _csv_manifest(source: Path) -> list[dict]:
    import csv
    with source.open(newline="") as f:
        rows = list(csv.DictReader(f))
    if not rows:
        return []
    path_key = next((k for k in ("path", "recording") if k in rows[0]), None)
    if path_key is None:
        raise FleetError(f"{source}: a CSV manifest needs a 'path' (or 'recording') column")
    entries = []
    for line, row in enumerate(rows, start=2):
        if not (row.get(path_key) or "").strip():
            raise FleetError(f"{source}, line {line}: empty path")
        options = {k: yaml.safe_load(v) for k, v in row.items()
                   if k not in (path_key, "name") and k and v is not None and v.strip() != ""}
        entries.append({"path": row[path_key].strip(), "name": (row.get("name") or "").strip(),
                        "options": options})
    return entries


# --- the fleet ------------------------------------------------------------------------------------------------

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


def run_fleet(source, task: str, options: dict | None = None, scheduler: str | None = None,
              workers: int | None = None, progress: Callable | None = None, client=None) -> FleetResult:
    """Run ``task`` on every recording of ``source`` (folder or manifest) on dask; see the module docstring.

    Parameters
    ----------
    source : str or Path
        Folder of recordings, a recording, or a manifest (YAML / CSV).
    task : str
        A name in :data:`TASKS`.
    options : dict, optional
        Options for every recording (the manifest's own override them).
    scheduler, workers :
        See :func:`dask_client`; ignored when ``client`` is given.
    progress : callable, optional
        ``progress(done, total, row)`` as each recording finishes.
    client : distributed.Client, optional
        An open client to use (and leave open).

    Returns
    -------
    FleetResult
    """
    import pandas as pd
    if task not in TASKS:
        raise FleetError(f"unknown task {task!r}; known: {', '.join(sorted(TASKS))}")
    spec = TASKS[task]
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
    start = time.perf_counter()

    def wrapped(done, total, value):
        if progress:
            progress(done, total, value if isinstance(value, dict) else {"ok": False, "error": one_line(value)})

    with contextlib.ExitStack() as stack:
        if client is None:
            client = stack.enter_context(dask_client(scheduler, workers))
        n_workers = len(client.scheduler_info().get("workers", {}))
        run_id = uuid.uuid4().hex[:8]  # keys unique per run: a client may run the same fleet twice
        keys = [f"{task}-{run_id}-{i}-{item.name}" for i, item in enumerate(items)]
        values = submit_ordered(client, run_task, [(spec, item) for item in items], wrapped, keys)
    rows = [value if isinstance(value, dict) else
            {"name": item.name, "recording": str(item.path), "task": task, "ok": False, "error": one_line(value),
             "seconds": math.nan}  # the task itself never returned: the worker died or the task was lost
            for item, value in zip(items, values)]
    table = pd.DataFrame(rows)
    columns = list(BASE_COLUMNS) + [c for c in table.columns if c not in BASE_COLUMNS]
    table = table.reindex(columns=columns)
    return FleetResult(table, task, time.perf_counter() - start, n_workers)


# --- outputs --------------------------------------------------------------------------------------------------

def _arrow_safe(table):
    """Object columns holding mixed kinds (a number in one row, text in another) become text: Parquet needs
    one type per column."""
    table = table.copy()
    for name in table.columns:
        if table[name].dtype == object:
            kinds = {type(v) for v in table[name] if v is not None and not (isinstance(v, float) and math.isnan(v))}
            if len(kinds) > 1 and not kinds <= {int, float, bool}:
                table[name] = [None if v is None or (isinstance(v, float) and math.isnan(v)) else str(v)
                               for v in table[name]]
    return table


def write_table(table, path) -> list[Path]:
    """Write ``table`` as CSV and as Parquet (both, atomically): ``path`` with either suffix names the pair.

    Returns the two paths written.
    """
    path = Path(path)
    if path.suffix.lower() not in (".csv", ".parquet"):
        raise FleetError(f"{path}: the table is written as .csv and .parquet; name one of them")
    path.parent.mkdir(parents=True, exist_ok=True)
    csv_path, parquet_path = path.with_suffix(".csv"), path.with_suffix(".parquet")
    atomic_write_text(csv_path, table.to_csv(index=False))
    buffer = io.BytesIO()
    _arrow_safe(table).to_parquet(buffer, index=False, engine="pyarrow")
    atomic_write_bytes(parquet_path, buffer.getvalue())
    return [csv_path, parquet_path]


def numeric_summary(table):
    """Per numeric column: count, mean, std, min, median, max (the fleet's spread of each result)."""
    import pandas as pd
    numeric = table.drop(columns=["ok"], errors="ignore").select_dtypes(include="number")
    if numeric.empty:
        return pd.DataFrame()
    stats = numeric.agg(["count", "mean", "std", "min", "median", "max"]).T
    stats["count"] = stats["count"].astype(int)
    return stats


HISTOGRAM_COLUMNS_MAX = 12


def histogram_figure(table, max_columns: int = HISTOGRAM_COLUMNS_MAX):
    """One panel per numeric column that varies over at least 3 recordings (first ``max_columns``), or None."""
    from matplotlib.figure import Figure
    numeric = table.drop(columns=["ok"], errors="ignore").select_dtypes(include="number")
    columns = [c for c in numeric.columns
               if numeric[c].notna().sum() >= 3 and numeric[c].nunique(dropna=True) > 1][:max_columns]
    if not columns:
        return None
    ncols = min(3, len(columns))
    nrows = math.ceil(len(columns) / ncols)
    fig = Figure(figsize=(4.0 * ncols, 2.8 * nrows))
    for i, name in enumerate(columns):
        ax = fig.add_subplot(nrows, ncols, i + 1)
        values = numeric[name].dropna().to_numpy(dtype=float)
        ax.hist(values, bins=min(20, max(3, int(np.sqrt(len(values))) + 1)))
        ax.set_title(name, fontsize=8)
        ax.tick_params(labelsize=7)
    fig.tight_layout()
    return fig


def _png(fig) -> bytes:
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=80)
    return buffer.getvalue()


def write_fleet_report(result: FleetResult, path) -> Path:
    """A short report: counts, failures, per-column statistics, histograms.

    ``.html``: one self-contained file (plots embedded); ``.md``: Markdown with the histograms in
    ``<stem>.png`` beside it.  Written atomically.
    """
    import base64
    import html
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    table = result.table
    failed = table[~table["ok"].astype(bool)]
    stats = numeric_summary(table)
    fig = histogram_figure(table)
    counts = (f"{len(table)} recordings, {len(table) - len(failed)} succeeded, {len(failed)} failed; "
              f"task {result.task}, {result.seconds:.1f} s on {result.workers} worker(s)")
    if path.suffix.lower() == ".md":
        lines = [f"# Fleet report: {result.task}", "", counts, ""]
        if len(failed):
            lines += ["## Failures", "", "| recording | error |", "|---|---|"]
            lines += [f"| {r['name']} | {str(r['error']).replace('|', '/')} |" for _, r in failed.iterrows()]
            lines.append("")
        if not stats.empty:
            lines += ["## Summary statistics (successful recordings)", "", stats.to_markdown()
                      if _has_tabulate() else "```\n" + stats.to_string() + "\n```", ""]
        if fig is not None:
            png_path = path.with_suffix(".png")
            atomic_write_bytes(png_path, _png(fig))
            lines += ["## Histograms", "", f"![histograms]({png_path.name})", ""]
        return atomic_write_text(path, "\n".join(lines))
    parts = [f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>Fleet report: {html.escape(result.task)}"
             "</title><style>body{font-family:sans-serif;margin:2em}table{border-collapse:collapse}"
             "td,th{border:1px solid #ccc;padding:2px 6px;font-size:90%}</style></head><body>",
             f"<h1>Fleet report: {html.escape(result.task)}</h1><p>{html.escape(counts)}</p>"]
    if len(failed):
        parts.append("<h2>Failures</h2>" + failed[["name", "recording", "error"]].to_html(index=False))
    if not stats.empty:
        parts.append("<h2>Summary statistics (successful recordings)</h2>"
                     + stats.to_html(float_format=lambda x: f"{x:.6g}"))
    if fig is not None:
        parts.append("<h2>Histograms</h2><img alt='histograms' src='data:image/png;base64,"
                     + base64.b64encode(_png(fig)).decode() + "'>")
    parts.append("<h2>Table</h2>" + table[["name", "ok", "error", "seconds"]].to_html(index=False)
                 + "</body></html>\n")
    return atomic_write_text(path, "\n".join(parts))


def _has_tabulate() -> bool:
    try:
        import tabulate  # noqa: F401  (pandas' to_markdown needs it)
    except ImportError:
        return False
    return True


# --- Monte Carlo on the same engine ---------------------------------------------------------------------------

@dataclass(frozen=True)
class Study:
    """A Monte Carlo study: ``block(n_runs, first_seed, **params)`` runs seeds ``first_seed ..`` one after the
    other; ``combine(blocks)`` joins the blocks' results (given in seed order) into one."""

    name: str
    block: Callable
    combine: Callable


def _combine_rotation_studies(blocks: list):
    from selfcal.pipelines.imu_pair import RotationStudy
    return RotationStudy(errors_graph=np.concatenate([b.errors_graph for b in blocks]),
                         nees=np.concatenate([b.nees for b in blocks]), bound_cov=blocks[0].bound_cov,
                         errors_patent=np.concatenate([b.errors_patent for b in blocks]),
                         seconds_graph=sum(b.seconds_graph for b in blocks),
                         seconds_patent=sum(b.seconds_patent for b in blocks))


def _imu_pair_rotation_block(n_runs: int, first_seed: int, **params):
    from selfcal.pipelines.imu_pair import imu_pair_rotation_study
    return imu_pair_rotation_study(n_runs, first_seed=first_seed, **params)


STUDIES: dict[str, Study] = {}


def register_study(name: str, block: Callable, combine: Callable) -> Study:
    """Make a Monte Carlo study runnable by :func:`run_study` (``block`` must be a module-level function)."""
    STUDIES[name] = Study(name, block, combine)
    return STUDIES[name]


register_study("imu-pair-rotation", _imu_pair_rotation_block, _combine_rotation_studies)


def _run_block(study: Study, n_runs: int, first_seed: int, params: dict):
    return study.block(n_runs, first_seed, **params)


def run_study(study: str | Study, n_runs: int, first_seed: int = 1000, block_size: int | None = None,
              client=None, scheduler: str | None = None, workers: int | None = None,
              progress: Callable | None = None, **params):
    """Run a Monte Carlo study on dask: seeds ``first_seed .. first_seed + n_runs - 1`` in blocks.

    Parameters
    ----------
    study : str or Study
        A name in :data:`STUDIES`, or a :class:`Study`.
    n_runs, first_seed :
        The seeds (run ``k`` uses ``first_seed + k``, exactly as the study run in one process does).
    block_size : int, optional
        Runs per dask task (default: ``n_runs`` split into 4 blocks per worker, at least 1): a block pays the
        study's set-up (e.g. the bound) once.
    client, scheduler, workers, progress :
        As in :func:`run_fleet`.
    **params
        Passed to the study (e.g. ``scenario=...``).

    Returns
    -------
    The study's combined result; raises the first block's exception if a block failed (a study with holes
    would not be the study asked for).
    """
    spec = STUDIES[study] if isinstance(study, str) else study
    if n_runs < 1:
        raise ValueError(f"n_runs must be at least 1, not {n_runs}")
    with contextlib.ExitStack() as stack:
        if client is None:
            client = stack.enter_context(dask_client(scheduler, workers))
        n_workers = max(1, len(client.scheduler_info().get("workers", {})))
        size = block_size or max(1, math.ceil(n_runs / (4 * n_workers)))
        starts = list(range(0, n_runs, size))
        arguments = [(spec, min(size, n_runs - s), first_seed + s, params) for s in starts]
        run_id = uuid.uuid4().hex[:8]
        keys = [f"{spec.name}-{run_id}-{first_seed + s}-{min(size, n_runs - s)}" for s in starts]
        blocks = submit_ordered(client, _run_block, arguments, progress, keys)
    for block in blocks:
        if isinstance(block, BaseException):
            raise block
    return spec.combine(blocks)
