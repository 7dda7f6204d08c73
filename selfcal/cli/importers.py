"""``selfcal import``: convert a public dataset into a recording."""
from __future__ import annotations

from pathlib import Path

from selfcal.cli.common import UsageError, Verb


def import_arguments(p) -> None:
    p.add_argument("kind", help="dataset kind: imu-tk-xsens, mpu6050-tomisuarez, ansfl-quadrotor, sunsided-mpu6050, "
                                "adis16405-static")
    p.add_argument("source", help="dataset file or folder")
    p.add_argument("out", help="recording folder to write")
    p.add_argument("--overwrite", action="store_true")


def import_dataset(args) -> None:
    from selfcal.io.importers import IMPORTERS
    from selfcal.io.recording import write_recording
    if args.kind not in IMPORTERS:
        raise UsageError(f"unknown dataset kind {args.kind!r}; known: {', '.join(sorted(IMPORTERS))}")
    rec = IMPORTERS[args.kind](Path(args.source))
    path = write_recording(rec, Path(args.out), overwrite=args.overwrite)
    print(f"wrote {path} ({', '.join(rec.sensors)})")


VERBS = (Verb("import", "convert a public dataset into a recording", import_arguments, import_dataset),)
