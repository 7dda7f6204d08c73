"""``selfcal import KIND SOURCE OUT``: convert a dataset, a ROS bag, an EuRoC folder or an IMU text table into a
recording.  Each kind is a sub-command with its own options (``selfcal import rosbag --help``)."""
from __future__ import annotations

from pathlib import Path

from selfcal.cli.common import Parser, Verb

DATASET_KINDS = {  # the public datasets of selfcal.io.importers.IMPORTERS (kept here: --help imports no numpy)
    "imu-tk-xsens": "IMU-TK's Xsens MTi multi-position set (folder with xsens_acc/gyro.mat.gz)",
    "mpu6050-tomisuarez": "an MPU-6050 raw-count log of tomisuarez2/ImuCalibration (.csv[.gz])",
    "ansfl-quadrotor": "one ANSFL quadrotor flight (folder with IMU_1..4.csv.gz, GT.csv.gz)",
    "sunsided-mpu6050": "one scenario of sunsided/sensor-fusion set 2 (folder with mpu6050.csv.gz)",
    "adis16405-static": "one ADIS16405 static run of imudata (.npz)",
    "spherecalib-lidar": "the SphereCalib LiDAR scans (folder with L1_S<i>.xyz.gz)",
    "hilti-stationing": "one Hilti stationing dataset (<condition>.yaml, trailblazer.urdf beside it)",
}


def _source_out(p, source_help: str, metavar: str = "SOURCE") -> None:
    p.add_argument("source", metavar=metavar, help=source_help)
    p.add_argument("out", metavar="OUT", help="recording folder to write")
    p.add_argument("--overwrite", action="store_true", help="replace an existing OUT")


def import_arguments(p) -> None:
    kinds = p.add_subparsers(dest="kind", required=True, parser_class=Parser, metavar="KIND",
                             title="kinds (selfcal import KIND --help)")
    rosbag = kinds.add_parser("rosbag", help="topics of a ROS 1 (.bag) or ROS 2 (folder: metadata.yaml + .db3/.mcap) "
                                             "bag, at their header stamps")
    _source_out(rosbag, "a ROS 1 .bag file or a ROS 2 bag folder", metavar="BAG")
    topics = rosbag.add_argument_group("topics (one sensor each, numbered in the order given)")
    topics.add_argument("--imu", action="append", default=[], metavar="TOPIC",
                        help="sensor_msgs/msg/Imu -> imu0, imu1, ...")
    topics.add_argument("--points", action="append", default=[], metavar="TOPIC",
                        help="sensor_msgs/msg/PointCloud2 -> lidar0, ... (one .ply per cloud)")
    topics.add_argument("--pose", action="append", default=[], metavar="TOPIC",
                        help="geometry_msgs/msg/PointStamped or PoseStamped -> pose0, ...")

    euroc = kinds.add_parser("euroc", help="the IMU of an EuRoC dataset (its mav0 folder or the folder above it); "
                                           "other folders are not read")
    _source_out(euroc, "the mav0 folder, or the folder holding it")
    euroc.add_argument("--imu", action="append", default=[], metavar="FOLDER",
                       help="IMU folder inside mav0 (default: imu0; repeat for more)")

    table = kinds.add_parser("imu-table", help="an IMU from text table(s) described by a YAML column/unit map "
                                               "(docs/importers.md)")
    _source_out(table, "the table file, or the folder holding the files the map names")
    table.add_argument("--map", required=True, metavar="MAP.yaml",
                       help="files, delimiter, header, time column and unit, the six channels' columns and units")

    for kind, text in DATASET_KINDS.items():
        _source_out(kinds.add_parser(kind, help=text), "dataset file or folder")


def import_dataset(args) -> None:
    from selfcal.io.recording import write_recording
    out = Path(args.out)
    if out.exists() and not args.overwrite:  # refuse before reading a bag of gigabytes, not after
        raise FileExistsError(f"{out}: already exists (pass --overwrite to replace it)")
    source = Path(args.source)
    if args.kind == "rosbag":
        from selfcal.io.rosbag import import_rosbag
        rec = import_rosbag(source, args.imu, args.points, args.pose)
    elif args.kind == "euroc":
        from selfcal.io.euroc import import_euroc
        rec = import_euroc(source, args.imu or ["imu0"])
    elif args.kind == "imu-table":
        from selfcal.io.imu_table import import_imu_table, read_imu_map
        rec = import_imu_table(source, read_imu_map(args.map), where=args.map)
    else:
        from selfcal.io.importers import IMPORTERS
        rec = IMPORTERS[args.kind](source)
    path = write_recording(rec, out, overwrite=args.overwrite)
    print(f"wrote {path} ({', '.join(rec.sensors)})")


VERBS = (Verb("import", "convert a dataset, a ROS bag, an EuRoC folder or an IMU table into a recording",
              import_arguments, import_dataset),)
