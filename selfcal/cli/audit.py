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
    from selfcal.core.progress import TerminalProgress
    from selfcal.io.atomic import atomic_write_texts
    from selfcal.io.recording import read_recording
    from selfcal.pipelines.audit import audit_recording
    if not args.json and not args.report:
        raise UsageError("nothing to write: give --json OUT.json and/or --report OUT.html")
    if args.json and args.report and output(args.json).resolve() == output(args.report).resolve():
        raise UsageError("--json and --report name the same file: give two paths")
    with TerminalProgress(f"audit {args.system}") as progress:
        rec = read_recording(args.recording)
        sensors = [name for name in (args.imu, args.imu1) if name] or None
        run = audit_recording(rec, args.system, args.base, sensors, progress=progress)
        contract = run.to_json()
        texts = {}
        if args.json:
            texts[output(args.json)] = json.dumps(contract, indent=1, default=plain) + "\n"
        if args.report:
            from selfcal.audit.report import render_report
            progress("write the report")
            texts[output(args.report)] = render_report(run.result, run.report_extras(str(args.recording)))
        atomic_write_texts(texts)  # the JSON and the HTML of one audit: both or neither
    print_summary(contract)  # after the bar is gone: results on stdout, never mixed with it
    if args.report:
        print(f"report: {args.report}")


def print_summary(contract: dict) -> None:
    """What the audit found, what passed the significance test but was not accepted, and what remains."""
    from selfcal.audit.engine import entry_name
    for finding in contract["findings"]:
        gain = finding["gain"]  # a noise finding's RMS is a relative error of the Allan deviation: no unit
        unit = f" {gain['unit']}" if gain.get("unit") else " (relative)" if "metric" in gain else ""
        name = finding["effect"] if finding["effect"] != "unlisted" else f"unlisted: {finding['meaning']}"
        print(f"found {name} ({finding['target']}): RMS {gain['rms_before']:.4g} -> {gain['rms_after']:.4g}{unit}, "
              f"held-out {gain['heldout_rms_before']:.4g} -> {gain['heldout_rms_after']:.4g}{unit}"
              + (" [ambiguous with " + ", ".join(entry_name(r) for r in finding["ambiguous_with"]) + "]"
                 if finding.get("ambiguous_with") else "")
              + (f" [same as the library term {finding['same_as']['form']} in {finding['same_as']['driver']}]"
                 if finding.get("same_as") else ""))
    rejected = contract.get("rejected", [])
    for entry in rejected:
        by = entry.get("outdone_by") or {}
        print(f"not accepted: {entry_name(entry)} ({entry['target']}, p={entry['evidence']['p_value']:.2g}): "
              f"{REASONS[entry['reason']]}" + (f" ({by['form']} in {by['driver']})" if by.get("form") else ""))
    if not contract["findings"]:
        if rejected:
            print(f"no finding accepted: {len(rejected)} candidate(s) passed the significance test but were "
                  "rejected (above)")
        else:
            print("no finding: the data give no significant evidence against the base model")
    for label, verdict in contract.get("remaining", {}).items():
        if verdict["verdict"] == "structure_remains":
            strongest = verdict.get("strongest") or {}
            term = (f"strongest term {strongest['form']} in {strongest['driver']}, p={strongest['p_value']:.2g}"
                    if strongest else "")
            white = (f"whiteness p={verdict['whiteness_p']:.2g}" if verdict.get("whiteness_p") is not None else "")
            print(f"structure remains in {label}: " + "; ".join(x for x in (term, white) if x))


REASONS = {"bic": "the BIC does not fall", "heldout": "does not predict held-out data",
           "implausible": "estimate outside its physically plausible range",
           "outdone": "a library term explains the same residual better"}


VERBS = (Verb("audit", "find what the model gets wrong in a recording, name the cause, measure the gain",
              audit_arguments, audit),)
