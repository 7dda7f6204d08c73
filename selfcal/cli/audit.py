"""``selfcal audit``: find what the model gets wrong in a recording, name the cause, measure the gain."""
from __future__ import annotations

import json

from selfcal import registry
from selfcal.cli.common import UsageError, Verb, log, output, plain


def audit_arguments(p) -> None:
    p.add_argument("recording")
    audited = registry.names("audit")
    p.add_argument("--system", required=True, choices=audited)
    bases = "; ".join(f"{s}: {' or '.join(registry.system(s).audit)}" for s in audited)
    p.add_argument("--base", help=f"base model (default: the first) -- {bases}")
    p.add_argument("--imu", help="IMU to audit (imu, ship) or reference IMU (imu-pair); default: the first")
    p.add_argument("--imu1", help="second IMU for imu-pair; default: the second")
    p.add_argument("--json", help="findings in the audit JSON contract")
    p.add_argument("--report", help="HTML report with plots")


def audit(args) -> None:
    from selfcal.io.atomic import atomic_write_text
    from selfcal.io.recording import read_recording
    from selfcal.pipelines.audit import audit_recording
    if not args.json and not args.report:
        raise UsageError("nothing to write: give --json OUT.json and/or --report OUT.html")
    rec = read_recording(args.recording)
    sensors = [name for name in (args.imu, args.imu1) if name] or None
    run = audit_recording(rec, args.system, args.base, sensors, progress=log.info)
    contract = run.to_json()
    for finding in contract["findings"]:
        print(f"found {finding['effect']} ({finding['target']}): RMS {finding['gain']['rms_before']:.4g} -> "
              f"{finding['gain']['rms_after']:.4g}, held-out {finding['gain']['heldout_rms_before']:.4g} -> "
              f"{finding['gain']['heldout_rms_after']:.4g}"
              + (" [ambiguous with " + ", ".join(r["effect"] for r in finding["ambiguous_with"]) + "]"
                 if finding.get("ambiguous_with") else ""))
    if not contract["findings"]:
        print("no finding: the data give no significant evidence against the base model")
    if args.json:
        atomic_write_text(output(args.json), json.dumps(contract, indent=1, default=plain) + "\n")
        log.info("wrote %s", args.json)
    if args.report:
        from selfcal.audit.report import write_report
        write_report(run.result, output(args.report), run.report_extras(str(args.recording)))
        print(f"report: {args.report}")


VERBS = (Verb("audit", "find what the model gets wrong in a recording, name the cause, measure the gain",
              audit_arguments, audit),)
