"""Catalog recall of the audit on every audited system: is each catalog effect named, under its own name, on any
seed, sized within 3 of the sigmas the audit reports, and is nothing else named?

Per system and planted effect, ``--seeds`` recordings (default 20) each hide that one effect at a stated size;
per system ``--null-seeds`` recordings (default 20) hide nothing.  Counted per case:

* recall: the planted effect named with the right name (and target),
* recall where determined: over the seeds where the planted size is at least ``DETERMINED`` (5) of the sigmas the
  audit reports for it (where it was missed: fitted on top of the base and of the catalog effects named in its
  place; where it was named with look-alikes flagged in ``ambiguous_with``: fitted beside those too.  A look-alike
  the data cannot tell from it leaves it undetermined): a miss below that is the data's,
* named as an ambiguous look-alike: a rival named instead that says, in ``ambiguous_with``, it cannot be told
  from the planted effect (not counted as a false finding, nor as recall),
* size within 3 sigma: every entry of its estimate within 3 reported sigma of the truth (over the named ones),
* size in sigma: the median over seeds of |truth| / reported sigma (the planted size as the audit measures it;
  the largest entry for a vector),
* false findings per recording: findings of anything not planted (on the nulls: every finding),
* seconds per audit (the lead schedules the full run with these).

Every catalog entry of every system is planted (the encoder's ``eccentricity`` is not offered where the edges are
free: no self-calibration separates it from the graduation, tests/test_encoder_mixed_multi.py), and the IMU's
scale, misalignment and drift entries on the ``bias`` base (the main job's).  The planting code is the systems'
tests' (scenarios and sizes), ``audit_recall.py`` (imu, imu-pair) and ``audit_open_world_systems.py`` (qc,
encoder, ship and scan library suites).  Usage:

    .venv/bin/python benchmarks/audit_catalog_recall.py [--quick] [--seeds 20] [--null-seeds 20]
        [--systems tracker,imu] [--cases TEXT] [--jobs 2] [--json out.json]
    .venv/bin/python benchmarks/audit_catalog_recall.py --merge A.json B.json --json out.json

``--quick``: 2 seeds per effect and 2 nulls per system (a smoke run, not a figure).
"""
from __future__ import annotations

import argparse
import time
from concurrent.futures import ProcessPoolExecutor
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

import _schema
import audit_open_world_systems as open_world
import audit_recall as recall
from selfcal.audit.engine import run_audit
from selfcal.core.errors import SelfcalError


@dataclass
class Planted:
    """What the audit should name, and the truth of its estimate entry (None: named, size not checked)."""

    effect: str
    target: str | None  # residual family label; None: any
    key: str | None
    truth: object
    driver: tuple | None = None  # for effect "unlisted": (driver, forms)
    check: Callable[[dict], bool] | None = None  # a size check of its own (the open-world suites')
    planted_size: object = None  # the planted change where the truth is not it (a lever arm: truth - nominal)


@dataclass
class Case:
    system: str
    name: str  # effect planted, or "null"
    size: str  # the planted size, stated
    make: Callable[[int], tuple[object, list[Planted], tuple[str, ...]]]  # seed -> (audit system, planted, allowed)


# --- tracker: the calibration run of tests/test_tracker_audit.py ------------------------------------------------

TRACKER_STEERED = dict(steer_position_m=(0.02, 0.05), steer_position_period_s=(4.0, 8.0),
                       steer_position_axes=(0.0, 0.0, 1.0))  # the clock offset needs the target to move: steered
# up and down by 2-5 cm a 24 ms offset is ~5 of its sigmas (tests/test_tracker_audit.py steers 5-10 cm: ~12)


def tracker_system(seed: int, nominal_lever_error_m=None, duration_s: float = 20.0, **effects):
    from selfcal.audit.tracker import TrackerAudit
    from selfcal.pipelines.tracker import estimator_for_audit
    from selfcal.sim.tracker import TrackerScenario
    sc = TrackerScenario(duration_s=duration_s, seed=seed, **{"burst_rate_per_min": 6.0, **effects},
                         steer_angle_deg=(1.0, 2.0), steer_period_s=(20.0, 40.0))
    rec = sc.measurements(seed=1000 + seed)
    if nominal_lever_error_m is not None:  # sensor.yaml states a lever arm that is wrong by this much
        rec.sensors["tracker0"].meta["lever_arm_prism_m"] = (sc.r_P_B + nominal_lever_error_m).tolist()
    return sc, TrackerAudit(estimator_for_audit(rec))


def tracker_case(effect: str, size: str, key: str, truth, nominal_lever_error_m=None, **effects) -> Case:
    target = {"lever_arm_prism": "tracker0/position", "tracker_time_offset": "tracker0/position"}.get(effect,
                                                                                                    "incl0/tilt")

    def make(seed):
        sc, system = tracker_system(seed, nominal_lever_error_m, **effects)
        if effect == "lever_arm_prism":  # the truth is sensor.yaml's lever arm less the error it states
            return system, [Planted(effect, target, key, sc.r_P_B, planted_size=nominal_lever_error_m)], ()
        return system, [Planted(effect, target, key, truth)], ()
    return Case("tracker", effect, size, make)


TRACKER = [
    tracker_case("tracker_time_offset", "24 ms (steered 2-5 cm at 4-8 s)", "dt_s", 0.024,
                 tracker_clock_offset_s=0.024, **TRACKER_STEERED),
    tracker_case("incl_bias", "(1.1, 4.2) mrad", "bias", [1.1e-3, 4.2e-3], incl_bias_rad=(1.1e-3, 4.2e-3)),
    tracker_case("lever_arm_prism", "3 cm (height)", "r_m", None, nominal_lever_error_m=np.array([0.0, 0.0, 0.03])),
    tracker_case("incl_scale", "0.02", "scale", 0.02, incl_scale=0.02),
    tracker_case("incl_accel_sensitivity", "0.3 (60 s: it shows only in vibration bursts, 6 per min)", "sensitivity",
                 0.3, incl_accel_sensitivity=0.3, duration_s=60.0),
    Case("tracker", "null", "-", lambda seed: (tracker_system(seed)[1], [], ())),
]


# --- imu, imu-pair: audit_recall.py's types -------------------------------------------------------------------

def from_recall(system: str, make_case, effect: str, size: str) -> Case:
    def make(seed):
        case = make_case(seed)
        return case.system, [Planted(p.effect, p.target, p.key, p.truth) for p in case.planted], ()
    return Case(system, effect, size, make)


IMU = [from_recall("imu", recall.g_sensitivity, "gyro_g_sensitivity", f"{recall.G_SENSITIVITY} rad/s per m/s^2"),
       from_recall("imu", recall.temperature_gyro, "bias_temperature (gyro)",
                   f"{recall.GYRO_TEMPERATURE_SLOPE} rad/s per degC"),
       from_recall("imu", recall.temperature_accel, "bias_temperature (accel)",
                   f"{recall.ACCEL_TEMPERATURE_SLOPE} m/s^2 per degC"),
       from_recall("imu", recall.fan_accel, "channel:fan_speed (accel)", "3e-5 m/s^2 per rpm"),
       from_recall("imu", recall.fan_gyro, "channel:fan_speed (gyro)", "3e-6 rad/s per rpm"),
       Case("imu", "null", "-", lambda seed: (recall.null_single(seed).system, [], ()))]
IMU_PAIR = [from_recall("imu-pair", recall.time_offset, "time_offset", f"{recall.TIME_OFFSET_S * 1e3:g} ms"),
            from_recall("imu-pair", recall.lever_arm, "lever_arm", f"{recall.LEVER_ARM_M} m"),
            Case("imu-pair", "null", "-", lambda seed: (recall.null_pair(seed).system, [], ()))]


# --- imu on the bias-only base: its scale, misalignment and drift entries (the main job's base) -----------------

def imu_bias_base(seed: int, accel: dict, gyro: dict, drift: tuple[str, np.ndarray] | None = None):
    """A multi-position run whose accelerometer and gyro each have only the errors in ``accel`` / ``gyro``
    (random_intrinsics' keywords; the rest zero, biases always), audited on the ``bias`` base; ``drift``:
    (``accel`` or ``gyro``, slope per s) added to the raw output linearly in time."""
    from selfcal.audit.imu.intrinsics import ImuIntrinsicsAudit
    from selfcal.sim.imu import ImuScenario, random_intrinsics
    from selfcal.sim.trajectories import MultiPositionTrajectory
    zero = dict(scale=(0.0, 0.0), misalignment_rad=0.0, gyro_axis_rotation_rad=0.0)
    a, _ = random_intrinsics(seed, **{**zero, **accel})
    _, g = random_intrinsics(seed + 1, **{**zero, **gyro})
    sc = ImuScenario(MultiPositionTrajectory(n_poses=recall.N_POSES, seed=seed), accel=a, gyro=g, noise=recall.WHITE,
                     rate_hz=recall.RATE_HZ)
    data = sc.perturbed_measurements(seed).imu("imu0")
    if drift is not None:
        column = data.accel_m_s2 if drift[0] == "accel" else data.gyro_rad_s
        column += data.t_s[:, None] * np.asarray(drift[1])[None, :]
    return sc, ImuIntrinsicsAudit(data, sc.gravity_m_s2, base="bias")


def scale_of(M: np.ndarray) -> np.ndarray:
    """The catalog's scale entries of a calibration matrix M = T K (T unit diagonal): 1 / K - 1."""
    return 1.0 / np.diag(M) - 1.0


def angles_of(M: np.ndarray, accel: bool) -> np.ndarray:
    """The catalog's misalignment entries of M (the audit's convention: T = M / K; Tedaldi's signs for the
    accelerometer's upper triangle, every off-diagonal entry row-major for the gyro)."""
    T = M / np.diag(M)[None, :]
    if accel:
        return np.array([-T[0, 1], T[0, 2], -T[1, 2]])
    return np.array([T[i, j] for i in range(3) for j in range(3) if i != j])


SCALE = dict(scale=(0.005, 0.02))  # 0.5-2 % per axis, random signs
SKEW = dict(misalignment_rad=1e-3, gyro_axis_rotation_rad=1e-3)  # ~1 mrad each angle
ACCEL_DRIFT = np.array([4e-5, -3e-5, 5e-5])  # m s^-2 per s: ~10 mg over the run of ~400 s
GYRO_DRIFT = np.array([4e-6, -3e-6, 5e-6])  # rad s^-1 per s


def imu_bias_case(name: str, size: str, key: str, truth_of, accel=None, gyro=None, drift=None) -> Case:
    """``name``: the effect, or ``effect (accel)`` / ``effect (gyro)`` for the one of that triad."""
    effect, _, triad = name.partition(" (")
    target = f"imu0/{triad.rstrip(')')}" if triad else None

    def make(seed):
        sc, system = imu_bias_base(seed, accel or {}, gyro or {}, drift)
        return system, [Planted(effect, target, key, truth_of(sc))], ()
    return Case("imu", name, size, make)


IMU_BIAS_BASE = [
    imu_bias_case("accel_scale", "0.5-2 % per axis (base bias)", "scale", lambda sc: scale_of(sc.accel.M), accel=SCALE),
    imu_bias_case("gyro_scale", "0.5-2 % per axis (base bias)", "scale", lambda sc: scale_of(sc.gyro.M), gyro=SCALE),
    imu_bias_case("accel_misalignment", "~1 mrad per angle (base bias)", "angles",
                  lambda sc: angles_of(sc.accel.M, True), accel=SKEW),
    imu_bias_case("gyro_misalignment", "~1 mrad per angle + 1 mrad axis rotation (base bias)", "angles",
                  lambda sc: angles_of(sc.gyro.M, False), gyro=SKEW),
    imu_bias_case("bias_drift (accel)", "(4, -3, 5)e-5 m/s^2 per s (base bias)", "slope", lambda sc: ACCEL_DRIFT,
                  drift=("accel", ACCEL_DRIFT)),
    imu_bias_case("bias_drift (gyro)", "(4, -3, 5)e-6 rad/s per s (base bias)", "slope", lambda sc: GYRO_DRIFT,
                  drift=("gyro", GYRO_DRIFT)),
    Case("imu", "null (base bias)", "-", lambda seed: (imu_bias_base(seed, {}, {})[1], [], ())),
]


# --- imu-pair: the relative-gain and axis-rotation entries ------------------------------------------------------

def pair_gains_case(effect: str) -> Case:
    """Each IMU with its own scale and misalignment (audit_recall.relative_gains): both relative gains are real,
    and each gyro triad's own rotation is the accelerometer axis rotation: named beside it, not false."""
    target = {"accel_relative_gain": "imu1/pair_accel", "gyro_relative_gain": "imu1/pair_gyro"}[effect]
    allowed = ("accel_relative_gain", "gyro_relative_gain", "accel_axis_rotation")

    def make(seed):
        return recall.relative_gains(seed).system, [Planted(effect, target, None, None)], allowed
    return Case("imu-pair", effect, "own scale 0.5-2 % and ~1 mrad misalignment per IMU", make)


def pair_axis_rotation(seed: int):
    """Each IMU's gyro triad rotated by its own ~5 mrad (tests/test_audit_hidden_effects.py): the accelerometers
    see the pair rotation off by R^T rho0 - rho1."""
    from dataclasses import replace
    from scipy.spatial.transform import Rotation
    from selfcal.audit.imu_pair import ImuPairAudit
    from selfcal.sim.imu import random_intrinsics
    sc, _ = recall.pair(seed)
    gyros = [random_intrinsics(sub, scale=(0.0, 0.0), misalignment_rad=0.0, gyro_axis_rotation_rad=5e-3)[1]
             for sub in (10 + seed, 20 + seed)]
    sc = replace(sc, gyro0=replace(sc.gyro0, M=gyros[0].M), gyro1=replace(sc.gyro1, M=gyros[1].M))
    rec = sc.perturbed_measurements(seed)
    rho0, rho1 = (Rotation.from_matrix(g.M).as_rotvec() for g in gyros)
    truth = sc.R_imu0_imu1.T @ rho0 - rho1
    return ImuPairAudit(rec.imu("imu0"), rec.imu("imu1")), [Planted("accel_axis_rotation", "imu1/pair_accel",
                                                                    "rho_rad", truth)], ()


IMU_PAIR_GAINS = [pair_gains_case("accel_relative_gain"), pair_gains_case("gyro_relative_gain"),
                  Case("imu-pair", "accel_axis_rotation", "~5 mrad gyro triad rotation per IMU", pair_axis_rotation)]


# --- ship, encoder, scan: their catalogs (the scenarios of their tests) -------------------------------------------

def ship_catalog_case(effect: str, size: str, key: str, truth, kind: str, duration_s: float, **effects) -> Case:
    def make(seed):
        from selfcal.audit.ship import ShipAudit
        from selfcal.pipelines.ship import ship_inputs
        from selfcal.sim.ship import ShipScenario
        rec = ShipScenario(kind=kind, duration_s=duration_s, seed=seed, **{"lever_arm_m": (0.0, 0.0, 0.0), **effects}
                           ).perturbed_measurements(100 + seed)
        return ShipAudit(ship_inputs(rec), keyframe_s=1.0), [Planted(effect, None, key, truth)], ()
    return Case("ship", effect, size, make)


SHIP = [ship_catalog_case("lever_arm", "(2, 0.5, 5) m (heave 90 s)", "r_m", [2.0, 0.5, 5.0], "heave", 90.0,
                          lever_arm_m=(2.0, 0.5, 5.0)),
        ship_catalog_case("gyro_scale", "(2, 2, 0) % (heave 90 s)", "scale", [0.02, 0.02, 0.0], "heave", 90.0,
                          gyro_scale=(0.02, 0.02, 0.0)),
        ship_catalog_case("speed_log_scale", "10 % (turning 240 s)", "scale", 0.10, "turning", 240.0,
                          speed_log_scale=1.10)]


TINY_ENCODER = dict(l=5, n_diodes=64, n_positions=24, cells_per_image=12.0)  # tests/test_encoder_audit.py


def encoder_catalog_case(effect: str, size: str, key: str, truth_of, **effects) -> Case:
    def make(seed):
        from selfcal.pipelines import encoder as pe
        from selfcal.sim.encoder import EncoderScenario
        sc = EncoderScenario(seed=seed, **TINY_ENCODER, **effects)
        rec, _ = sc.perturbed_measurements(seed)
        system = pe.audit_system(rec, frames={"array0": sc.perturbed_frames(seed)})
        return system, [Planted(effect, None, key, truth_of(sc))], ()
    return Case("encoder", effect, size, make)


ENCODER = [encoder_catalog_case("prnu", "1 % per diode", "gain", lambda sc: sc.gain[0], prnu_sigma=0.01),
           encoder_catalog_case("temperature_scale", "2e-4 per degC over 10 degC", "k_per_degC", lambda sc: 2e-4,
                                temperature_scale_per_degC=2e-4, temperature_range_degC=10.0)]


def scan_catalog_case(effect: str, size: str, key: str, truth, length_m: float, n_spheres: int, **effects) -> Case:
    def make(seed):
        from scan_helpers import scan_data
        from selfcal.audit.scan import ScanAudit
        from selfcal.pipelines.scan import scan_problem
        from selfcal.sim.scan import ScanScenario, simulate_scan
        sim = simulate_scan(ScanScenario(length_m=length_m, n_spheres=n_spheres, **effects), seed=seed)
        return ScanAudit(scan_problem(scan_data(sim))), [Planted(effect, None, key, truth)], ()
    return Case("scan", effect, size, make)


SWAY = dict(roll_deg=1.0, sway_m=0.02)  # the vehicle rolls and sways: the clock offset and gyro scale show
SCAN = [scan_catalog_case("sphere_radius", "0.5 mm (8 m, 4 spheres)", "dR_m", 5e-4, 8.0, 4, sphere_radius_error_m=5e-4),
        scan_catalog_case("time_offset", "20 ms (12 m, 6 spheres, rolling 1 deg, swaying 2 cm)", "dt_s", 0.02, 12.0, 6,
                          time_offset_s=0.02, **SWAY),
        scan_catalog_case("accel_scale", "1 % along track (12 m, 6 spheres, 0.05-0.95 m/s)", "scale",
                          [0.01, 0.0, 0.0], 12.0, 6, accel_scale=np.array([0.01, 0.0, 0.0]), speed_change_m_s=0.45),
        scan_catalog_case("gyro_scale", "2 % per axis (12 m, 6 spheres, rolling 1 deg, swaying 2 cm)", "scale",
                          [0.02, 0.02, 0.02], 12.0, 6, gyro_scale=np.array([0.02, 0.02, 0.02]), **SWAY),
        scan_catalog_case("extrinsic_rotation", "(20, -10, 15) mrad (8 m, 4 spheres)", "angles",
                          [2e-2, -1e-2, 1.5e-2], 8.0, 4, extrinsic_rotation_rad=np.array([2e-2, -1e-2, 1.5e-2]))]


# --- qc, encoder, ship, scan: audit_open_world_systems.py's suites -----------------------------------------------

def from_open_world(system: str, suite: str, size: str) -> Case:
    make_suite = open_world.SYSTEMS[system][0]

    def make(seed):
        audit, expected, check, allowed = make_suite(suite, seed)
        if expected is None:
            return audit, [], allowed
        driver = (expected[1], expected[2]) if expected[0] == "unlisted" else None
        return audit, [Planted(expected[0], None, None, None, driver, check)], allowed
    return Case(system, "null" if "null" in suite else suite, size, make)


OPEN_WORLD = [from_open_world("qc", "radius", "5 mm"), from_open_world("qc", "range_offset", "3 cm"),
              from_open_world("qc", "null", "-"),
              from_open_world("encoder", "compression", "5 % of full scale (library term)"),
              from_open_world("encoder", "null", "-"),
              from_open_world("ship", "heading", "0.1 m/s^2 (library term)"), from_open_world("ship", "null", "-"),
              from_open_world("scan", "range", "2 % of range (library term)"), from_open_world("scan", "null", "-")]

CASES = TRACKER + IMU + IMU_BIAS_BASE + IMU_PAIR + IMU_PAIR_GAINS + OPEN_WORLD + SHIP + ENCODER + SCAN
SYSTEMS = list(dict.fromkeys(c.system for c in CASES))


DETERMINED = 5.0  # reported sigmas: the score test's threshold (1e-3 / ~5 candidates: F ~ 14, 3.7 sigma for one
# parameter) is passed with ~90 % power at 5 sigma; below it a miss is the data's, not the rule's

# --- scoring --------------------------------------------------------------------------------------------------

def _named(finding: dict, planted: Planted) -> bool:
    if finding["effect"] != planted.effect or (planted.target and finding["target"] != planted.target):
        return False
    return planted.driver is None or (finding.get("driver") == planted.driver[0]
                                      and finding.get("form") in planted.driver[1])


def _size_in_sigma_when_fitted(system, planted: Planted, beside: tuple = ()) -> float | None:
    """|planted size| / the sigma the audit would report, fitting the missed catalog effect on top of the base and
    of the catalog effects ``beside`` ((effect, target) pairs): how many of its own sigmas the effect stood in these
    data (a miss at 2 sigma is the data's, not the rule's).  Beside the catalog effects the audit named in its place,
    it says whether these data tell the two apart at all: a 3 cm prism height stands at 30-40 of its sigmas alone
    and at ~1 beside the inclinometer pitch bias it looks like (the camera sees both as one beam elevation)."""
    candidates = system.candidates()
    cand = next((c for c in candidates if c.effect == planted.effect
                 and (planted.target is None or c.label == planted.target)), None)
    if cand is None:  # not offered on this recording (e.g. nothing it could be told from)
        return None
    others = tuple(c for c in candidates if (c.effect, c.label) in beside and c != cand)
    fit = system.fit(tuple(system.base_effects) + others + (cand,))
    _, std = system.estimate(fit, cand)
    sigma = np.ravel(np.asarray(std[planted.key], float))
    size = np.ravel(np.asarray(planted.truth if planted.planted_size is None else planted.planted_size, float))
    return float(np.max(np.abs(size) / sigma))


def run_one(case: Case, seed: int) -> dict:
    t0 = time.perf_counter()
    try:
        system, planted, allowed = case.make(seed)
        report = run_audit(system).to_json()
    except SelfcalError as err:  # a recording the audit refuses is counted, not a crash
        return {"seed": seed, "refused": str(err), "seconds": time.perf_counter() - t0}
    findings = report["findings"]
    out = {"seed": seed, "seconds": time.perf_counter() - t0,
           "named": [f"{f['effect']}@{f['target']}" for f in findings],
           "rejected": [f"{r['effect']}@{r['target']}: {r['reason']} (p {r['evidence']['p_value']:.2g})"
                        for r in report["rejected"]]}
    matched = set()
    for p in planted:
        hit = next((i for i, f in enumerate(findings) if _named(f, p)), None)
        out["recalled"] = hit is not None
        if hit is None:
            # named as a look-alike that says it cannot be told from the planted effect: honest, not a recall
            rival = next((i for i, f in enumerate(findings) if any(
                r["effect"] == p.effect and (p.target is None or r["target"] == p.target)
                for r in f.get("ambiguous_with", []))), None)
            if rival is not None:
                out["ambiguous"] = True
                matched.add(rival)
            if p.key is not None and p.driver is None:  # how well these data determine the missed effect
                out["size_in_sigma"] = _size_in_sigma_when_fitted(system, p)
                named = tuple((f["effect"], f["target"]) for f in findings if f["effect"] != "unlisted")
                out["determined_in_sigma"] = (_size_in_sigma_when_fitted(system, p, named) if named
                                              else out["size_in_sigma"])
            continue
        matched.add(hit)
        f = findings[hit]
        if p.check is not None:
            out["within_3_sigma"] = bool(p.check(f))
        elif p.key is not None:
            value = np.ravel(np.asarray(f["estimate"][p.key], float))  # a matrix compares entry by entry
            sigma = np.ravel(np.asarray(f["std"][p.key], float))
            truth = np.ravel(np.asarray(p.truth, float))
            out["within_3_sigma"] = bool(np.all(np.abs(value - truth) < 3 * sigma))
            out["z"] = ((value - truth) / sigma).tolist()
            size = np.ravel(np.asarray(p.truth if p.planted_size is None else p.planted_size, float))
            out["size_in_sigma"] = float(np.max(np.abs(size) / sigma))
            # the finding's sigma is beside all that was named; beside the look-alikes it flags as ambiguous too
            flagged = tuple((r["effect"], r["target"]) for r in f.get("ambiguous_with", [])
                            if r["effect"] != "unlisted")
            out["determined_in_sigma"] = (_size_in_sigma_when_fitted(system, p, flagged + tuple(
                (g["effect"], g["target"]) for g in findings if g is not f and g["effect"] != "unlisted"))
                if flagged else out["size_in_sigma"])
    out["false"] = [f"{f['effect']}@{f['target']}" for i, f in enumerate(findings)
                    if i not in matched and f["effect"] not in allowed]
    return out


def _run_planned(job) -> dict:
    """One audit in a worker process: (system, case name, seed) -> :func:`run_one`'s record."""
    system, name, seed = job
    return run_one(next(c for c in CASES if c.system == system and c.name == name), seed)


def summarise(case: Case, runs: list[dict]) -> dict:
    done = [r for r in runs if "refused" not in r]
    sized = [r["within_3_sigma"] for r in done if "within_3_sigma" in r]
    size_sigma = [r["size_in_sigma"] for r in done if "size_in_sigma" in r]
    entry = {"system": case.system, "effect": case.name, "planted_size": case.size, "recordings": len(runs),
             "refused": len(runs) - len(done),
             "false_per_recording": sum(len(r["false"]) for r in done) / max(len(done), 1),
             "false_findings": sorted({n for r in done for n in r["false"]}),
             "audit_s_per_recording": float(np.mean([r["seconds"] for r in runs])) if runs else None}
    if not case.name.startswith("null"):
        entry["recall"] = sum(r.get("recalled", False) for r in done) / max(len(done), 1)
        entry["missed_seeds"] = [r["seed"] for r in done if not r.get("recalled", False)]
        entry["named_as_ambiguous_look_alike"] = sum(r.get("ambiguous", False) for r in done) / max(len(done), 1)
    if sized:
        entry["size_within_3_sigma"] = sum(sized) / len(sized)
    if size_sigma:
        entry["planted_size_in_reported_sigma_median"] = float(np.median(size_sigma))
    beside = [r["determined_in_sigma"] for r in done if r.get("determined_in_sigma") is not None]
    if beside:
        entry["planted_size_in_sigma_beside_named_median"] = float(np.median(beside))
    if not case.name.startswith("null"):  # recall where the data determine the effect: planted >= DETERMINED reported sigmas
        determined = [r for r in done if r.get("determined_in_sigma", r.get("size_in_sigma")) is not None
                      and r.get("determined_in_sigma", r.get("size_in_sigma")) >= DETERMINED]
        entry["recordings_determined"] = len(determined)
        if determined:
            entry["recall_determined"] = sum(r.get("recalled", False) for r in determined) / len(determined)
    return entry


def write_results(args, cases: list[Case], runs_of: dict, seconds: float, n_effect: int, n_null: int,
                  final: bool) -> None:
    """Summaries, schema rows and the JSON of the audits done so far (printed when ``final``)."""
    rows, table = [], []
    for i, case in enumerate(cases):
        runs = runs_of[i]
        if not runs:
            continue
        n = len(runs)
        entry = summarise(case, runs)
        table.append({**entry, "runs": runs})
        label = f"{case.system}/{case.name}" + ("" if case.name.startswith("null") else f" at {case.size}")
        if not case.name.startswith("null"):
            rows.append(_schema.row(f"{label}: recall", "fraction", entry["recall"], better="higher",
                                    note=f"{n} seeds; no baseline"))
        if "recall_determined" in entry:
            rows.append(_schema.row(f"{label}: recall where planted >= {DETERMINED:g} reported sigma", "fraction",
                                    entry["recall_determined"], better="higher",
                                    note=f"{entry['recordings_determined']} of {n} seeds; no baseline"))
        if "size_within_3_sigma" in entry:
            rows.append(_schema.row(f"{label}: size within 3 sigma", "fraction", entry["size_within_3_sigma"],
                                    better="higher", note=f"{n} seeds; no baseline"))
        rows.append(_schema.row(f"{label}: false findings per recording", "count", entry["false_per_recording"],
                                note=f"{n} seeds; no baseline"))
        rows.append(_schema.row(f"{label}: audit time per recording", "s", entry["audit_s_per_recording"],
                                note=f"{args.jobs} parallel audits on 2 shared cores; no baseline"))
        if final:
            print(f"{label}: " + ", ".join(f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}"
                                           for k, v in entry.items() if k not in ("system", "effect", "planted_size")),
                  flush=True)
    _schema.write(args.json, "audit_catalog_recall", "audit", args.quick, seconds, rows,
                  {"seeds": n_effect, "null_seeds": n_null, "first_seed": args.first_seed, "jobs": args.jobs,
                   "complete": final, "cases": table})


def merge(args) -> None:
    """Every case's runs from the ``--merge`` files (a seed measured twice counts once), summarised again."""
    import json
    runs_by = {}
    seconds, jobs = 0.0, 1
    for path in args.merge:
        doc = json.loads(open(path).read())
        seconds += doc["seconds"]
        jobs = max(jobs, doc["extra"].get("jobs", 1))
        for table in doc["extra"]["cases"]:
            runs = runs_by.setdefault((table["system"], table["effect"]), {})
            runs.update({r["seed"]: r for r in table["runs"]})
    cases = [c for c in CASES if (c.system, c.name) in runs_by]
    runs_of = {i: sorted(runs_by[(c.system, c.name)].values(), key=lambda r: r["seed"]) for i, c in enumerate(cases)}
    seeds = [len(r) for i, r in runs_of.items() if not cases[i].name.startswith("null")]
    nulls = [len(r) for i, r in runs_of.items() if cases[i].name.startswith("null")]
    args.jobs, args.first_seed = jobs, min(r["seed"] for runs in runs_of.values() for r in runs)
    write_results(args, cases, runs_of, seconds, min(seeds, default=0), min(nulls, default=0), final=True)
    print(f"merged {len(args.merge)} files; results: {args.json}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    _schema.add_arguments(parser, "audit_catalog_recall")
    parser.add_argument("--seeds", type=int, default=None, help="recordings per planted effect (default 20)")
    parser.add_argument("--null-seeds", type=int, default=None, help="null recordings per system (default 20)")
    parser.add_argument("--first-seed", type=int, default=3000)
    parser.add_argument("--systems", default=",".join(SYSTEMS), help="comma-separated subset of " + ",".join(SYSTEMS))
    parser.add_argument("--cases", default="", help="comma-separated texts: only the cases whose effect name "
                        "contains one of them (e.g. incl_bias,tracker_time_offset,null)")
    parser.add_argument("--jobs", type=int, default=1, help="audits run in parallel processes (default 1)")
    parser.add_argument("--merge", nargs="+", default=None, metavar="JSON",
                        help="only combine the audits of earlier runs (e.g. seeds split over two machines) into "
                             "--json: each case's runs from every file, summarised again")
    args = parser.parse_args()
    if args.merge:
        merge(args)
        return
    n_effect = args.seeds or (2 if args.quick else _schema.DEFAULT_SEEDS)
    n_null = args.null_seeds or (2 if args.quick else _schema.DEFAULT_SEEDS)
    start = time.perf_counter()
    wanted = [w for w in args.cases.split(",")]
    cases = [c for c in CASES if c.system in args.systems.split(",") and any(w in c.name for w in wanted)]
    plan = sorted(((i, seed) for i, c in enumerate(cases)  # seed by seed: an early stop leaves every case measured
                   for seed in range(args.first_seed, args.first_seed + (n_null if c.name.startswith("null") else n_effect))),
                  key=lambda job: (job[1], job[0]))
    runs_of = {i: [] for i in range(len(cases))}
    with ProcessPoolExecutor(args.jobs) as pool:
        done = pool.map(_run_planned, [(cases[i].system, cases[i].name, seed) for i, seed in plan])
        for (i, seed), r in zip(plan, done):
            runs_of[i].append(r)
            print(f"  {cases[i].system}/{cases[i].name} seed {seed}: {r.get('named', r.get('refused'))} "
                  f"({r['seconds']:.1f} s)", flush=True)
            # written after every audit: a run stopped early keeps what it measured (seeds counted per case)
            write_results(args, cases, runs_of, time.perf_counter() - start, n_effect, n_null, final=False)
    write_results(args, cases, runs_of, time.perf_counter() - start, n_effect, n_null, final=True)
    print(f"total {time.perf_counter() - start:.0f} s; results: {args.json}")


if __name__ == "__main__":
    main()
