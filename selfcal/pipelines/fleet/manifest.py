"""The fleet's input: a folder of recordings or a manifest (YAML or CSV) with per-recording options."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import yaml

from selfcal.core.errors import SelfcalError


class FleetError(SelfcalError):
    """A fleet that cannot start (bad manifest, unknown task or option, no recordings): one line, exit 1."""


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
