"""Open-world recall: effects no catalog lists, hidden in generated IMU recordings, over many seeds.

Suites (the audit is not told; each raw output is changed after the simulation):

* ``quadratic_temperature``: accelerometer bias ``c (T - 25)^2``, T cycling 15..35 degC (named poly2 in
  temperature, not ``bias_temperature``);
* ``scale_drift``: gyro x scale ``1 + k (T - 25)`` (a product of ``w_x`` and temperature);
* ``warm_up``: gyro bias ``b0 exp(-t / tau)``, tau half the recording (a polynomial in time, replacing the
  linear ``bias_drift``);
* ``bias_jump``: a static log whose gyro bias jumps at 62 % (a step in time);
* ``null`` and ``static_null``: nothing outside the base model.

Per suite: recall (the finding names the right target, driver and form), coverage of the size (the quadratic
coefficient, the scale drift, the step: within 3 reported sigma; the warm-up is compared only by form), false
findings per recording (any other finding), and the time of the library search against the whole audit.
Usage:

    .venv/bin/python benchmarks/audit_open_world.py [--quick] [--seeds 20] [--json out.json]
"""
from __future__ import annotations

import argparse
import time

import numpy as np

import _schema
from selfcal.audit.engine import run_audit
from selfcal.audit.imu.intrinsics import ImuIntrinsicsAudit
from selfcal.audit.imu.static import ImuStaticAudit
from selfcal.core.inertial import ImuNoise
from selfcal.io.recording import Recording, imu_sensor
from selfcal.sim.imu import ImuScenario, random_intrinsics
from selfcal.sim.trajectories import MultiPositionTrajectory

WHITE = ImuNoise(accelerometer_random_walk=0.0, gyroscope_random_walk=0.0)
RATE_HZ = 100.0
ACCEL = ("a_RS_S_x", "a_RS_S_y", "a_RS_S_z")
GYRO = ("w_RS_S_x", "w_RS_S_y", "w_RS_S_z")
ACCEL_T2 = np.array([2e-4, -1.5e-4, 2.5e-4])  # m s^-2 per degC^2
SCALE_PER_DEGC = 2e-3
WARM_UP = np.array([3e-3, -2e-3, 2.5e-3])  # rad s^-1
GYRO_STEP = np.array([4e-4, -3e-4, 2e-4])  # rad s^-1


def multi_position(seed: int, temperature: bool) -> Recording:
    trajectory = MultiPositionTrajectory(n_poses=24, seed=seed)
    accel, gyro = random_intrinsics(seed)
    cycle = (lambda t: 25.0 + 10.0 * np.sin(2 * np.pi * np.asarray(t, float) / trajectory.duration_s)) \
        if temperature else None
    return ImuScenario(trajectory, accel=accel, gyro=gyro, noise=WHITE, rate_hz=RATE_HZ,
                       temperature=cycle).perturbed_measurements(seed)


def static_log(seed: int, jump: bool, duration_s: float = 240.0) -> Recording:
    rng = np.random.default_rng(seed)
    n = int(duration_s * RATE_HZ)
    t_ns = np.arange(n, dtype=np.int64) * int(1e9 / RATE_HZ)
    accel_sigma, gyro_sigma = WHITE.white_sigma(RATE_HZ)
    accel = np.array([0.1, -0.2, 9.80665]) + accel_sigma * rng.standard_normal((n, 3))
    gyro = np.array([1e-3, 2e-3, -1e-3]) + gyro_sigma * rng.standard_normal((n, 3))
    if jump:
        gyro[int(0.62 * n):] += GYRO_STEP
    return Recording(None, {"imu0": imu_sensor("imu0", t_ns, gyro, accel, meta={"rate_hz": RATE_HZ})})


def hide(rec: Recording, columns, offset) -> Recording:
    values = rec.sensors["imu0"].values
    for j, name in enumerate(columns):
        values[name] = values[name] + offset[:, j]
    return rec


def case(suite: str, seed: int):
    """(audit system, expected (target, driver, form) or None, truth check(finding) -> bool or None)."""
    if suite in ("bias_jump", "static_null"):
        system = ImuStaticAudit(static_log(seed, suite == "bias_jump").imu("imu0"))
        if suite == "static_null":
            return system, None, None
        return system, ("imu0/gyro", "time", "step"), lambda f: _within(f["estimate"]["step"], f["std"]["step"],
                                                                         GYRO_STEP)
    rec = multi_position(seed, suite in ("quadratic_temperature", "scale_drift"))
    values = rec.sensors["imu0"].values
    t_s = (rec.sensors["imu0"].t_ns - rec.sensors["imu0"].t_ns[0]) * 1e-9
    expected, check = None, None
    if suite == "quadratic_temperature":
        hide(rec, ACCEL, np.outer((values["temperature"] - 25.0) ** 2, ACCEL_T2))
        expected = ("imu0/accel", "temperature", "poly2")
        check = lambda f: _within(f["estimate"]["coefficients"][1], f["std"]["coefficients"][1], ACCEL_T2)  # noqa: E731
    elif suite == "scale_drift":
        offset = np.zeros((len(t_s), 3))
        offset[:, 0] = SCALE_PER_DEGC * (values["temperature"] - 25.0) * values["w_RS_S_x"]
        hide(rec, GYRO, offset)
        expected = ("imu0/gyro_motion", "w_x", "product")
        check = lambda f: _within(f["estimate"]["coefficient"], f["std"]["coefficient"],  # noqa: E731
                                  [SCALE_PER_DEGC, 0, 0])
    elif suite == "warm_up":
        hide(rec, GYRO, np.outer(np.exp(-t_s / (t_s[-1] / 2)), WARM_UP))
        expected = ("imu0/gyro", "time", ("poly2", "poly3"))
    return ImuIntrinsicsAudit(rec.imu("imu0"), 9.80665, base="standard"), expected, check


def _within(estimate, std, truth) -> bool:
    estimate, std, truth = (np.asarray(x, dtype=float) for x in (estimate, std, truth))
    return bool(np.all(np.abs(estimate - truth) < 3 * std))


def matches(finding: dict, expected) -> bool:
    target, driver, form = expected
    forms = form if isinstance(form, tuple) else (form,)
    return (finding["effect"] == "unlisted" and finding["target"] == target and finding["driver"] == driver
            and finding["form"] in forms)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    _schema.add_arguments(parser, "audit_open_world")
    parser.add_argument("--seeds", type=int, default=None, help="recordings per suite (default 20, quick 3)")
    args = parser.parse_args()
    n = args.seeds or (3 if args.quick else 20)
    suites = ("quadratic_temperature", "scale_drift", "warm_up", "bias_jump", "null", "static_null")
    start = time.perf_counter()
    rows, table = [], {}
    for suite in suites:
        named = sized = checked = false = 0
        audit_s = library_s = 0.0
        for seed in range(1000, 1000 + n):
            system, expected, check = case(suite, seed)
            marks = []
            t0 = time.perf_counter()
            result = run_audit(system, progress=lambda m: marks.append((time.perf_counter(), m)))
            t1 = time.perf_counter()
            audit_s += t1 - t0
            first_library = next((t for t, m in marks if "(library)" in m), t1)
            library_s += t1 - first_library
            hits = [f for f in result.findings if expected and matches(f, expected)]
            named += bool(hits)
            false += len(result.findings) - len(hits)
            if hits and check is not None:
                checked += 1
                sized += check(hits[0])
        recall = named / n if suite not in ("null", "static_null") else None
        coverage = sized / checked if checked else None
        table[suite] = {"recall": recall, "coverage_3sigma": coverage, "false_per_recording": false / n,
                        "audit_s_per_recording": audit_s / n, "library_share": library_s / max(audit_s, 1e-9)}
        print(f"{suite:22s} recall {'-' if recall is None else f'{recall:.2f}':>5}  size within 3 sigma "
              f"{'-' if coverage is None else f'{coverage:.2f}':>5}  false findings/recording {false / n:.2f}  "
              f"audit {audit_s / n:5.1f} s (library {100 * library_s / max(audit_s, 1e-9):3.0f} %)", flush=True)
        if recall is not None:
            rows.append(_schema.row(f"{suite}: recall", "fraction", recall, None, "higher"))
        if coverage is not None:
            rows.append(_schema.row(f"{suite}: size within 3 sigma", "fraction", coverage, None, "higher"))
        rows.append(_schema.row(f"{suite}: false findings per recording", "count", false / n, None, "lower"))
    _schema.write(args.json, "audit_open_world", "audit", args.quick, time.perf_counter() - start, rows,
                  extra={"seeds": n, "suites": table})


if __name__ == "__main__":
    main()
