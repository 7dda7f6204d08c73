"""Stationing calibration on the Hilti total-station + accelerometer datasets (real data, read in place).

1. Calibrate on each of the 7 files separately: prism lever arm, pivot fraction, column and base accelerometer
   mountings, residuals against the stated sigmas -> consistency across conditions.
2. Held out: the flat.yaml calibration (the dataset's calibration set) applied to every file: each column height
   stationed from its stationing points, evaluation points predicted, RMS against the total station.  Library
   (lever arm from the calibration, column bend from the column accelerometer, tilt sensors re-zeroed at the
   site) vs baseline (URDF lever arm, rigid stations from the prism alone, as the dataset's Kabsch example).
   The figure is a distribution over the datasets (median, 90th percentile, worst, and of the per-dataset ratio):
   real data, so 7 datasets (all there are), not 20 seeds.

    .venv/bin/python benchmarks/stationing_hilti.py [--quick] [--json PATH]
"""
from __future__ import annotations

import argparse
import json
import resource
import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from selfcal.io.atomic import atomic_write_text  # noqa: E402
from selfcal.pipelines.stationing import calibrate_stationing, heldout_stationing  # noqa: E402

sys.path.insert(0, str(ROOT / "benchmarks"))
import _schema  # noqa: E402  benchmarks/_schema.py: the results schema (its distribution rows)

DATA = ROOT.parent / "shared" / "data" / "hilti_stationing_totalstation_accelerometers"
FILES = ["flat", "pallet", "orthogonal_wood", "wood_left_track", "seesaw", "diagonal_wood", "outdoor"]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="flat and seesaw only")
    ap.add_argument("--json", default=str(ROOT / "benchmarks" / "results" / "stationing_hilti.json"))
    args = ap.parse_args(argv)
    if not (DATA / "flat.yaml").is_file():
        print(f"dataset not found: {DATA}")
        return 1
    files = ["flat", "seesaw"] if args.quick else FILES
    start = time.perf_counter()
    per_file = {}
    flat_cal = None
    print(f"{'file':16s} {'prism x,y,z [mm]':>26s} {'pivot':>6s} {'col mount r,p,y [deg]':>26s} "
          f"{'base mount r,p [deg]':>20s} {'prism RMS/sigma':>17s} {'col acc/sig':>11s} {'base acc/sig':>12s}")
    for name in files:
        cal = calibrate_stationing([DATA / f"{name}.yaml"])
        if name == "flat":
            flat_cal = cal.calibration
        d = cal.to_dict()
        c = cal.calibration
        col = Rotation.from_matrix(c.R_T_Acol).as_euler("xyz", degrees=True)
        base = Rotation.from_matrix(c.R_B_Abase).as_euler("xyz", degrees=True)
        r = d["residuals"][name]
        per_file[name] = {"tool_t_prism_mm": (c.tool_t_prism * 1e3).tolist(),
                          "tool_t_prism_sigma_mm": (np.array(d["tool_t_prism_m_sigma"]) * 1e3).tolist(),
                          "pivot_fraction": c.pivot_fraction, "pivot_fraction_sigma": d["pivot_fraction_sigma"],
                          "column_mount_rpy_deg": col.tolist(),
                          "column_mount_rotvec_sigma_deg": np.degrees(d["R_column_tip_accel"]["rotvec_rad_sigma"]).tolist(),
                          "base_mount_rpy_deg": base.tolist(), "residuals": r, "seconds": cal.seconds}
        print(f"{name:16s} {np.array2string(c.tool_t_prism * 1e3, precision=2):>26s} {c.pivot_fraction:6.3f} "
              f"{np.array2string(col, precision=3):>26s} {np.array2string(base[:2], precision=3):>20s} "
              f"{np.array2string(np.array(r['prism_rms_over_sigma']), precision=1):>17s} "
              f"{np.array2string(np.array(r['column_accel_rms_over_sigma'][:2]), precision=2):>11s} "
              f"{np.array2string(np.array(r['base_accel_rms_over_sigma'][:2]), precision=2):>12s}", flush=True)
    spread = {k: np.ptp([per_file[n][k] for n in files], axis=0).tolist()
              for k in ("tool_t_prism_mm", "column_mount_rpy_deg", "base_mount_rpy_deg")}
    print("spread (max - min) across files:", {k: np.round(v, 3).tolist() for k, v in spread.items()})

    rows, held = [], {}
    print(f"\nheld out (flat.yaml calibration; stationing points -> evaluation points), 3D RMS [mm]")
    for name in files:
        h = heldout_stationing(flat_cal, DATA / f"{name}.yaml").to_dict()
        h_fixed = heldout_stationing(flat_cal, DATA / f"{name}.yaml", rezero=False).to_dict()
        h["no_rezero_rms_3d_mm"] = h_fixed["rms_3d_mm"]
        h["no_rezero_rms_mm"] = h_fixed["rms_mm"]
        held[name] = h
        print(f"{name:16s} library {h['rms_3d_mm']:6.2f} ({np.round(h['rms_mm'], 2).tolist()})  "
              f"without re-zeroing {h['no_rezero_rms_3d_mm']:6.2f}  baseline {h['baseline_rms_3d_mm']:6.2f} "
              f"({np.round(h['baseline_rms_mm'], 2).tolist()})  n={h['n_evaluation']}", flush=True)
        rows.append({"metric": f"held-out prism 3D RMS, {name}", "unit": "mm", "library": h["rms_3d_mm"],
                     "baseline": h["baseline_rms_3d_mm"], "ratio": h["baseline_rms_3d_mm"] / h["rms_3d_mm"],
                     "better": "lower", "note": "baseline / library; > 1 means the library is better"})
    rows.insert(0, _schema.distribution("held-out prism 3D RMS per dataset", "mm",
                                        [held[n]["rms_3d_mm"] for n in files],
                                        [held[n]["baseline_rms_3d_mm"] for n in files], population="real datasets",
                                        note="flat.yaml calibration applied to every dataset; baseline: URDF lever "
                                             "arm, rigid stations; per-dataset ratio > 1: the library is better"))
    print(_schema.describe(rows[0]))
    for name in files:
        r = per_file[name]["residuals"]
        rows.append({"metric": f"calibration prism RMS / sigma (3D), {name}", "unit": "1",
                     "library": float(np.sqrt(np.mean(np.square(r["prism_rms_over_sigma"])))), "baseline": None,
                     "ratio": None, "better": "lower", "note": "stated sigma 0.75 mm per axis"})
    out = {"benchmark": "stationing_hilti", "system": "tracker", "quick": args.quick,
           "seconds": time.perf_counter() - start,
           "peak_memory_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
           "rows": rows, "extra": {"per_file_calibration": per_file, "spread_across_files": spread,
                                   "heldout": held}}
    path = Path(args.json)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, json.dumps(out, indent=1) + "\n")
    print(f"wrote {path} ({out['seconds']:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
