"""``selfcal fleet``: one task per recording (a production line, a test campaign) on dask.distributed."""
from __future__ import annotations

import logging
import sys

from selfcal import registry
from selfcal.cli.common import UsageError, Verb, output


def fleet_arguments(p) -> None:
    p.add_argument("source", help="folder of recordings, or a manifest (.yaml/.csv; see docs/fleet.md)")
    p.add_argument("--task", required=True,
                   help="calibrate-imu, calibrate-imu-pair, calibrate-encoder, audit, or any task a system registered")
    p.add_argument("--out", required=True, help="result table TABLE.csv or TABLE.parquet (both are written)")
    p.add_argument("--report", help="short report: .html (plots embedded) or .md")
    cluster = p.add_argument_group("cluster")
    cluster.add_argument("--scheduler", help="address of a running dask scheduler (default: a local cluster)")
    cluster.add_argument("--workers", type=int, help="worker processes of the local cluster (default 2)")
    options = p.add_argument_group("task options")
    options.add_argument("--system", help=f"audit: the system ({', '.join(registry.names('audit'))})")
    options.add_argument("--imu", help="IMU to use (calibrate-imu, audit; default: the first)")
    options.add_argument("--imu1", help="second IMU (audit imu-pair; default: the second)")
    options.add_argument("--option", action="append", metavar="KEY=VALUE",
                         help="any further task option for every recording (repeatable; value read as YAML)")


def _task_options(args) -> dict:
    import yaml
    options = {"system": args.system, "imu": args.imu, "imu1": args.imu1}
    for item in args.option or []:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise UsageError(f"--option {item!r}: expected KEY=VALUE")
        options[key.strip().replace("-", "_")] = yaml.safe_load(value)
    return options


def dashboard_line(client) -> str:
    """Where to watch the fleet: the scheduler and its dashboard (served only when bokeh is installed)."""
    import importlib.util
    link = client.dashboard_link
    if link and importlib.util.find_spec("bokeh") is None:
        link += " (its pages need the bokeh package: pip install bokeh)"
    return f"dask scheduler {client.scheduler.address}, dashboard {link or 'not served'}"


def fleet(args) -> None:
    from selfcal.core.progress import TerminalProgress
    from selfcal.pipelines.fleet import dask_client, fleet_plan, run_fleet, write_fleet_report, write_table
    if not args.verbose:  # dask logs every scheduler and worker start at INFO: one line below says where it runs
        import dask
        import distributed  # noqa: F401  (it sets its loggers' levels when imported: quiet them after that)
        logging.getLogger("distributed").setLevel(logging.WARNING)
        dask.config.set({"logging.distributed": "warning"})  # the worker processes read it as they start
    options = _task_options(args)
    if not args.out.lower().endswith((".csv", ".parquet")):
        raise UsageError(f"--out {args.out}: the table is TABLE.csv or TABLE.parquet (both are written)")
    fleet_plan(args.source, args.task, options)  # a wrong task or option is refused before a cluster starts
    with dask_client(args.scheduler, args.workers) as client:
        print(dashboard_line(client), file=sys.stderr, flush=True)
        with TerminalProgress("fleet") as progress:
            result = run_fleet(args.source, args.task, options, progress=progress, client=client)
    paths = write_table(result.table, output(args.out))
    print(f"{len(result.table)} recordings, {result.n_failed} failed, {result.seconds:.1f} s on "
          f"{result.workers} worker(s); table: {', '.join(map(str, paths))}")
    if args.report:
        print(f"report: {write_fleet_report(result, output(args.report))}")


VERBS = (Verb("fleet", "run one task per recording (a production line, a test campaign) on dask", fleet_arguments,
              fleet),)
