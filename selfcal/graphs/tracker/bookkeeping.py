"""Which factor is where in the smoother: each sensor's recent factor indices (removed again on a soft fault),
the indices already removed, and (``keep_graph``) the log of every factor for :func:`batch_smooth` and the audit."""
from __future__ import annotations

from collections import deque
from collections.abc import Callable

import gtsam
import numpy as np

from selfcal.graphs.tracker.options import SENSORS, TrackerOptions


class FactorBook:
    """The smoother's factor indices: recent ones per sensor, those to remove at the next update, those removed."""

    def __init__(self, options: TrackerOptions, deferral_s: Callable[[], float]):
        self.options = options
        self._deferral_s = deferral_s  # how long an inclinometer sample's decision waits now
        self._to_remove: list[int] = []  # factor indices to remove at the next smoother update
        # (keyframe, factor index) of each sensor's factors still in the smoother: on a soft-fault alarm all of them
        # are removed, back to the lag -- a ramp the state followed for seconds before the alarm (the detection
        # delay exceeds the detector's window) would otherwise stay in the state through the whole hold-out
        self.recent = {s: deque(maxlen=3 * int(np.ceil(options.lag_s / options.keyframe_s)) + 8) for s in SENSORS}
        self._removed_indices: set = set()  # bounded: duplicates only arise within the deferral (< 1 s)
        self._removed_order: deque = deque(maxlen=4096)
        self.removed = 0  # factors removed or dropped because of a fault decision (soft-fault alarm, faulty sensor)
        self.replaced = 0  # provisional inclinometer factors replaced by their final form: no fault
        self._fault_removals: set = set()  # indices named by remove_recent, until removed
        # [factor, tag, keyframe, removed, meta]: meta holds what the audit needs to rebuild the factor with
        # calibration effects (selfcal.audit.tracker)
        self.graph_log: list | None = [] if options.keep_graph else None
        self.keyframe_t_ns: list[int] | None = [] if options.keep_graph else None
        self.initial_values = gtsam.Values() if options.keep_graph else None
        self._log_position: dict[int, int] = {}  # smoother factor index -> position in graph_log
        self._meta: dict[int, dict] = {}  # id(factor object) -> meta, until the factor enters the graph

    def remember(self, factor, **meta) -> None:
        """Keep the measurement behind a factor for the audit, until the factor enters the graph."""
        self._meta[id(factor)] = meta

    def annotate(self, index: int, **meta) -> None:
        """Add to the remembered measurement of the factor at smoother ``index`` (already in the graph)."""
        if self.graph_log is not None and index in self._log_position:
            entry = self.graph_log[self._log_position[index]]
            if entry[4] is not None:
                entry[4].update(meta)

    def take_metas(self, factors: list) -> list:
        """The remembered measurements of the factors entering the graph (None where none); forgets the rest."""
        metas = [self._meta.pop(id(factor), None) for factor in factors]
        self._meta.clear()
        return metas

    def remove_later(self, index: int) -> None:
        """Remove a factor at the next smoother update."""
        self._to_remove.append(index)

    def removals(self) -> list[int]:
        """The factors to remove at this update: those not removed before, each once (a factor may be named twice:
        fault window, provisional replaced); marks them removed."""
        to_remove = [i for i in dict.fromkeys(self._to_remove) if i not in self._removed_indices]
        self._to_remove = []
        for i in to_remove:
            if len(self._removed_order) == self._removed_order.maxlen:
                self._removed_indices.discard(self._removed_order[0])
            self._removed_order.append(i)
            self._removed_indices.add(i)
        faulty = sum(1 for i in to_remove if i in self._fault_removals)
        self.removed += faulty
        self.replaced += len(to_remove) - faulty
        self._fault_removals.clear()
        if self.graph_log is not None:
            for i in to_remove:
                self.graph_log[self._log_position[i]][3] = True
        return to_remove

    def added(self, graph: gtsam.NonlinearFactorGraph, indices, tags: list, k: int, metas: list | None) -> None:
        """Record the smoother indices of the factors of ``graph`` that entered at keyframe ``k``."""
        for i, (idx, tag) in enumerate(zip(indices, tags)):
            if tag is not None and tag.split("/")[0] in self.recent:
                self.recent[tag.split("/")[0]].append((k, int(idx)))
            if self.graph_log is not None:
                self._log_position[int(idx)] = len(self.graph_log)
                self.graph_log.append([graph.at(i), tag, k, False, metas[i] if metas else None])

    def add_keyframe(self, t_ns: int, values: gtsam.Values) -> None:
        if self.keyframe_t_ns is not None:
            self.keyframe_t_ns.append(t_ns)
            self.initial_values.insert(values)

    def remove_recent(self, sensor: str, k: int) -> None:
        """Remove, at the next update, all the sensor's recent factors still inside the smoother (not
        marginalised)."""
        # factors are logged with the keyframe they entered at; a deferred inclinometer factor sits on a keyframe
        # up to the deferral older
        o = self.options
        defer = int(np.ceil(self._deferral_s() / o.keyframe_s)) + 1
        margin = int(np.ceil(o.lag_s / o.keyframe_s)) - 2 - defer
        named = [idx for kf, idx in self.recent[sensor] if o.mode == "isam2" or k - kf < margin]
        self._to_remove.extend(named)
        self._fault_removals.update(named)
        self.recent[sensor].clear()
