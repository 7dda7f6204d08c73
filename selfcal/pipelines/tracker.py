"""Use cases of the laser-tracker target: ``selfcal smooth tracker REC`` and the online :class:`OnlineTracker`.

Recording columns (docs/tracker.md): ``imu0`` EuRoC; ``tracker0`` ``x, y, z [m]`` (+ optional ``vx, vy, vz
[m s^-1]``); ``incl0`` ``roll, pitch [rad]``; ``cam0`` ``u, v [px]``.  Geometry and sigmas come from the
sensors' sensor.yaml (keys written by :mod:`selfcal.sim.tracker`), defaults otherwise.
"""
from __future__ import annotations

import heapq
import json
import logging
import operator
import time
from dataclasses import dataclass, field, replace

import numpy as np

from selfcal.core.inertial import STANDARD_GRAVITY_M_S2
from selfcal.core.progress import quiet
from selfcal.core.sanity import (accelerometer_tilt_at, clock_jump_problems, coverage_problems, inclinometer_problems,
                                 tracker_problems)
from selfcal.graphs.tracker import (UNGATED, GatingOptions, SensorNoise, TrackerEstimator, TrackerOptions,
                                    batch_smooth)
from selfcal.io.camera import read_camera
from selfcal.io.recording import GYRO_COLUMNS, ACCEL_COLUMNS, Recording, RecordingError
from selfcal.pipelines.track import LatencyHistogram

log = logging.getLogger(__name__)

MODES = ("batch", "isam2", "fixed-lag")
# The longest IMU gap the tracker bridges: keyframes are 0.1 s apart, each tied to the next by the IMU; over 0.25 s
# (two keyframes and a half) a gap leaves keyframes without an inertial link: a 0.32 s clock step moved the smoothed
# position by 1.7 mm and a 0.56 s one broke the inclinometer's bookkeeping (found by tests/test_fuzz.py).  Tighter
# than the recording's general rule (1 s), which real loggers' 0.3-0.5 s stalls must pass.
MAX_IMU_GAP_S = 0.25
# The longest silence of every aiding sensor (tracker and inclinometer) the estimator coasts through on the IMU
# alone: as long as the IMU gap it bridges (keyframes 0.1 s apart).  A beam break is no such silence (the
# inclinometer goes on); once both are silent the poses are dead reckoning: 1.9 s of it put the pose 1.9 mm RMS
# off (0.25 mm aided), and 8 s made the smoother's marginals indeterminate (an internal error; tests/test_fuzz.py).
MAX_AIDING_GAP_S = MAX_IMU_GAP_S
AIDING = ("tracker0", "incl0")
_GYRO, _ACCEL = operator.itemgetter(*GYRO_COLUMNS), operator.itemgetter(*ACCEL_COLUMNS)  # 200 Hz: every us counts
REQUIRED = {"imu0": GYRO_COLUMNS + ACCEL_COLUMNS, "tracker0": ("x", "y", "z"), "incl0": ("roll", "pitch"),
            "cam0": ("u", "v")}


def noise_from_meta(meta: dict[str, dict]) -> SensorNoise:
    """SensorNoise from the sensor.yaml dicts of imu0, tracker0, incl0, cam0 (missing keys keep defaults)."""
    n = SensorNoise()
    imu, tr, inc, cam = (meta.get(s, {}) or {} for s in ("imu0", "tracker0", "incl0", "cam0"))
    updates = {
        "gyro_noise_density": imu.get("gyroscope_noise_density"),
        "accel_noise_density": imu.get("accelerometer_noise_density"),
        "gyro_random_walk": imu.get("gyroscope_random_walk"),
        "accel_random_walk": imu.get("accelerometer_random_walk"),
        "imu_rate_hz": imu.get("rate_hz"), "gravity_m_s2": imu.get("gravity_m_s2"),
        "tracker_sigma_m": tr.get("position_sigma_m"), "tracker_velocity_sigma_m_s": tr.get("velocity_sigma_m_s"),
        "incl_sigma_rad": inc.get("sigma_rad"), "incl_average_s": inc.get("averaging_s"),
        "cam_sigma_px": cam.get("sigma_px")}
    n = replace(n, **{k: float(v) for k, v in updates.items() if v is not None})
    arrays = {"r_P_B": tr.get("lever_arm_prism_m"), "tracker_W": tr.get("tracker_W_m"),
              "r_C_B": cam.get("lever_arm_camera_m"), "R_B_C": cam.get("R_B_C")}
    if any(key in cam for key in ("intrinsics", "camera_matrix")):
        intrinsics = read_camera(cam, "cam0/sensor.yaml")
        arrays.update(camera_matrix=intrinsics.K, dist_coeffs=intrinsics.dist)
    return replace(n, **{k: np.asarray(v, dtype=float) for k, v in arrays.items() if v is not None})


class OnlineTracker:
    """The online estimator behind ``selfcal track``: one sample at a time, in timestamp order.

    ``push(sensor_name, t_ns, values)`` takes the recording's column names without units (``imu0``:
    ``w_RS_S_x ... a_RS_S_z``; ``tracker0``: ``x, y, z`` [+ ``vx, vy, vz``]; ``incl0``: ``roll, pitch``;
    ``cam0``: ``u, v``) and returns the keyframe outputs this sample completed (usually none or one):
    ``{"t_ns", "position", "quaternion" (qx, qy, qz, qw), "covariance" (6x6 list, [rotation, position], world
    frame), "faults" {sensor: bool}, "decisions" [...]}``.  Unknown sensors are ignored (counted); a sample
    missing a column raises RecordingError naming it.
    """

    def __init__(self, noise: SensorNoise | None = None, mode: str = "fixed-lag", gating: bool = True,
                 options: TrackerOptions | None = None):
        if options is None:
            options = TrackerOptions(mode=mode, gating=GatingOptions() if gating else UNGATED)
        self.noise, self.options = noise or SensorNoise(), options
        self.estimator = TrackerEstimator(self.noise, options)
        self.ignored = 0
        self.restarts = 0
        self.latency_s = LatencyHistogram()  # per keyframe output; bounded: a live run lasts hours
        self._last_imu_ns: int | None = None
        self._gap_ns = int(1e9 * MAX_IMU_GAP_S)
        self._last_aiding_ns: int | None = None
        self._aiding_gap_ns = int(1e9 * MAX_AIDING_GAP_S)
        self._coasting = False  # every aiding sensor silent too long: the IMU is set aside until one reports

    def push(self, sensor_name: str, t_ns: int, values: dict[str, float]) -> list[dict]:
        start = time.perf_counter()
        if sensor_name in AIDING:
            if self._coasting:
                self._coasting = False
                self._restart(t_ns, f"{sensor_name} reports again after every aiding sensor was silent")
            self._last_aiding_ns = t_ns
        if sensor_name == "imu0":
            if self._last_aiding_ns is not None and t_ns - self._last_aiding_ns > self._aiding_gap_ns:
                if not self._coasting:
                    self._coasting = True
                    log.warning("tracker0 and incl0: silent for over %g s before t = %d ns: no pose until one reports "
                                "again (the IMU alone is dead reckoning)", MAX_AIDING_GAP_S, t_ns)
                self._last_imu_ns = t_ns
                return []
            if self._last_imu_ns is not None and t_ns - self._last_imu_ns > self._gap_ns:
                self._restart(t_ns, f"imu0: {(t_ns - self._last_imu_ns) * 1e-9:.3g} s without samples")
            self._last_imu_ns = t_ns
        e = self.estimator
        try:
            if sensor_name == "imu0":
                out = e.imu(int(t_ns), np.array(_GYRO(values)), np.array(_ACCEL(values)))
            elif sensor_name == "tracker0":
                vel = [values[c] for c in ("vx", "vy", "vz")] if "vx" in values else None
                out = e.tracker(int(t_ns), [values["x"], values["y"], values["z"]], vel)
            elif sensor_name == "incl0":
                out = e.incl(int(t_ns), values["roll"], values["pitch"])
            elif sensor_name == "cam0":
                out = e.cam(int(t_ns), values["u"], values["v"])
            else:
                self.ignored += 1
                return []
        except KeyError as err:
            raise RecordingError(f"{sensor_name}: sample at {t_ns} ns lacks column {err}") from None
        if out:
            for o in out:
                if o["covariance"] is not None:
                    o["covariance"] = np.asarray(o["covariance"]).tolist()
            self.latency_s.add(time.perf_counter() - start)
        return out

    def check(self) -> None:
        """At the end of a run: refuse (RecordingError) a run whose sensors disagreed with the model throughout
        (:func:`check_agreement`)."""
        check_agreement("the stream", self.estimator.counts)

    def _restart(self, t_ns: int, reason: str) -> None:
        """After an IMU gap (or a silence of every aiding sensor) the state cannot be propagated across: start over
        (a new estimator, initialised again from the next samples), and say so once."""
        log.warning("%s before t = %d ns: the estimator starts over (no pose is bridged across the gap)", reason, t_ns)
        self.restarts += 1
        self.estimator = TrackerEstimator(self.noise, self.options)


def recording_events(recording: Recording):
    """Every sample of the four sensors as (sensor, t_ns, values) in timestamp order (IMU first at ties)."""
    order = {"imu0": 0, "tracker0": 1, "incl0": 2, "cam0": 3}
    for name in ("imu0", "tracker0", "incl0"):
        if name not in recording.sensors:
            raise RecordingError(f"{recording.path}: the tracker system needs sensor {name!r} "
                                 f"(has: {', '.join(sorted(recording.sensors))})")
    streams = []
    for name, rank in order.items():
        if name not in recording.sensors:
            continue
        s = recording.sensors[name]
        missing = [c for c in REQUIRED[name] if c not in s.values]
        if missing:
            raise RecordingError(f"{recording.path}/{name}: missing columns {', '.join(missing)}")
        streams.append(_sensor_events(name, rank, s))
    check_sensors(recording)
    for t, _, name, values in heapq.merge(*streams, key=lambda e: (e[0], e[1])):
        yield name, t, values


def check_recording(recording: Recording) -> None:
    """What ``selfcal track --replay`` refuses before it starts: what :func:`smooth_tracker` refuses, but a gap
    (the online estimator starts over there)."""
    for name in ("imu0", "tracker0", "incl0"):
        if name not in recording.sensors:
            raise RecordingError(f"{recording.path}: the tracker system needs sensor {name!r} "
                                 f"(has: {', '.join(sorted(recording.sensors))})")
    check_sensors(recording, gaps_allowed=True)


def check_sensors(recording: Recording, gaps_allowed: bool = False) -> None:
    """Refuse (RecordingError, one line) a recording whose sensors the tool cannot vouch for: the IMU's own gates
    (:meth:`Recording.imu`), tracker positions and inclinometer angles against the IMU (:mod:`selfcal.core.sanity`)."""
    imu = recording.imu("imu0", gaps_allowed)
    t0_ns = int(imu.t_ns[0])
    gaps = np.diff(imu.t_ns) * 1e-9
    if not gaps_allowed and gaps.max(initial=0.0) > MAX_IMU_GAP_S:
        i = int(np.argmax(gaps))
        raise RecordingError(f"{recording.path}/imu0: {gaps[i]:.3g} s without samples after t = "
                             f"{(imu.t_ns[i] - t0_ns) * 1e-9:.6g} s: the tracker bridges at most {MAX_IMU_GAP_S:g} s "
                             "(its keyframes are 0.1 s apart); split the recording at the gap")
    t_imu = (imu.t_ns - t0_ns) * 1e-9
    t_aiding = np.sort(np.concatenate([recording.sensors[name].t_ns for name in AIDING]))
    silences = np.diff(t_aiding) * 1e-9
    if not gaps_allowed and silences.max(initial=0.0) > MAX_AIDING_GAP_S:
        i = int(np.argmax(silences))
        raise RecordingError(f"{recording.path}: tracker0 and incl0 silent for {silences[i]:.3g} s after t = "
                             f"{(t_aiding[i] - t0_ns) * 1e-9:.6g} s: the IMU alone coasts at most {MAX_AIDING_GAP_S:g} "
                             "s; split the recording at the gap")
    for name in ("tracker0", "incl0"):
        problems = coverage_problems(t_imu, (recording.sensors[name].t_ns - t0_ns) * 1e-9, name)
        if problems:
            raise RecordingError(f"{recording.path}/imu0: {problems[0]}")
    tr = recording.sensors["tracker0"]
    meta = tr.meta or {}
    problems = tracker_problems((tr.t_ns - t0_ns) * 1e-9, np.column_stack([tr.values[c] for c in ("x", "y", "z")]),
                                t_imu, imu.accel_m_s2, meta.get("tracker_W_m", (0.0, 0.0, 0.0)),
                                float(meta.get("position_sigma_m", SensorNoise().tracker_sigma_m)),
                                float(imu.meta.get("gravity_m_s2", STANDARD_GRAVITY_M_S2)))
    if problems:
        raise RecordingError(f"{recording.path}/tracker0: {problems[0]}")
    inc = recording.sensors["incl0"]
    t_inc = (inc.t_ns - t0_ns) * 1e-9
    problems = inclinometer_problems(t_inc, np.column_stack([inc.values["roll"], inc.values["pitch"]]),
                                     accelerometer_tilt_at(t_inc, t_imu, imu.accel_m_s2))
    if problems:
        raise RecordingError(f"{recording.path}/incl0: {problems[0]}")
    if gaps_allowed:  # a gap the online estimator starts over at must be samples lost, not the IMU's clock
        # jumping while the others keep time: its data after the gap would be fused out of step with theirs
        average_s = noise_from_meta({"incl0": inc.meta}).incl_average_s
        problems = clock_jump_problems(t_imu, imu.accel_m_s2, t_inc, np.column_stack([inc.values["roll"],
                                       inc.values["pitch"]]), average_s, MAX_IMU_GAP_S)
    if problems:
        raise RecordingError(f"{recording.path}/imu0: {problems[0]}")


def _sensor_events(name, rank, sensor):
    cols = list(sensor.values)
    data = np.column_stack([sensor.values[c] for c in cols])
    for t, row in zip(sensor.t_ns.tolist(), data.tolist()):
        yield t, rank, name, dict(zip(cols, row))


@dataclass
class TrackerResult:
    t_ns: np.ndarray  # (K,)
    position: np.ndarray  # (K, 3) body (IMU) origin in the tracker frame, m
    quaternion: np.ndarray  # (K, 4) qx qy qz qw of R_W_B
    covariance: np.ndarray | None  # (K, 6, 6) [rotation rad, position m], world frame
    faults: list[dict]  # per keyframe
    decisions: list[dict]  # every gating decision, in order
    mode: str
    seconds: float
    counts: dict = field(default_factory=dict)

    def tum_text(self) -> str:
        """TUM lines ``t x y z qx qy qz qw`` (t in s since the epoch of the recording's stamps)."""
        return "".join(f"{t * 1e-9:.9f} {p[0]:.6f} {p[1]:.6f} {p[2]:.6f} {q[0]:.9f} {q[1]:.9f} {q[2]:.9f} {q[3]:.9f}\n"
                       for t, p, q in zip(self.t_ns, self.position, self.quaternion))

    def decisions_jsonl(self) -> str:
        return "".join(json.dumps(d) + "\n" for d in self.decisions)


def smooth_tracker(recording: Recording, mode: str = "batch", gating: bool = True,
                   options: TrackerOptions | None = None, covariance: bool = True,
                   progress=quiet) -> TrackerResult:
    """Smooth a tracker recording: ``'fixed-lag'`` / ``'isam2'`` give the online (filtered) poses, ``'batch'``
    runs the online pass for the gating decisions and then Levenberg-Marquardt over every keyframe.
    ``progress(stage, done, total)`` counts the seconds of recording passed (:mod:`selfcal.core.progress`)."""
    if mode not in MODES:
        raise ValueError(f"unknown mode {mode!r}; known: {', '.join(MODES)}")
    meta = {name: s.meta for name, s in recording.sensors.items()}
    if options is None:
        g = GatingOptions() if gating else UNGATED
        options = TrackerOptions(mode="isam2" if mode == "isam2" else "fixed-lag", gating=g,
                                 keep_graph=(mode == "batch"))
    tracker = OnlineTracker(noise_from_meta(meta), options=options)
    start = time.perf_counter()
    outputs = []
    events = recording_events(recording)
    t_first_ns, t_last_ns = (recording.sensors["imu0"].t_ns[[0, -1]] if "imu0" in recording.sensors else (0, 0))
    duration_s = int((t_last_ns - t_first_ns) * 1e-9)
    second = -1
    for name, t, values in events:
        if (t - t_first_ns) // 1_000_000_000 != second:  # once per second of recording, not per sample
            second = (t - t_first_ns) // 1_000_000_000
            progress("online pass (s of recording)", int(min(max(second, 0), duration_s)), duration_s)
        outputs.extend(tracker.push(name, t, values))
    if not outputs:
        raise RecordingError(f"{recording.path}: no pose: the tracker, inclinometer and camera never all reported")
    decisions = [d for o in outputs for d in o["decisions"]]
    faults = [o["faults"] for o in outputs]
    if mode == "batch":
        progress("batch smoothing (LM over every keyframe" + (", covariance)" if covariance else ")"))
        t_ns, poses, covs = batch_smooth(tracker.estimator, covariance=covariance)
        position = np.array([p.translation() for p in poses])
        quats = np.array([[q.x(), q.y(), q.z(), q.w()] for q in (p.rotation().toQuaternion() for p in poses)])
        cov = np.array(covs) if covs is not None else None
        faults = [{}] + faults  # the first keyframe has no output of its own
    else:
        t_ns = np.array([o["t_ns"] for o in outputs], dtype=np.int64)
        position = np.array([o["position"] for o in outputs])
        quats = np.array([o["quaternion"] for o in outputs])
        cov = np.array([o["covariance"] for o in outputs]) if outputs[0]["covariance"] is not None else None
    counts = dict(tracker.estimator.counts)
    check_agreement(recording.path, counts)
    return TrackerResult(t_ns, position, quats, cov, faults, decisions, mode, time.perf_counter() - start, counts)


MAX_REJECTED_FRACTION = 0.25


def check_agreement(where, counts: dict) -> None:
    """Refuse a run whose sensors disagree with the model throughout.  The chi-square gate rejects a good
    measurement with probability ``gate_alpha`` (1e-4) and the default fault schedule of the simulator rejects
    under 5 %; a quarter of all measurements rejected is no fault to gate out but a model that does not hold (a
    gyro in deg/s on a near-still TBM, where no sanity check can see it, rejects 45 %)."""
    judged = counts.get("accepted", 0) + counts.get("rejected", 0)
    if judged and counts.get("rejected", 0) > MAX_REJECTED_FRACTION * judged:
        raise RecordingError(f"{where}: {counts['rejected']} of {judged} measurements failed the chi-square "
                             "gate: the IMU and the other sensors disagree throughout, not a fault to gate out; check "
                             "units (gyro in rad/s?) and the sensor.yaml noise")


def patent_baseline(recording: Recording, use_fading: bool = True, use_fault_detection: bool = True):
    """Patent 004's filter (:mod:`selfcal.baselines.tracker`) on a recording, same sensor model."""
    from selfcal.baselines.tracker import Patent004Filter, Patent004Params
    n = noise_from_meta({name: s.meta for name, s in recording.sensors.items()})
    params = Patent004Params(
        tracker_sigma_m=n.tracker_sigma_m, tracker_velocity_sigma_m_s=n.tracker_velocity_sigma_m_s,
        incl_sigma_rad=n.incl_sigma_rad, cam_sigma_rad=n.cam_sigma_rad, gyro_noise_density=n.gyro_noise_density,
        accel_noise_density=n.accel_noise_density, gyro_random_walk=n.gyro_random_walk,
        accel_random_walk=n.accel_random_walk, gravity_m_s2=n.gravity_m_s2, r_P_B=n.r_P_B, r_C_B=n.r_C_B,
        R_B_C=n.R_B_C, camera_matrix=n.camera_matrix, dist_coeffs=n.dist_coeffs, tracker_W=n.tracker_W,
        use_fading=use_fading, use_fault_detection=use_fault_detection)
    imu = recording.imu("imu0")
    tr, inc, cam = (recording.sensors[s] for s in ("tracker0", "incl0", "cam0"))
    vel = np.column_stack([tr.values[c] for c in ("vx", "vy", "vz")]) if "vx" in tr.values else None
    return Patent004Filter(params).run(
        imu.t_ns, imu.gyro_rad_s, imu.accel_m_s2, tr.t_ns, np.column_stack([tr.values[c] for c in "xyz"]), vel,
        inc.t_ns, np.column_stack([inc.values["roll"], inc.values["pitch"]]), cam.t_ns,
        np.column_stack([cam.values["u"], cam.values["v"]]))


def estimator_for_audit(recording: Recording, keyframe_s: float = 0.2) -> TrackerEstimator:
    """The online pass over a recording (no gating) with every factor and its measurement kept: the input of
    :class:`selfcal.audit.tracker.TrackerAudit` (``selfcal audit REC --system tracker``)."""
    meta = {name: s.meta for name, s in recording.sensors.items()}
    # every sample enters: gating would hold out exactly the sensor whose calibration error the audit is to
    # find (a biased inclinometer disagrees with the camera); the vibration model stays
    options = TrackerOptions(mode="fixed-lag", keyframe_s=keyframe_s, keep_graph=True,
                             gating=UNGATED)
    tracker = OnlineTracker(noise_from_meta(meta), options=options)
    for name, t, values in recording_events(recording):
        tracker.push(name, t, values)
    if tracker.estimator.k < 0:
        raise RecordingError(f"{recording.path}: no pose: the tracker, inclinometer and camera never all reported")
    return tracker.estimator


def audit_system(recording: Recording, base: str = "smoother", sensors: list[str] | None = None):
    """The audit's view of a tracker recording: the ungated online pass with every factor kept, and the
    recording's auxiliary columns as drivers of the generic term library."""
    from selfcal.audit.tracker import TrackerAudit
    return TrackerAudit(estimator_for_audit(recording), channels=auxiliary_channels(recording))


KNOWN_COLUMNS = {**{name: set(columns) for name, columns in REQUIRED.items()},
                 "tracker0": {"x", "y", "z", "vx", "vy", "vz"}}


def auxiliary_channels(recording: Recording) -> dict[str, tuple]:
    """Every column of the four sensors that is not one of the system's own (``temperature [degC]`` ...):
    ``name -> (t_ns, values, unit)``; a name two sensors share is prefixed with the sensor (``incl0.temperature``)."""
    found = [(sensor, column) for sensor in REQUIRED if sensor in recording.sensors
             for column in recording.sensors[sensor].values if column not in KNOWN_COLUMNS[sensor]]
    names = [column for _, column in found]
    out = {}
    for sensor, column in found:
        s = recording.sensors[sensor]
        name = column if names.count(column) == 1 else f"{sensor}.{column}"
        out[name] = (np.asarray(s.t_ns), np.asarray(s.values[column], dtype=float), s.units.get(column, ""))
    return out


def online_estimator(meta: dict[str, dict]):
    """``selfcal track --system tracker``: the gated online estimator, configured from sensor.yaml contents."""
    return OnlineTracker(noise=noise_from_meta(meta))
