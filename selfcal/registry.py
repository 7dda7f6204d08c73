"""The one list of systems.

A system is a column of the layer grid: its modules carry its name in every layer it needs
(``models/tracker.py``, ``graphs/tracker/``, ``audit/tracker.py``, ``pipelines/tracker.py``, ``cli/tracker.py``,
...), and this file is the only place that lists the systems.  The audit pipeline, fleet and the command line
find a system's modules here by name (as evo's entry points import ``evo.cli.<app>`` by name); nothing else
lists the systems or branches on a system's name.

What a system offers is declared here, so that the command line can build its choices without importing any
estimator; the code behind each capability is found by convention in the system's pipeline module:

=========  ============================================================================================
audit      ``pipelines/<system>.py: audit_system(recording, base, sensors) -> AuditSystem``; ``audit`` lists
           the base models it accepts, the first being the default
online     ``pipelines/<system>.py: online_estimator(sensor_meta) -> estimator`` (``selfcal track``)
fleet      ``pipelines/<system>.py`` registers fleet tasks / Monte Carlo studies when imported
verbs      ``cli/<system>.py: VERBS``, the system's commands (always present)
=========  ============================================================================================

Adding a system: one module per layer it needs, named after it, plus one line in :data:`SYSTEMS`.
"""
from __future__ import annotations

import importlib
from dataclasses import dataclass
from types import ModuleType

from selfcal.core.errors import SelfcalError


@dataclass(frozen=True)
class System:
    name: str  # as typed on the command line: `selfcal calibrate imu-pair`, `--system imu-pair`
    summary: str  # one line, for help texts and docs
    patent: str | None = None  # the seed (../shared/seeds) whose method the system implements, if any
    audit: tuple[str, ...] = ()  # base models of `selfcal audit --system <name>` (first: the default)
    online: bool = False  # has an online estimator for `selfcal track --system <name>`
    fleet: bool = False  # its pipeline module registers fleet tasks or Monte Carlo studies

    @property
    def module(self) -> str:
        """Its module name in every layer (a Python name: ``imu-pair`` -> ``imu_pair``)."""
        return self.name.replace("-", "_")

    def load(self, layer: str) -> ModuleType:
        """Its module in ``layer`` (``"pipelines"``, ``"cli"``, ``"audit"``, ...), imported by name."""
        return importlib.import_module(f"selfcal.{layer}.{self.module}")


SYSTEMS: tuple[System, ...] = (
    System("imu", "IMU intrinsics from static poses and the moves between them (no turntable)",
           audit=("bias", "standard"), fleet=True),
    System("imu-pair", "rotation, clock offset and lever arm between two rigidly mounted IMUs",
           patent="002_1c48bc589d8ac4c3.txt", audit=("rotation",), fleet=True),
    System("encoder", "optical angle encoder self-calibrated from its own diode-array images",
           patent="000_8647083394453bbe.txt", audit=("ml",), fleet=True),
    System("scan", "mobile stereo + inertial 3D measurement, inertial drift corrected by sphere targets",
           patent="001_23c1f2a99406445a.txt", audit=("error15",)),
    System("qc", "quality control of a 3D scan (VDI/VDE 2634-2 figures, deviation from a reference mesh)",
           audit=("sphere",)),
    System("ship", "vessel attitude and gyro drift from gyro + accelerometer tilt (total force vector)",
           patent="003_5cbcad933271d834.txt", audit=("attitude",), online=True),
    System("tracker", "laser tracker + inclinometer + beam camera + IMU, fault-gated 6-DoF pose",
           patent="004_ebbf7d44e5184b68.txt", audit=("smoother",), online=True),
    System("stationing", "prism lever arm, column bend and tilt-sensor mountings from total-station stationing",
           audit=("bend",)),
)


class UnknownSystemError(SelfcalError):
    """A system name that is not in :data:`SYSTEMS`, or a system without the capability asked for."""


def system(name: str) -> System:
    for entry in SYSTEMS:
        if entry.name == name:
            return entry
    raise UnknownSystemError(f"unknown system {name!r}; known: {', '.join(names())}")


def names(capability: str | None = None) -> list[str]:
    """System names, optionally only those with ``capability`` (``"audit"``, ``"online"``, ``"fleet"``)."""
    return [s.name for s in SYSTEMS if capability is None or getattr(s, capability)]
