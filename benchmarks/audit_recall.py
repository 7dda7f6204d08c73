"""Audit recall: does the audit name effects it is not told about, estimate them honestly, and name nothing else?

A generated suite: several seeds per hidden-effect type (the cases of tests/test_audit_hidden_effects.py, plus
accelerometer-side variants) and null recordings with nothing outside the base model.  Per type it prints

* recall: fraction of planted effects named correctly (effect and residual target; for the time-collinear
  channel, named as either rival *with* the other reported in ``ambiguous_with``),
* coverage: fraction of estimated entries within 3 sigma of the truth, with the sigma the finding reports
  (``finding``) and with the audit's final model (``final fit``: every accepted effect in); 99.7 % when honest,
* z rms: RMS of (estimate - truth) / sigma over those entries (1 when the reported sigma is right; well
  below 1: sigma too pessimistic, above: too optimistic),
* false findings per recording: findings of effects that were not planted,

then the overall false-finding rate and the total time.  White noise only (no bias walk).  Usage:

    .venv/bin/python benchmarks/audit_recall.py [--quick] [--seeds 5] [--null-seeds 20] [--first-seed 1000]
        [--only TEXT] [--json out.json]

``--quick``: one recording per type (defaults of --seeds / --null-seeds become 1 / 1).
"""
from __future__ import annotations

import argparse
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from selfcal.audit.engine import run_audit
from selfcal.audit.imu_pair import ImuPairAudit
from selfcal.audit.imu.intrinsics import ImuIntrinsicsAudit
from selfcal.sim.imu import AuxChannel, ImuPairScenario, ImuScenario, random_intrinsics
from selfcal.core.inertial import ImuNoise
from selfcal.sim.trajectories import HandheldTrajectory, MultiPositionTrajectory

import _schema  # benchmarks/_schema.py: the results schema every benchmark writes

WHITE = ImuNoise(accelerometer_random_walk=0.0, gyroscope_random_walk=0.0)
RATE_HZ = 100.0
N_POSES = 24
Z_MAX = 3.0
G_SENSITIVITY = 1e-4  # rad s^-1 per m s^-2
GYRO_TEMPERATURE_SLOPE = 1e-4  # rad s^-1 per degC
ACCEL_TEMPERATURE_SLOPE = 2e-3  # m s^-2 per degC
FAN_ACCEL_SLOPE = np.array([3e-5, -2e-5, 4e-5])  # m s^-2 per rpm
FAN_GYRO_SLOPE = np.array([2e-6, -3e-6, 2.5e-6])  # rad s^-1 per rpm
HEATER_GYRO_SLOPE = np.array([0.02, -0.03, 0.025])  # rad s^-1 per A
HEATER_RAMP_A_PER_S = 0.002
TIME_OFFSET_S = 0.007
LEVER_ARM_M = 0.08


@dataclass
class Planted:
    """One hidden effect: what the audit should name, and the truth of its estimate key."""

    effect: str
    target: str
    key: str | None  # None: the effect must be named, its parameter has no simple truth to compare with
    truth: np.ndarray | None
    rival: Planted | None = None  # an equivalent explanation the audit may name instead, with ambiguity


@dataclass
class Case:
    kind: str
    system: object
    planted: list[Planted] = field(default_factory=list)


# --- scenarios ------------------------------------------------------------------------------------------------

def rise_then_fall(duration_s: float):
    return lambda t_s: 25.0 + 10.0 * np.sin(np.pi * np.asarray(t_s, dtype=float) / duration_s)


def fan_steps(t_s):
    levels = np.array([1800.0, 2600.0, 2200.0, 3000.0, 1500.0, 2800.0, 2000.0])
    return levels[np.clip((np.asarray(t_s, dtype=float) // 20.0).astype(int), 0, len(levels) - 1)]


def single(seed, warm=False, channels=None, **intrinsics) -> tuple[ImuScenario, ImuIntrinsicsAudit]:
    trajectory = MultiPositionTrajectory(n_poses=N_POSES, seed=seed)
    accel, gyro = random_intrinsics(seed, **intrinsics)
    scenario = ImuScenario(trajectory, accel=accel, gyro=gyro, noise=WHITE, rate_hz=RATE_HZ,
                           temperature=rise_then_fall(trajectory.duration_s) if warm else None,
                           channels=channels or {})
    recording = scenario.perturbed_measurements(seed)
    return scenario, ImuIntrinsicsAudit(recording.imu("imu0"), scenario.gravity_m_s2, base="standard")


def pair(seed, lever_arm_m=0.0, dt_s=0.0, realistic=False) -> tuple[ImuPairScenario, ImuPairAudit]:
    extra = {} if realistic else {"scale": (0.0, 0.0), "misalignment_rad": 0.0, "gyro_axis_rotation_rad": 0.0}
    intrinsics = {}
    for suffix, sub_seed in (("0", 10 + seed), ("1", 20 + seed)):
        intrinsics["accel" + suffix], intrinsics["gyro" + suffix] = random_intrinsics(sub_seed, **extra)
    scenario = ImuPairScenario.random(HandheldTrajectory(duration_s=40.0, seed=seed), seed, lever_arm_m=lever_arm_m,
                                      dt_s=dt_s, noise0=WHITE, noise1=WHITE, rate_hz=RATE_HZ, **intrinsics)
    recording = scenario.perturbed_measurements(seed)
    return scenario, ImuPairAudit(recording.imu("imu0"), recording.imu("imu1"))


def g_sensitivity(seed):
    sc, system = single(seed, g_sensitivity=G_SENSITIVITY)
    return Case("gyro_g_sensitivity", system, [Planted("gyro_g_sensitivity", "imu0/gyro", "matrix", sc.gyro.A)])


def temperature_gyro(seed):
    sc, system = single(seed, warm=True, gyro_temperature_slope=GYRO_TEMPERATURE_SLOPE)
    return Case("bias_temperature (gyro)", system,
                [Planted("bias_temperature", "imu0/gyro", "slope", sc.gyro.temperature_slope)])


def temperature_accel(seed):
    sc, system = single(seed, warm=True, accel_temperature_slope=ACCEL_TEMPERATURE_SLOPE)
    return Case("bias_temperature (accel)", system,
                [Planted("bias_temperature", "imu0/accel", "slope", sc.accel.temperature_slope)])


def fan_accel(seed):
    fan = AuxChannel(fan_steps, "rpm", accel_slope=FAN_ACCEL_SLOPE, reference=2200.0)
    _, system = single(seed, channels={"fan_speed": fan})
    return Case("channel:fan_speed (accel)", system, [Planted("channel:fan_speed", "imu0/accel", "slope",
                                                              FAN_ACCEL_SLOPE)])


def fan_gyro(seed):
    fan = AuxChannel(fan_steps, "rpm", gyro_slope=FAN_GYRO_SLOPE, reference=2200.0)
    _, system = single(seed, channels={"fan_speed": fan})
    return Case("channel:fan_speed (gyro)", system, [Planted("channel:fan_speed", "imu0/gyro", "slope",
                                                             FAN_GYRO_SLOPE)])


def two_single(seed):
    sc, system = single(seed, warm=True, g_sensitivity=G_SENSITIVITY, gyro_temperature_slope=GYRO_TEMPERATURE_SLOPE)
    return Case("g_sensitivity + temperature", system,
                [Planted("gyro_g_sensitivity", "imu0/gyro", "matrix", sc.gyro.A),
                 Planted("bias_temperature", "imu0/gyro", "slope", sc.gyro.temperature_slope)])


def heater_ramp(seed):
    heater = AuxChannel(lambda t_s: 0.1 + HEATER_RAMP_A_PER_S * np.asarray(t_s, dtype=float), "A",
                        gyro_slope=HEATER_GYRO_SLOPE, reference=0.2)
    _, system = single(seed, channels={"heater_current": heater})
    drift = Planted("bias_drift", "imu0/gyro", "slope", HEATER_GYRO_SLOPE * HEATER_RAMP_A_PER_S)
    return Case("channel collinear with time (ambiguity)", system,
                [Planted("channel:heater_current", "imu0/gyro", "slope", HEATER_GYRO_SLOPE, rival=drift)])


def time_offset(seed):
    sc, system = pair(seed, dt_s=TIME_OFFSET_S)
    return Case("time_offset (pair)", system, [Planted("time_offset", "imu1/pair_gyro", "dt_s", np.array(sc.dt_s))])


def lever_arm(seed):
    sc, system = pair(seed, lever_arm_m=LEVER_ARM_M)
    return Case("lever_arm (pair)", system, [Planted("lever_arm", "imu1/pair_accel", "r_m", sc.r_m)])


def two_pair(seed):
    sc, system = pair(seed, lever_arm_m=LEVER_ARM_M, dt_s=TIME_OFFSET_S)
    return Case("time_offset + lever_arm (pair)", system,
                [Planted("time_offset", "imu1/pair_gyro", "dt_s", np.array(sc.dt_s)),
                 Planted("lever_arm", "imu1/pair_accel", "r_m", sc.r_m)])


def null_single(seed):
    return Case("null: standard intrinsics", single(seed)[1])


def noise_channel(seed):
    """A supply voltage with no effect: white (even seeds) or a slow random walk (odd seeds)."""
    rng_seed = 100 + seed

    def voltage(t_s):
        z = np.random.default_rng(rng_seed).standard_normal(np.shape(t_s))
        return 5.0 + (np.cumsum(0.002 * z) if seed % 2 else 0.05 * z)

    return Case("null: noise channel supply_voltage", single(seed, channels={"supply_voltage": (voltage, "V")})[1])


def null_pair(seed):
    return Case("null: pair, biases only", pair(seed)[1])


def relative_gains(seed):
    """Each IMU with its own scale and misalignment: their difference is real and belongs to the relative-gain
    entries (its symmetric part; the antisymmetric rest goes into R), never to a lever arm or a clock offset."""
    return Case("relative gains (pair: own scale + misalignment)", pair(seed, realistic=True)[1],
                [Planted("accel_relative_gain", "imu1/pair_accel", None, None),
                 Planted("gyro_relative_gain", "imu1/pair_gyro", None, None)])


EFFECT_TYPES: list[Callable[[int], Case]] = [g_sensitivity, temperature_gyro, temperature_accel, fan_accel, fan_gyro,
                                             two_single, heater_ramp, time_offset, lever_arm, two_pair,
                                             relative_gains]
NULL_TYPES: list[Callable[[int], Case]] = [null_single, noise_channel, null_pair]


# --- scoring --------------------------------------------------------------------------------------------------

def z_scores(estimate: dict, std: dict, planted: Planted) -> np.ndarray:
    value = np.atleast_1d(np.asarray(estimate[planted.key], dtype=float))
    sigma = np.atleast_1d(np.asarray(std[planted.key], dtype=float))
    return (value - np.ravel(planted.truth)) / sigma


def score(case: Case) -> dict:
    start = time.perf_counter()
    result = run_audit(case.system)
    seconds = time.perf_counter() - start
    findings = result.findings
    accepted = [c for c in result.final_effects if c not in result.base_fit.effects]
    matched, hits, z_finding, z_final = set(), [], [], []
    for planted in case.planted:
        hit = None
        for i, f in enumerate(findings):
            if f["effect"] == planted.effect and f["target"] == planted.target:
                hit, used = i, planted
            elif planted.rival and f["effect"] == planted.rival.effect and f["target"] == planted.rival.target:
                named_other = {(r["effect"], r["target"]) for r in f.get("ambiguous_with", [])}
                if (planted.effect, planted.target) in named_other:  # named the rival and said so: correct
                    hit, used = i, planted.rival
                else:  # named the rival silently: matched (not a false finding) but not recalled
                    matched.add(i)
        hits.append(hit is not None)
        if hit is None:
            continue
        matched.add(hit)
        if used.key is None:
            continue
        z_finding.append(z_scores(findings[hit]["estimate"], findings[hit]["std"], used))
        estimate, std = case.system.estimate(result.final_fit, accepted[hit])
        z_final.append(z_scores(estimate, std, used))
    false = [f"{f['effect']}@{f['target']}" for i, f in enumerate(findings) if i not in matched]
    return {"kind": case.kind, "seconds": seconds, "named": [f"{f['effect']}@{f['target']}" for f in findings],
            "planted": [f"{p.effect}@{p.target}" for p in case.planted], "recalled": hits, "false": false,
            "z_finding": np.concatenate(z_finding).tolist() if z_finding else [],
            "z_final_fit": np.concatenate(z_final).tolist() if z_final else []}


def summarise(rows: list[dict]) -> dict:
    def coverage(z):
        return float(np.mean(np.abs(z) < Z_MAX)) if len(z) else None

    def rms(z):
        return float(np.sqrt(np.mean(np.square(z)))) if len(z) else None

    out = {}
    for kind in dict.fromkeys(r["kind"] for r in rows):
        group = [r for r in rows if r["kind"] == kind]
        recalled = [h for r in group for h in r["recalled"]]
        z_finding = np.array([z for r in group for z in r["z_finding"]])
        z_final = np.array([z for r in group for z in r["z_final_fit"]])
        out[kind] = {"recordings": len(group),
                     "recall": float(np.mean(recalled)) if recalled else None,
                     "coverage_finding": coverage(z_finding), "coverage_final_fit": coverage(z_final),
                     "z_rms_finding": rms(z_finding), "z_rms_final_fit": rms(z_final),
                     "false_findings_per_recording": sum(len(r["false"]) for r in group) / len(group),
                     "false_findings": sorted({n for r in group for n in r["false"]}),
                     "seconds_per_recording": float(np.mean([r["seconds"] for r in group]))}
    return out


def _fmt(x, spec):
    width = int(spec.split(".")[0])
    return "-".rjust(width) if x is None else format(x, spec)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=None, help="recordings per hidden-effect type (default 5)")
    parser.add_argument("--null-seeds", type=int, default=None, help="recordings per null type (default 20)")
    parser.add_argument("--first-seed", type=int, default=1000)
    parser.add_argument("--only", help="run only the types whose name contains this text (e.g. 'pair')")
    _schema.add_arguments(parser, "audit_recall")
    args = parser.parse_args()
    args.seeds = args.seeds or (1 if args.quick else 5)
    args.null_seeds = args.null_seeds or (1 if args.quick else 20)
    start = time.perf_counter()
    rows = []
    plan = ([(make, args.seeds) for make in EFFECT_TYPES] + [(make, args.null_seeds) for make in NULL_TYPES])
    for make, n in plan:
        kind = make(args.first_seed).kind if args.only else None
        if args.only and args.only not in kind:
            continue
        for seed in range(args.first_seed, args.first_seed + n):
            row = score(make(seed))
            row["seed"] = seed
            rows.append(row)
        print(f"  {rows[-1]['kind']}: {n} recordings done ({time.perf_counter() - start:.0f} s)", flush=True)
    total_s = time.perf_counter() - start
    table = summarise(rows)
    print(f"\n{'type':42s} {'n':>3s} {'recall':>7s} {'cov(find)':>9s} {'cov(final)':>10s} {'z rms find':>10s} "
          f"{'z rms final':>11s} {'false/rec':>9s} {'s/rec':>6s}")
    for kind, s in table.items():
        print(f"{kind:42s} {s['recordings']:3d} {_fmt(s['recall'], '7.2f')} {_fmt(s['coverage_finding'], '9.2f')} "
              f"{_fmt(s['coverage_final_fit'], '10.2f')} {_fmt(s['z_rms_finding'], '10.2f')} "
              f"{_fmt(s['z_rms_final_fit'], '11.2f')} {s['false_findings_per_recording']:9.2f} "
              f"{s['seconds_per_recording']:6.2f}")
        if s["false_findings"]:
            print(f"{'':46s}false: {', '.join(s['false_findings'])}")
    false_all = sum(len(r["false"]) for r in rows) / len(rows)
    null_rows = [r for r in rows if not r["planted"]]
    false_null = sum(len(r["false"]) for r in null_rows) / max(len(null_rows), 1)
    planted = [h for r in rows for h in r["recalled"]]
    overall = {"recordings": len(rows), "recall": float(np.mean(planted)) if planted else float("nan"),
               "false_findings_per_recording": false_all, "false_findings_per_null_recording": false_null,
               "total_seconds": total_s}
    print(f"\noverall: {len(rows)} recordings, recall {overall['recall']:.2f}, false findings per recording "
          f"{false_all:.3f} (null recordings only: {false_null:.3f}), total {total_s:.0f} s")
    _schema.write(args.json, "audit_recall", "audit", args.quick, total_s, schema_rows(overall, table),
                  {"settings": vars(args), "overall": overall, "per_type": table, "recordings": rows})
    print(f"results: {args.json}")


def schema_rows(overall: dict, table: dict) -> list[dict]:
    """Recall, false findings and sigma honesty as schema rows (the audit has no patent baseline)."""
    def pooled(key):
        values = [(s[key], s["recordings"]) for s in table.values() if s[key] is not None]
        return sum(v * n for v, n in values) / sum(n for _, n in values) if values else None

    return [
        _schema.row("recall of planted effects", "fraction", overall["recall"], better="higher",
                    note=f"{overall['recordings']} generated recordings; no baseline"),
        _schema.row("false findings per null recording", "count", overall["false_findings_per_null_recording"],
                    note="no baseline"),
        _schema.row("false findings per recording", "count", overall["false_findings_per_recording"],
                    note="no baseline"),
        _schema.row("coverage within 3 sigma (finding)", "fraction", pooled("coverage_finding"), better="higher",
                    note="0.997 when the reported sigmas are honest; no baseline"),
        _schema.row("RMS of error/sigma (finding)", "-", pooled("z_rms_finding"),
                    note="1 when the reported sigmas are honest; no baseline"),
        _schema.row("time per recording", "s", overall["total_seconds"] / max(overall["recordings"], 1),
                    note="no baseline")]


if __name__ == "__main__":
    main()
