"""``selfcal qc``: quality control of a scan (VDI/VDE 2634-2 figures, deviation from a reference mesh)."""
from __future__ import annotations

import json

from selfcal.cli.common import UsageError, Verb, output, plain

QC_EXIT_CODES = {"pass": 0, "reported": 0, "fail": 3, "incomplete": 4, "cannot be vouched for": 5}  # 1 is an error, 2 a usage error


def qc_arguments(p) -> None:
    p.add_argument("scan", help="point cloud: .ply, .pcd, .xyz (or .xyz.gz / .txt columns x y z), metres")
    p.add_argument("--reference", help="reference mesh of the object in the scan's frame (.ply, .stl, .obj, ...)")
    p.add_argument("--spec", help="QC spec YAML: tolerances and detection settings (see docs/qc.md)")
    reports = p.add_argument_group("reports")
    reports.add_argument("--report", help="HTML report to write (deviation image embedded)")
    reports.add_argument("--markdown", help="Markdown report to write (deviation image next to it as .png)")
    reports.add_argument("--json", help="all figures and checks as JSON")
    reports.add_argument("--png", help="deviation image to write (default: next to the Markdown report)")


def qc(args) -> int:
    from selfcal.core.progress import TerminalProgress
    from selfcal.io.atomic import atomic_write_text
    from selfcal.io.pointcloud import read_point_attribute, read_point_cloud, read_triangle_mesh
    from selfcal.pipelines.qc.checks import run_qc
    from selfcal.pipelines.qc.report import write_reports
    from selfcal.pipelines.qc.spec import QCSpec
    if not (args.report or args.markdown or args.json):
        raise UsageError("nothing to write: give --report OUT.html, --markdown OUT.md and/or --json OUT.json")
    spec = QCSpec.from_yaml(args.spec) if args.spec else QCSpec()
    with TerminalProgress("qc") as progress:
        progress("read the scan")
        mesh = read_triangle_mesh(args.reference) if args.reference else None
        loaded = read_point_cloud(args.scan, drop_nonfinite=True)
        sigma = read_point_attribute(args.scan, "sigma_m")  # the predicted accuracy 'smooth scan' writes
        result = run_qc(loaded, spec, mesh, args.reference, progress=progress, point_sigma_m=sigma)
        progress("write the reports")
        written = write_reports(result, html_path=output(args.report) if args.report else None,
                                markdown_path=output(args.markdown) if args.markdown else None,
                                png_path=output(args.png) if args.png else None)
    for check in result.checks:
        value = "-" if check.value is None else (f"{check.value * 100:.4g} %" if check.unit == "fraction"
                                                 else f"{check.value * 1e3:.4g} mm")
        print(f"{check.name}: {value} [{check.status}]" + (f" ({check.note})" if check.value is None else ""))
    for warning in result.warnings:
        print(f"warning: {warning}")
    print(f"verdict: {result.verdict} ({result.seconds['total']:.1f} s)")
    if args.json:
        written["json"] = atomic_write_text(output(args.json),
                                            json.dumps(result.to_json(), indent=1, default=plain) + "\n")
    for kind, path in written.items():
        print(f"{kind}: {path}")
    return QC_EXIT_CODES[result.verdict]  # a CI job fails on a failed part without parsing the report


VERBS = (Verb("qc", "quality control of a scan (VDI/VDE 2634-2 figures, deviation from a reference)", qc_arguments, qc,
              epilog="exit status: 0 pass (or figures only), 3 fail, 4 incomplete (a toleranced check could not be "
                     "made), 5 cannot be vouched for (the scan's predicted accuracy misses the point tolerance), "
                     "1 error"),)
