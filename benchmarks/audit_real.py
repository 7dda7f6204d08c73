"""The audit of every real recording at hand, as a user runs it: ``selfcal import`` where the data need it, then
``selfcal audit REC --system S --json OUT``.  Per recording: what is named (effect or driver and form, target,
RMS and held-out RMS before and after), what passed the significance test and was rejected (with the reason),
each family's verdict, and the wall time.  Real data: one recording each, all there are (no seeds).

    .venv/bin/python benchmarks/audit_real.py [--quick] [--only hilti/flat,mpu6050_static] [--json PATH]

docs/audit.md quotes this output (sections "On real recordings", "Hilti stationing (real)", "Real scans").
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import _schema

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data"
if not SHARED.exists():
    SHARED = Path("/work/shared/data")
SELFCAL = [sys.executable, "-m", "selfcal.cli.main"]
HILTI = ("flat", "seesaw", "wood_left_track", "diagonal_wood", "orthogonal_wood", "pallet", "outdoor")

# name -> (system, recording in data/ or (importer, source under shared/data))
RECORDINGS = {
    "xsens_mti_multiposition": ("imu", ROOT / "data" / "xsens_mti_multiposition"),
    "mpu6050_multiposition": ("imu", ROOT / "data" / "mpu6050_multiposition"),
    "mpu6050_static": ("imu", ROOT / "data" / "mpu6050_static"),
    "adis16405_static_run1": ("imu", ("adis16405-static", "imudata_adis16405_static/adis16405_static_run1.npz")),
    "spherecalib_lidar": ("qc", ROOT / "data" / "spherecalib_lidar"),
    **{f"hilti/{name}": ("stationing", ("hilti-stationing", f"hilti_stationing_totalstation_accelerometers/{name}.yaml"))
       for name in HILTI},
}
QUICK = ("mpu6050_multiposition", "hilti/flat")


def summary(out: dict) -> dict:
    def label(f):
        return f["effect"] if f["effect"] != "unlisted" else \
            f"unlisted {f['form']} in {f['driver']}" + (f" x {f['second_driver']}" if f.get("second_driver") else "")
    return {
        "findings": [{"what": label(f), "target": f["target"], "meaning": f.get("meaning"),
                      "rms": [f["gain"].get("rms_before"), f["gain"].get("rms_after")],
                      "heldout_rms": [f["gain"].get("heldout_rms_before"), f["gain"].get("heldout_rms_after")],
                      "unit": f["gain"].get("unit"), "estimate": f["estimate"], "std": f["std"],
                      "ambiguous_with": [a["effect"] + "@" + a["target"] for a in f.get("ambiguous_with", [])]}
                     for f in out["findings"]],
        "rejected": [{"what": label(r) if r["effect"] == "unlisted" else r["effect"], "target": r["target"],
                      "reason": r["reason"]} for r in out.get("rejected", [])],
        "remaining": {k: {"verdict": v["verdict"], "strongest": v.get("strongest")}
                      for k, v in out.get("remaining", {}).items()},
        "notes": out.get("notes", []),
    }


def audit(name: str, system: str, source, work: Path) -> dict:
    if isinstance(source, tuple):
        kind, rel = source
        rec = work / name.replace("/", "_")
        subprocess.run([*SELFCAL, "import", kind, str(SHARED / rel), str(rec)], check=True, capture_output=True)
    else:
        rec = source
    out = work / (name.replace("/", "_") + ".json")
    t0 = time.perf_counter()
    run = subprocess.run([*SELFCAL, "audit", str(rec), "--system", system, "--json", str(out)],
                         capture_output=True, text=True)
    seconds = time.perf_counter() - t0
    if run.returncode != 0:
        return {"system": system, "seconds": seconds, "refused": (run.stderr or run.stdout).strip()[-400:]}
    return {"system": system, "seconds": seconds, **summary(json.loads(out.read_text()))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    _schema.add_arguments(parser, "audit_real")
    parser.add_argument("--only", default=None, help="comma-separated recording names: " + ",".join(RECORDINGS))
    args = parser.parse_args()
    names = args.only.split(",") if args.only else list(QUICK if args.quick else RECORDINGS)
    start = time.perf_counter()
    results, rows = {}, []
    with tempfile.TemporaryDirectory() as tmp:
        for name in names:
            system, source = RECORDINGS[name]
            r = results[name] = audit(name, system, source, Path(tmp))
            named = [f"{f['what']} @ {f['target']}" for f in r.get("findings", [])]
            print(f"{name} ({system}, {r['seconds']:.0f} s): " + (r["refused"] if "refused" in r else
                  f"named {named or 'nothing'}; rejected {len(r['rejected'])}; "
                  f"structure remains in {[k for k, v in r['remaining'].items() if v['verdict'] != 'noise_floor']}"),
                  flush=True)
            rows.append(_schema.row(f"{name}: findings", "count", len(r.get("findings", [])), None, better="higher",
                                    note="real recording, no baseline (the patents' methods have no audit)"))
            rows.append(_schema.row(f"{name}: audit wall time", "s", r["seconds"], None))
            # written after every recording: a run stopped on the way (the Hilti files take minutes each) keeps
            # what it measured
            _schema.write(args.json, "audit_real", "audit", args.quick, time.perf_counter() - start, rows,
                          extra={"recordings": results, "complete": len(results) == len(names)})


if __name__ == "__main__":
    main()
