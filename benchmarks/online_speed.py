"""Online fusion speed (issue 19 item 3): CPU-time real-time factors of the streaming paths, with accuracy beside.

Per seed, on simulated recordings at the default rates (tracker: 200 Hz IMU, 50 Hz tracker, 10 Hz inclinometer
and camera; ship: 50 Hz IMU, 1 Hz speed log and GPS), each command in its own subprocess, end to end (start-up,
imports and reading the recording included), timed by the CPU time the kernel charges it (``os.wait4``: user +
system; the machine is shared, the wall clock is not a measure here):

* ``selfcal track --replay REC`` (tracker): real-time factor, p99 push latency (``track``'s LatencyHistogram,
  printed in its summary), peak RSS; the pose error against the truth beside the patent's filter on the same
  recording (:func:`tracker_vs_patent.baseline_run`);
* ``selfcal smooth tracker REC --mode isam2``: real-time factor;
* ``selfcal track --system ship --replay REC`` against ``selfcal smooth ship REC --online`` on the same voyage:
  both real-time factors, their ratio, and the roll/pitch error of each beside the patent's filter.

``--reference TREE`` runs every command a second time from another source tree (e.g. ``/work/main``: the code
before a change) in the same run, interleaved, and reports after / before as ratios: on a shared machine only
ratios measured side by side mean anything.  The memory over a 3 h fixed-lag run is
:func:`tracker_vs_patent.memory_run` (in-process, RSS sampled along the run; ``--memory-hours``, 0 to skip).

Usage: ``.venv/bin/python benchmarks/online_speed.py [--quick] [--reference /work/main] [--json PATH]``
"""
from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

import _schema  # noqa: E402  benchmarks/_schema.py: the results schema every benchmark writes

ROOT = Path(__file__).resolve().parents[1]
TARGETS = {"tracker_track_rt": 100.0, "tracker_p99_ms": 5.0, "isam2_rt": 30.0, "ship_ratio": 1.3}
P99 = re.compile(r"p99 ([0-9.]+) ms")


def run_cpu(args: list[str], tree: Path) -> dict:
    """``selfcal ARGS`` in a subprocess from source tree ``tree``: its CPU seconds (user + system, read by reaping
    it with ``os.wait4``), peak RSS (MB) and stdout."""
    env = {**os.environ, "PYTHONPATH": str(tree)}
    with tempfile.TemporaryFile("w+") as out, tempfile.TemporaryFile("w+") as err:
        proc = subprocess.Popen([sys.executable, "-m", "selfcal.cli.main", *args], cwd=tree, env=env, stdout=out,
                                stderr=err, text=True)
        _, status, usage = os.wait4(proc.pid, 0)
        proc.returncode = os.waitstatus_to_exitcode(status)
        out.seek(0), err.seek(0)
        stdout, stderr = out.read(), err.read()
    if proc.returncode != 0:
        last = stderr.strip().splitlines()[-1] if stderr.strip() else ""
        raise RuntimeError(f"selfcal {' '.join(args)} failed ({proc.returncode}): {last}")
    return {"cpu_s": usage.ru_utime + usage.ru_stime, "rss_mb": usage.ru_maxrss / 1024, "stdout": stdout}


def read_tum(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t_ns, position (n, 3), quaternion qx qy qz qw (n, 4)) of a TUM file (comment lines skipped)."""
    rows = [line.split() for line in path.read_text().splitlines() if line.strip() and not line.startswith("#")]
    t_ns = np.array([_stamp_ns(r[0]) for r in rows], dtype=np.int64)
    values = np.array([[float(v) for v in r[1:8]] for r in rows])
    return t_ns, values[:, :3], values[:, 3:]


def _stamp_ns(text: str) -> int:
    """A TUM stamp in s (``sec.fraction``) as integer ns, without the rounding of a float."""
    sec, _, frac = text.partition(".")
    return int(sec) * 10**9 + int((frac + "000000000")[:9])


def tracker_accuracy(sc, rec, tum: Path) -> dict:
    """Attitude (deg) and position (mm) RMS error of a TUM trajectory against the scenario's truth."""
    from tracker_vs_patent import errors, rms
    t_ns, p, q = read_tum(tum)
    att, pos = errors(sc, t_ns, Rotation.from_quat(q).as_matrix(), p)
    return {"att_deg": rms(att), "pos_mm": rms(pos)}


def tracker_seed(seed: int, duration_s: float, trees: dict[str, Path], work: Path) -> dict:
    """Simulate one tracker recording, run track --replay and smooth --mode isam2 from each tree, and the patent's
    filter once."""
    from selfcal.sim.tracker import TrackerScenario
    from tracker_vs_patent import baseline_run
    sc = TrackerScenario(duration_s=duration_s, seed=seed)
    rec_path = work / f"tracker_s{seed}"
    sc.write(rec_path, seed=100 + seed, overwrite=True)
    rec = sc.measurements(seed=100 + seed)
    out = {"seed": seed, "duration_s": duration_s, "patent": {k: v for k, v in baseline_run(sc, rec).items()
                                                             if k in ("att_deg", "pos_mm")}}
    for label, tree in trees.items():
        tum = work / f"tracker_s{seed}_{label}.tum"
        tum.unlink(missing_ok=True)
        track = run_cpu(["track", "--replay", str(rec_path), "--out-tum", str(tum)], tree)
        isam_tum = work / f"tracker_s{seed}_{label}_isam2.tum"
        isam2 = run_cpu(["smooth", "tracker", str(rec_path), "--mode", "isam2", "--out", str(isam_tum)], tree)
        p99 = P99.search(track["stdout"])
        out[label] = {"track_cpu_s": track["cpu_s"], "track_rt": duration_s / track["cpu_s"],
                      "track_rss_mb": track["rss_mb"], "p99_ms": float(p99.group(1)) if p99 else None,
                      "isam2_cpu_s": isam2["cpu_s"], "isam2_rt": duration_s / isam2["cpu_s"],
                      "track": tracker_accuracy(sc, rec, tum), "isam2": tracker_accuracy(sc, rec, isam_tum)}
        tum.unlink(missing_ok=True)
        isam_tum.unlink(missing_ok=True)
        print(f"tracker seed {seed} [{label}]: track {out[label]['track_rt']:.1f}x (p99 {out[label]['p99_ms']} ms, "
              f"{track['rss_mb']:.0f} MB), isam2 {out[label]['isam2_rt']:.1f}x; track error "
              f"{out[label]['track']['att_deg']:.4f} deg {out[label]['track']['pos_mm']:.3f} mm "
              f"(patent {out['patent']['att_deg']:.4f} deg {out['patent']['pos_mm']:.3f} mm)", flush=True)
    return out


def ship_accuracy(scenario, t0_ns: int, tum: Path) -> dict:
    """Roll and pitch RMS error (deg) of a TUM attitude trajectory against the voyage's truth."""
    from ship_vs_patent import errors
    t_ns, _, q = read_tum(tum)
    yaw_pitch_roll = Rotation.from_quat(q).as_euler("ZYX")
    e = errors((t_ns - t0_ns) * 1e-9, yaw_pitch_roll[:, 2], yaw_pitch_roll[:, 1], scenario)
    return {"roll_deg": e["roll_rms_deg"], "pitch_deg": e["pitch_rms_deg"]}


def ship_seed(seed: int, duration_s: float, trees: dict[str, Path], work: Path) -> dict:
    """Simulate one turning voyage; ``track --system ship --replay`` and ``smooth ship --online`` from each tree;
    the patent's filter once."""
    from selfcal.baselines.ship import PatentDriftFilter
    from selfcal.pipelines.ship import ship_inputs
    from selfcal.sim.ship import ShipScenario
    from ship_vs_patent import errors, patent_cutoff_hz
    scenario = ShipScenario(kind="turning", duration_s=duration_s, seed=seed)
    rec_path = work / f"ship_s{seed}"
    scenario.write(rec_path, seed=seed + 100, overwrite=True)
    inputs = ship_inputs(scenario.perturbed_measurements(seed + 100))
    patent = PatentDriftFilter(patent_cutoff_hz(scenario)).run(inputs.t_s, inputs.gyro_rad_s, inputs.accel_m_s2,
                                                               inputs.speed_m_s)
    e = errors(inputs.t_s, patent.roll, patent.pitch, scenario)
    out = {"seed": seed, "duration_s": duration_s, "patent": {"roll_deg": e["roll_rms_deg"],
                                                              "pitch_deg": e["pitch_rms_deg"]}}
    for label, tree in trees.items():
        tum, online_tum = work / f"ship_s{seed}_{label}.tum", work / f"ship_s{seed}_{label}_online.tum"
        tum.unlink(missing_ok=True)
        track = run_cpu(["track", "--system", "ship", "--replay", str(rec_path), "--out-tum", str(tum)], tree)
        online = run_cpu(["smooth", "ship", str(rec_path), "--online", "--out", str(online_tum)], tree)
        p99 = P99.search(track["stdout"])
        out[label] = {"track_cpu_s": track["cpu_s"], "track_rt": duration_s / track["cpu_s"],
                      "p99_ms": float(p99.group(1)) if p99 else None, "online_cpu_s": online["cpu_s"],
                      "online_rt": duration_s / online["cpu_s"], "ratio": track["cpu_s"] / online["cpu_s"],
                      "track": ship_accuracy(scenario, scenario.t0_ns, tum),
                      "online": ship_accuracy(scenario, scenario.t0_ns, online_tum)}
        tum.unlink(missing_ok=True)
        online_tum.unlink(missing_ok=True)
        r = out[label]
        print(f"ship seed {seed} [{label}]: track {r['track_rt']:.1f}x, smooth --online {r['online_rt']:.1f}x, "
              f"track/online CPU {r['ratio']:.2f}; roll error track {r['track']['roll_deg']:.4f} online "
              f"{r['online']['roll_deg']:.4f} patent {out['patent']['roll_deg']:.4f} deg", flush=True)
    return out


def memory_over(hours: float) -> dict:
    """RSS along an in-process fixed-lag run of ``hours`` (tracker_vs_patent.memory_run), first and last third."""
    from tracker_vs_patent import memory_run
    marks = memory_run(hours * 3600.0, sample_every_s=max(60.0, hours * 3600.0 / 30))
    rss = np.array([m[1] for m in marks])
    third = max(1, len(rss) // 3)
    return {"hours": hours, "rss_first_third_mb": float(rss[:third].mean()), "rss_last_third_mb":
            float(rss[-third:].mean()), "marks": marks}


def median(runs: list[dict], label: str, *path) -> float | None:
    values = []
    for r in runs:
        v = r.get(label)
        for key in path:
            v = None if v is None else v.get(key)
        if v is not None:
            values.append(v)
    return float(np.median(values)) if values else None


def schema_rows(tracker: list[dict], ship: list[dict], memory: dict | None, reference: bool) -> list[dict]:
    """Library figures against the targets (and the reference tree, where given), accuracy against the patent."""
    row = _schema.row
    rows = [
        row("tracker track --replay real-time factor (CPU, end to end)", "x", median(tracker, "new", "track_rt"),
            TARGETS["tracker_track_rt"], better="higher", note="baseline = the issue's target (100x)"),
        row("tracker track p99 push latency", "ms", median(tracker, "new", "p99_ms"), TARGETS["tracker_p99_ms"],
            note="baseline = the issue's target (5 ms)"),
        row("tracker smooth --mode isam2 real-time factor (CPU)", "x", median(tracker, "new", "isam2_rt"),
            TARGETS["isam2_rt"], better="higher", note="baseline = the issue's target (30x)"),
        row("ship track / smooth --online CPU time", "ratio", median(ship, "new", "ratio"), TARGETS["ship_ratio"],
            note="baseline = the issue's target (1.3)"),
        row("tracker track attitude RMSE", "deg", median(tracker, "new", "track", "att_deg"),
            median(tracker, "patent", "att_deg"), note="baseline = patent 004's filter, same recordings"),
        row("tracker track position RMSE", "mm", median(tracker, "new", "track", "pos_mm"),
            median(tracker, "patent", "pos_mm"), note="baseline = patent 004's filter, same recordings"),
        row("ship track roll RMSE", "deg", median(ship, "new", "track", "roll_deg"), median(ship, "patent", "roll_deg"),
            note="baseline = patent 003's filter, same voyages"),
        row("ship track pitch RMSE", "deg", median(ship, "new", "track", "pitch_deg"),
            median(ship, "patent", "pitch_deg"), note="baseline = patent 003's filter, same voyages"),
    ]
    if reference:
        note = "baseline = the same command from the --reference tree, same run"
        rows += [
            row("tracker track real-time factor vs reference", "x", median(tracker, "new", "track_rt"),
                median(tracker, "reference", "track_rt"), better="higher", note=note),
            row("tracker smooth --mode isam2 real-time factor vs reference", "x", median(tracker, "new", "isam2_rt"),
                median(tracker, "reference", "isam2_rt"), better="higher", note=note),
            row("ship track real-time factor vs reference", "x", median(ship, "new", "track_rt"),
                median(ship, "reference", "track_rt"), better="higher", note=note),
            row("tracker track attitude RMSE vs reference", "deg", median(tracker, "new", "track", "att_deg"),
                median(tracker, "reference", "track", "att_deg"), note=note),
            row("tracker track position RMSE vs reference", "mm", median(tracker, "new", "track", "pos_mm"),
                median(tracker, "reference", "track", "pos_mm"), note=note),
            row("tracker isam2 position RMSE vs reference", "mm", median(tracker, "new", "isam2", "pos_mm"),
                median(tracker, "reference", "isam2", "pos_mm"), note=note),
            row("ship track roll RMSE vs reference", "deg", median(ship, "new", "track", "roll_deg"),
                median(ship, "reference", "track", "roll_deg"), note=note),
        ]
    if memory is not None:
        rows.append(row(f"tracker fixed-lag RSS, last third of {memory['hours']:g} h", "MB",
                        memory["rss_last_third_mb"], memory["rss_first_third_mb"],
                        note="baseline = the first third of the same run (flat: ratio ~1)"))
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    _schema.add_arguments(ap, "online_speed")
    ap.add_argument("--reference", help="another source tree (e.g. /work/main) to run side by side")
    ap.add_argument("--tracker-seeds", type=int, nargs="+", help="default 1 2 3 (--quick: 1)")
    ap.add_argument("--ship-seeds", type=int, nargs="+", help="default 3 4 (--quick: 3)")
    ap.add_argument("--memory-hours", type=float, help="fixed-lag memory run length (default 3, --quick 0: none)")
    args = ap.parse_args(argv)
    started = time.perf_counter()
    trees = {"new": ROOT}
    if args.reference:
        trees["reference"] = Path(args.reference).resolve()
    tracker_s = 60.0 if args.quick else 300.0
    ship_s = 300.0 if args.quick else 1800.0
    tracker_seeds = args.tracker_seeds or ([1] if args.quick else [1, 2, 3])
    ship_seeds = args.ship_seeds or ([3] if args.quick else [3, 4])
    memory_hours = args.memory_hours if args.memory_hours is not None else (0.0 if args.quick else 3.0)
    with tempfile.TemporaryDirectory(prefix="online_speed_") as tmp:
        work = Path(tmp)
        tracker = [tracker_seed(s, tracker_s, trees, work) for s in tracker_seeds]
        ship = [ship_seed(s, ship_s, trees, work) for s in ship_seeds]
    memory = memory_over(memory_hours) if memory_hours > 0 else None
    rows = schema_rows(tracker, ship, memory, "reference" in trees)
    for r in rows:
        print(f"{r['metric']}: {r['library']} {r['unit']} (baseline {r['baseline']}, ratio {r['ratio']})")
    _schema.write(args.json, "online_speed", "tracker", args.quick, time.perf_counter() - started, rows,
                  {"tracker": tracker, "ship": ship, "memory": memory, "targets": TARGETS,
                   "trees": {k: str(v) for k, v in trees.items()}})
    print(f"results: {args.json}")


if __name__ == "__main__":
    main()
