"""CAN log files (Vector .asc and .blf, candump .log) replayed as a sample source (``--can-log FILE``).

The files are read by python-can's own log readers (:func:`can.LogReader` picks the reader by the suffix) and each
frame goes through the decoder the live bus uses: the fixed inclinometer TPDO1 of
:class:`selfcal.io.streams.CanInclinometerSource` (its ``handle``), or a DBC (:class:`selfcal.io.dbc.DbcDecoder`).
The frame's time is the log's own (the live bus's receive time), so a logged run gives the samples the live bus
gave.  ASC logs are read with absolute times (python-can's ``relative_timestamp=False``: the header's start time,
local time zone, to the millisecond, plus each frame's offset), so that a log can be merged with a recording of
the same run.

A log is replayed as fast as possible, or paced by its timestamps (``realtime``); alone or merged exactly, in
timestamp order, with recordings (:func:`merge_offline`).  It is never mixed with live sources: their clocks are
not the log's.
"""
from __future__ import annotations

import heapq
import struct
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path

from selfcal.io.streams import CanInclinometerSource, Sample, StreamError

SUFFIXES = {".asc": "Vector ASCII", ".blf": "Vector binary", ".log": "candump -L"}


class CanLogError(StreamError):
    """A CAN log cannot be read (missing, unknown format, corrupt)."""


def read_can_log(path) -> Iterator:
    """The ``can.Message`` frames of a log file, in file order (one-line :class:`CanLogError` if unreadable)."""
    import can
    from can.io.blf import BLFParseError

    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in SUFFIXES:
        raise CanLogError(f"{path}: unknown CAN log suffix {suffix or '(none)'!r}; supported: "
                          + ", ".join(f"{s} ({kind})" for s, kind in SUFFIXES.items()))
    if not path.is_file():
        raise CanLogError(f"{path}: no such CAN log")
    kwargs = {"relative_timestamp": False} if suffix == ".asc" else {}
    try:
        with can.LogReader(path, **kwargs) as reader:
            yield from reader
    except (BLFParseError, ValueError, struct.error, EOFError, UnicodeDecodeError, IndexError) as err:
        raise CanLogError(f"{path}: not a readable {SUFFIXES[suffix]} log ({' '.join(str(err).split())})") from None


class CanLogSource:
    """A CAN log as a source: ``samples(stop)`` and ``stats`` as the live sources, plus frame counts.

    Parameters
    ----------
    path : path
        ``.asc``, ``.blf`` or candump ``.log``.
    decoder : object, optional
        A :class:`selfcal.io.dbc.DbcDecoder` (``decode(msg) -> list[Sample]``); default: the fixed inclinometer
        TPDO1 of ``node_id``, sample sensor ``sensor``.
    """

    def __init__(self, path, decoder=None, node_id: int = 1, sensor: str = "incl0"):
        self.path = Path(path)
        if decoder is None:
            # the live bus's decoder itself: its ``handle`` never touches the bus it is given
            tpdo = CanInclinometerSource(bus=self, node_id=node_id, sensor=sensor)
            self.decode = lambda msg: [s] if (s := tpdo.handle(msg)) is not None else []
            self.stats = tpdo.stats
        else:
            self.decode, self.stats = decoder.decode, decoder.stats
        self.stats.name = f"CAN log {self.path}"
        self.frames = 0
        self._last_t_ns: int | None = None
        next(iter(read_can_log(self.path)), None)  # refuse a missing, unknown or unreadable file now, not mid-run

    def samples(self, stop: threading.Event | None = None) -> Iterator[Sample]:
        """Every decoded sample in log order, as fast as possible (:func:`merge_offline` paces); one earlier than
        the last yielded is dropped and counted (late): the estimators are promised timestamp order."""
        for msg in read_can_log(self.path):
            if stop is not None and stop.is_set():
                return
            self.frames += 1
            for sample in self.decode(msg):
                if self._last_t_ns is not None and sample[1] < self._last_t_ns:
                    self.stats.late += 1
                    continue
                self._last_t_ns = sample[1]
                yield sample

    def summary(self) -> str:
        s = self.stats
        used = self.frames - s.ignored - s.malformed
        return (f"{s.name}: {self.frames} frames: {used} decoded into {s.samples} samples, {s.ignored} skipped "
                f"(IDs not decoded), {s.malformed} malformed skipped" + (f", {s.late} out of order dropped"
                                                                        if s.late else "")
                + (f", {s.reanchored} clock re-anchorings" if s.reanchored else ""))

    def close(self) -> None:
        """Nothing stays open between reads (each read opens and closes the file)."""


def paced(samples: Iterable[Sample], speed: float = 1.0, clock: Callable[[], float] = time.monotonic,
          sleep: Callable[[float], None] = time.sleep) -> Iterator[Sample]:
    """``samples`` released at their timestamps' pace (divided by ``speed``), as :func:`streams.replay` paces."""
    t0 = wall0 = None
    for sample in samples:
        if t0 is None:
            t0, wall0 = sample[1], clock()
        wait = wall0 + (sample[1] - t0) * 1e-9 / speed - clock()
        if wait > 0:
            sleep(wait)
        yield sample


def merge_offline(sources: list, stop: threading.Event, max_samples: int | None = None, realtime: bool = False,
                  speed: float = 1.0) -> Iterator[Sample]:
    """Samples of file sources (recording replays, CAN logs; each already in time order) merged exactly in
    timestamp order, ties in sensor name order (as :func:`streams.replay` orders a recording's sensors)."""
    merged = heapq.merge(*(s.samples(stop) for s in sources), key=lambda sample: (sample[1], sample[0]))
    for k, sample in enumerate(paced(merged, speed) if realtime else merged):
        if (max_samples is not None and k >= max_samples) or stop.is_set():
            return
        yield sample
