"""``selfcal track``: live samples -> online estimator -> TUM poses + JSON lines, written as they come.

The estimator is anything with ``push(sensor_name, t_ns, values) -> list[dict]`` consuming samples in timestamp
order; each output dict holds ``t_ns``, ``position`` (3), ``quaternion`` (qx, qy, qz, qw: TUM's order, as
:class:`selfcal.pipelines.tracker.OnlineTracker` gives it), ``covariance`` (6x6) and fault flags.  Systems are
found by name in :mod:`selfcal.registry` (those with ``online``): their pipeline module's ``online_estimator``
takes the sensors' sensor.yaml contents (``{sensor: meta}``, from the replayed recording or ``--sensors-from``).

Outputs are streams, not results: each line is appended and flushed as soon as the estimator gives it, so a
killed tracker leaves every pose computed before the kill (atomic whole-file writes would leave nothing).
"""
from __future__ import annotations

import bisect
import json
import logging
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from selfcal import registry
from selfcal.core.errors import SelfcalError

log = logging.getLogger(__name__)


class TrackError(SelfcalError):
    """A ``selfcal track`` run cannot start (unknown system, output exists, estimator output malformed)."""


class LatencyHistogram:
    """Push latencies in bounded memory (a live run lasts hours): counts on log-spaced bins 1 % wide from 1 us to
    100 s (a percentile is good to 1 %), the exact maximum.  A list of every latency grew 1.8 KB per pose."""

    EDGES = np.geomspace(1e-6, 100.0, 1159)  # ratio 1.01 between edges
    _EDGES = EDGES.tolist()  # bisect on a list: np.searchsorted on one float costs ~4 us, per sample

    def __init__(self):
        self.counts = np.zeros(len(self.EDGES) + 1, dtype=np.int64)
        self.max_s = float("nan")
        self.n = 0

    def add(self, seconds: float) -> None:
        self.counts[bisect.bisect_left(self._EDGES, seconds)] += 1  # = np.searchsorted(EDGES, seconds)
        self.max_s = seconds if self.n == 0 else max(self.max_s, seconds)
        self.n += 1

    def __len__(self) -> int:
        return self.n

    def percentile_s(self, q: float) -> float:
        """The q-th percentile (the geometric middle of its bin: within half a bin, 0.5 %; q = 100: the maximum);
        NaN without samples."""
        if self.n == 0:
            return float("nan")
        if q >= 100:
            return self.max_s
        k = int(np.clip(np.searchsorted(np.cumsum(self.counts), q / 100.0 * self.n), 1, len(self.EDGES) - 1))
        return float(min(np.sqrt(self.EDGES[k - 1] * self.EDGES[k]), self.max_s))


@dataclass
class TrackResult:
    """Counters of one run: samples in, poses out, wall time, data time span, push latencies."""

    samples: int = 0
    outputs: int = 0
    wall_s: float = 0.0
    data_span_s: float = 0.0
    latencies_s: LatencyHistogram = field(default_factory=LatencyHistogram, repr=False)
    first_t_ns: int | None = None
    last_t_ns: int | None = None
    interrupted: bool = False  # ended by Ctrl-C
    # --append: poses already in an output file (stamped at or before its last pose), not written again: file -> count
    skipped: dict[str, int] = field(default_factory=dict)
    per_sensor: dict[str, int] = field(default_factory=dict)

    @property
    def samples_per_s(self) -> float:
        return self.samples / self.wall_s if self.wall_s > 0 else float("inf")

    @property
    def realtime_factor(self) -> float:
        """Data time / wall time (> 1: faster than real time)."""
        return self.data_span_s / self.wall_s if self.wall_s > 0 else float("inf")

    def latency_percentile_ms(self, q: float) -> float:
        return self.latencies_s.percentile_s(q) * 1e3

    def summary(self) -> str:
        return (f"{self.samples} samples ({', '.join(f'{k} {v}' for k, v in sorted(self.per_sensor.items()))}) -> "
                f"{self.outputs} poses in {self.wall_s:.2f} s: {self.samples_per_s:.0f} samples/s, "
                f"{self.realtime_factor:.1f}x real time; push latency p50 {self.latency_percentile_ms(50):.3f} ms, "
                f"p99 {self.latency_percentile_ms(99):.3f} ms, max {self.latency_percentile_ms(100):.3f} ms")

    def to_dict(self) -> dict:
        return {"samples": self.samples, "outputs": self.outputs, "wall_s": self.wall_s,
                "data_span_s": self.data_span_s, "samples_per_s": self.samples_per_s,
                "realtime_factor": self.realtime_factor, "latency_p50_ms": self.latency_percentile_ms(50),
                "latency_p99_ms": self.latency_percentile_ms(99), "latency_max_ms": self.latency_percentile_ms(100),
                "per_sensor": dict(self.per_sensor)}


def make_estimator(system: str, meta: dict[str, dict] | None = None):
    """The online estimator of ``system`` (a system of :mod:`selfcal.registry` with ``online``; its pipeline
    module's ``online_estimator``), configured from sensor.yaml contents."""
    online = registry.names("online")
    if system not in online:
        raise TrackError(f"no online estimator for system {system!r}; known: {', '.join(online)}")
    return registry.system(system).load("pipelines").online_estimator(meta or {})


def check_replay(system: str, recording_path):
    """Vet a recording before it is replayed online: the system's own checks of what it cannot vouch for
    (``check_recording`` in its pipeline module: units, dead sensors, disagreeing sensors), the same as its batch
    path applies; a live stream cannot be vetted ahead, a recording can.  Returns the recording it read (for the
    replay: reading it again costs ~0.5 s of CPU per 300 s of tracker data), None when nothing was read."""
    from selfcal.io.recording import read_recording
    if system not in registry.names("online"):
        return None  # make_estimator names the systems that have one
    check = getattr(registry.system(system).load("pipelines"), "check_recording", None)
    if check is None:
        return None
    recording = read_recording(recording_path)
    check(recording)
    return recording


def sensor_meta(recording_path) -> dict[str, dict]:
    """``{sensor: sensor.yaml content}`` of a recording folder (only the YAML files are read, not the data)."""
    import yaml

    from selfcal.io.recording import RecordingError
    path = Path(recording_path)
    if not path.is_dir():
        raise RecordingError(f"{path}: no such recording folder")
    meta = {}
    for file in sorted(path.glob("*/sensor.yaml")):
        try:
            content = yaml.safe_load(file.read_text(encoding="utf-8"))
        except yaml.YAMLError as err:
            raise RecordingError(f"{file}: invalid YAML ({' '.join(str(err).split())})") from None
        meta[file.parent.name] = content if isinstance(content, dict) else {}
    return meta


def tum_line(out: dict) -> str:
    """``t x y z qx qy qz qw`` (TUM) from one estimator output; t in s with the full ns resolution."""
    t_ns = int(out["t_ns"])
    p = np.asarray(out["position"], dtype=float).reshape(3)
    q = np.asarray(out["quaternion"], dtype=float).reshape(4)  # qx qy qz qw
    sign = "-" if t_ns < 0 else ""
    sec, frac = divmod(abs(t_ns), 10**9)
    return " ".join([f"{sign}{sec}.{frac:09d}", *(repr(float(v)) for v in (*p, *q))])


def _plain(obj):
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


def tum_t_ns(field: str) -> int:
    """A TUM line's time field (s, as :func:`tum_line` writes it: up to nine decimals) back to ns, exactly."""
    sign, text = (-1, field[1:]) if field.startswith("-") else (1, field)
    sec, _, frac = text.partition(".")
    if not sec.isdigit() or not (frac == "" or frac.isdigit()):
        raise ValueError(f"not a time in s: {field!r}")
    return sign * (int(sec) * 10**9 + int(frac[:9].ljust(9, "0")))


def complete_lines_backwards(path: Path, block_bytes: int = 65536):
    """The lines of ``path`` that end in a newline, last first (a killed run's partial line after the last
    newline is not one), read from the end in blocks."""
    with open(path, "rb") as f:
        pos = f.seek(0, 2)
        buf, trimmed = b"", False
        while pos > 0:
            start = max(0, pos - block_bytes)
            f.seek(start)
            buf = f.read(pos - start) + buf
            pos = start
            if not trimmed:  # drop what follows the last newline, once
                cut = buf.rfind(b"\n")
                if cut < 0:
                    continue
                buf, trimmed = buf[:cut + 1], True
            # the line up to the first newline may have begun before this block: kept for the next one
            first = buf.find(b"\n") + 1 if pos > 0 else 0
            for line in reversed(buf[first:].splitlines()):
                yield line.decode("utf-8", errors="replace")
            buf = buf[:first]


def pose_t_ns(line: str) -> int | None:
    """The stamp (ns) of one output line: a TUM pose's first field (8 fields), a JSON line's ``t_ns``; None for
    anything else (a comment, a killed run's partial line ended by the next run)."""
    try:
        if line.startswith("{"):
            return int(json.loads(line)["t_ns"])
        fields = line.split()
        return tum_t_ns(fields[0]) if len(fields) == 8 else None
    except (ValueError, KeyError, TypeError):
        return None


def last_pose_t_ns(path: Path) -> int | None:
    """The stamp (ns) of the last whole pose in an output file, None when it holds none."""
    return next((t for t in map(pose_t_ns, complete_lines_backwards(path)) if t is not None), None)


class _LineSink:
    """A text file that lines are appended to and flushed one by one.  Continued (``append``), it resumes after
    the last pose already in it: outputs stamped at or before that are skipped and counted (a replay run again
    would write every pose twice)."""

    def __init__(self, path, append: bool):
        self.path = Path(path)
        if self.path.exists() and self.path.stat().st_size > 0 and not append:
            raise FileExistsError(f"{self.path}: already exists (pass --append to continue it)")
        self.resume_after_ns = last_pose_t_ns(self.path) if self.path.exists() else None
        self.skipped = 0
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.file = open(self.path, "a", encoding="utf-8", newline="\n")
        if self.file.tell() > 0:  # a killed run may have left a partial line: end it so ours start clean
            with open(self.path, "rb") as f:
                f.seek(-1, 2)
                if f.read(1) != b"\n":
                    self.file.write("\n")

    def write(self, line: str, t_ns: int) -> None:
        if self.resume_after_ns is not None and t_ns <= self.resume_after_ns:
            self.skipped += 1
            return
        self.file.write(line + "\n")
        self.file.flush()

    def close(self) -> None:
        self.file.close()


def run_track(samples: Iterable[tuple[str, int, dict]], estimator, out_tum=None, out_jsonl=None,
              append: bool = False, clock: Callable[[], float] = time.perf_counter) -> TrackResult:
    """Feed ``samples`` to ``estimator.push`` and stream its outputs to TUM and JSON-lines files.

    Parameters
    ----------
    samples : iterable of (sensor_name, t_ns, values)
        In timestamp order (see :mod:`selfcal.io.streams`).
    estimator : object
        With ``push(sensor_name, t_ns, values) -> list[dict]``.
    out_tum, out_jsonl : path, optional
        Poses (``t x y z qx qy qz qw``) and full outputs (one JSON object per line: the estimator's dict,
        covariance and fault flags included).
    append : bool
        Continue existing output files instead of refusing them, after the last pose already in each (outputs
        stamped at or before it are skipped, counted in ``TrackResult.skipped``).

    Returns
    -------
    TrackResult
        Throughput and latency counters (the latency of one ``push`` call, wall clock).
    """
    sinks = []
    result = TrackResult()
    try:
        tum = _LineSink(out_tum, append) if out_tum else None
        sinks.append(tum)
        jsonl = _LineSink(out_jsonl, append) if out_jsonl else None
        sinks.append(jsonl)
        start = clock()
        try:
            _track_samples(samples, estimator, result, tum, jsonl, clock)
        except KeyboardInterrupt:  # Ctrl-C ends a live run normally: the counters are still reported
            result.interrupted = True
            log.info("interrupted")
        t_first, t_last = result.first_t_ns, result.last_t_ns
        result.wall_s = clock() - start
        result.data_span_s = (t_last - t_first) * 1e-9 if t_first is not None else 0.0
    finally:
        for sink in sinks:
            if sink is not None:
                sink.close()
                if sink.resume_after_ns is not None:
                    result.skipped[str(sink.path)] = sink.skipped
    log.info("%s", result.summary())
    return result


def _track_samples(samples, estimator, result: TrackResult, tum, jsonl, clock) -> None:
    """Push every sample, write every pose; counters into ``result``."""
    for name, t_ns, values in samples:
        t0 = clock()
        outputs = estimator.push(name, t_ns, values)
        result.latencies_s.add(clock() - t0)
        result.samples += 1
        result.per_sensor[name] = result.per_sensor.get(name, 0) + 1
        result.first_t_ns = t_ns if result.first_t_ns is None else result.first_t_ns
        result.last_t_ns = t_ns
        for out in outputs or ():
            try:
                line = tum_line(out)
            except (KeyError, TypeError, ValueError) as err:
                raise TrackError(f"estimator output without a usable pose ({err!r}): keys {sorted(out)}") \
                    from None
            t_ns = int(out["t_ns"])
            if tum is not None:
                tum.write(line, t_ns)
            if jsonl is not None:
                jsonl.write(json.dumps(out, default=_plain, separators=(",", ":")), t_ns)
            result.outputs += 1
