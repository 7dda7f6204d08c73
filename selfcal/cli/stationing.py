"""``selfcal calibrate stationing``: a mobile manipulator's prism and tilt-sensor mountings from total-station
stationing datasets (real Hilti data, docs/stationing.md)."""
from __future__ import annotations

from selfcal.cli.common import Verb, write_yaml


def calibrate_arguments(p) -> None:
    p.add_argument("datasets", nargs="+", help="dataset YAML file(s) (Hilti stationing format), fitted jointly")
    p.add_argument("--urdf", help="robot URDF (default: trailblazer.urdf next to the first dataset)")
    p.add_argument("--heldout", nargs="+", metavar="DATASET.yaml",
                   help="apply the calibration to these files: station from the stationing points, predict the "
                        "evaluation points, report the RMS against the total station")
    p.add_argument("--out", help="calibration YAML to write")


def calibrate(args) -> None:
    import numpy as np

    from selfcal.pipelines.stationing import calibrate_stationing, heldout_stationing
    cal = calibrate_stationing(args.datasets, urdf=args.urdf)
    print(cal.summary())
    out = cal.to_dict()
    if args.heldout:
        out["heldout"] = {}
        for path in args.heldout:
            h = heldout_stationing(cal.calibration, path, urdf=args.urdf)
            out["heldout"][h.name] = h.to_dict()
            print(f"held out {h.name}: evaluation points predicted from stationing points, RMS "
                  f"{np.round(h.rms_m * 1e3, 2).tolist()} mm (3D {np.linalg.norm(h.rms_m) * 1e3:.2f} mm); rigid "
                  f"stations with the URDF lever arm: {np.linalg.norm(h.baseline_rms_m) * 1e3:.2f} mm")
    if args.out:
        write_yaml(args.out, out)


VERBS = (Verb("calibrate", "prism lever arm, column bend and tilt-accelerometer mountings of a mobile manipulator "
                           "from total-station stationing datasets", calibrate_arguments, calibrate),)
