"""Catalog recall of the audit on every audited system: is each catalog effect named, under its own name, on any
seed, sized within 3 of the sigmas the audit reports, and is nothing else named?

Per system and planted effect, ``--seeds`` recordings (default 20) each hide that one effect at a stated size;
per system ``--null-seeds`` recordings (default 20) hide nothing.  Counted per case:

* recall: the planted effect named with the right name (and target),
* size within 3 sigma: every entry of its estimate within 3 reported sigma of the truth (over the named ones),
* size in sigma: the median over seeds of |truth| / reported sigma (the planted size as the audit measures it;
  the largest entry for a vector),
* false findings per recording: findings of anything not planted (on the nulls: every finding),
* seconds per audit (the lead schedules the full run with these).

The planting code is the existing suites': ``audit_recall.py`` (imu, imu-pair), ``audit_open_world_systems.py``
(qc, encoder, ship, scan) and, for the tracker, the scenario of ``tests/test_tracker_audit.py``.  Usage:

    .venv/bin/python benchmarks/audit_catalog_recall.py [--quick] [--seeds 20] [--null-seeds 20]
        [--systems tracker,imu] [--cases TEXT] [--json out.json]

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


def tracker_system(seed: int, nominal_lever_error_m=None, **effects):
    from selfcal.audit.tracker import TrackerAudit
    from selfcal.pipelines.tracker import estimator_for_audit
    from selfcal.sim.tracker import TrackerScenario
    sc = TrackerScenario(duration_s=20.0, seed=seed, burst_rate_per_min=6.0, steer_angle_deg=(1.0, 2.0),
                         steer_period_s=(20.0, 40.0), **effects)
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
    tracker_case("incl_accel_sensitivity", "0.3", "sensitivity", 0.3, incl_accel_sensitivity=0.3),
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

CASES = TRACKER + IMU + IMU_PAIR + OPEN_WORLD
SYSTEMS = list(dict.fromkeys(c.system for c in CASES))


# --- scoring --------------------------------------------------------------------------------------------------

def _named(finding: dict, planted: Planted) -> bool:
    if finding["effect"] != planted.effect or (planted.target and finding["target"] != planted.target):
        return False
    return planted.driver is None or (finding.get("driver") == planted.driver[0]
                                      and finding.get("form") in planted.driver[1])


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
            continue
        matched.add(hit)
        f = findings[hit]
        if p.check is not None:
            out["within_3_sigma"] = bool(p.check(f))
        elif p.key is not None:
            value = np.atleast_1d(np.asarray(f["estimate"][p.key], float))
            sigma = np.atleast_1d(np.asarray(f["std"][p.key], float))
            truth = np.atleast_1d(np.asarray(p.truth, float))
            out["within_3_sigma"] = bool(np.all(np.abs(value - truth) < 3 * sigma))
            out["z"] = ((value - truth) / sigma).tolist()
            size = np.atleast_1d(np.asarray(p.truth if p.planted_size is None else p.planted_size, float))
            out["size_in_sigma"] = float(np.max(np.abs(size) / sigma))
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
    if case.name != "null":
        entry["recall"] = sum(r.get("recalled", False) for r in done) / max(len(done), 1)
        entry["missed_seeds"] = [r["seed"] for r in done if not r.get("recalled", False)]
    if sized:
        entry["size_within_3_sigma"] = sum(sized) / len(sized)
    if size_sigma:
        entry["planted_size_in_reported_sigma_median"] = float(np.median(size_sigma))
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
        label = f"{case.system}/{case.name}" + ("" if case.name == "null" else f" at {case.size}")
        if case.name != "null":
            rows.append(_schema.row(f"{label}: recall", "fraction", entry["recall"], better="higher",
                                    note=f"{n} seeds; no baseline"))
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
    args = parser.parse_args()
    n_effect = args.seeds or (2 if args.quick else _schema.DEFAULT_SEEDS)
    n_null = args.null_seeds or (2 if args.quick else _schema.DEFAULT_SEEDS)
    start = time.perf_counter()
    wanted = [w for w in args.cases.split(",")]
    cases = [c for c in CASES if c.system in args.systems.split(",") and any(w in c.name for w in wanted)]
    plan = sorted(((i, seed) for i, c in enumerate(cases)  # seed by seed: an early stop leaves every case measured
                   for seed in range(args.first_seed, args.first_seed + (n_null if c.name == "null" else n_effect))),
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
