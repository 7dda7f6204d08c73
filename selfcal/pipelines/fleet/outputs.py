"""The fleet's outputs: flat result columns, the table (CSV + Parquet), a short HTML or Markdown report."""
from __future__ import annotations

import io
import math
from pathlib import Path

import numpy as np

from selfcal.io.atomic import atomic_write_bytes, atomic_write_text
from selfcal.pipelines.fleet.manifest import FleetError

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


RESULT_COLUMNS = ("findings", "effects", "final_model")  # what a task found per recording (the audit's columns)


def per_recording(table):
    """One row per recording for the report: name, ok, error (empty when it ran), seconds, and the columns that
    say what was found (``effects``: ``none`` for a recording that ran and showed none)."""
    view = table[["name", "ok", "error", "seconds"] + [c for c in RESULT_COLUMNS if c in table.columns]].copy()
    ok = view["ok"].astype(bool)
    view["error"] = view["error"].where(~ok & view["error"].notna(), "")
    if "effects" in view.columns:
        view["effects"] = view["effects"].where(~ok | (view["effects"].fillna("") != ""), "none").fillna("")
    return view


def write_fleet_report(result, path) -> Path:
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
        recordings = per_recording(table)
        lines += ["## Recordings", "", recordings.to_markdown(index=False) if _has_tabulate()
                  else "```\n" + recordings.to_string(index=False, na_rep="") + "\n```", ""]
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
    parts.append("<h2>Recordings</h2>" + per_recording(table).to_html(index=False, na_rep="",
                                                                      float_format=lambda x: f"{x:.1f}")
                 + "</body></html>\n")
    return atomic_write_text(path, "\n".join(parts))


def _has_tabulate() -> bool:
    try:
        import tabulate  # noqa: F401  (pandas' to_markdown needs it)
    except ImportError:
        return False
    return True
