"""``selfcal <verb> ...``: the parser, built from the verbs each module declares, and the one error handler.

Verbs come from two places.  Every system of :mod:`selfcal.registry` declares its own in ``cli/<system>.py``
(``VERBS``): a verb named after a group below becomes ``selfcal <group> <system>``, any other name a
top-level command.  The verbs that serve every system (audit, import, record, track, fleet) live in the
modules of :data:`SHARED`.  Known errors (:data:`selfcal.core.errors.USER_ERRORS`) print one line and exit 1.
"""
from __future__ import annotations

import argparse
import importlib
import logging
import sys

from selfcal import registry
from selfcal.cli.common import Parser, UsageError, Verb

GROUPS = {  # verbs that take a system as their next word
    "calibrate": "calibrate a sensor system from a recording",
    "smooth": "smooth a recording offline (or replay it online with --online)",
    "simulate": "write a simulated recording (ground truth in truth/)",
    "measure": "measure with a calibrated instrument",
    "plan": "plan a measurement before making it (predicted accuracy, no data needed)",
}
SHARED = ("audit", "importers", "streams", "fleet")  # cli modules of the verbs every system shares


class _Version(argparse.Action):
    """``--version``: the installed package's version, looked up only when asked (importlib.metadata is slow)."""

    def __init__(self, option_strings, dest, **kwargs):
        super().__init__(option_strings, dest, nargs=0, help="show the version and exit")

    def __call__(self, parser, namespace, values, option_string=None):
        from importlib.metadata import PackageNotFoundError, version
        try:
            number = version("selfcal")
        except PackageNotFoundError:  # a source tree that was never installed
            number = "unknown"
        print(f"selfcal {number}")
        parser.exit()


def _add_verb(subparsers, name: str, verb: Verb) -> None:
    p = subparsers.add_parser(name, help=verb.help, description=verb.help, epilog=verb.epilog)
    verb.arguments(p)
    p.set_defaults(run=verb.run)


def build_parser() -> Parser:
    parser = Parser(prog="selfcal", description="Instrument self-calibration and sensor fusion as GTSAM factor "
                                                "graphs, and an audit of what the model gets wrong.")
    parser.add_argument("-v", "--verbose", action="store_true", help="progress and diagnostics on stderr")
    parser.add_argument("--version", action=_Version)
    verbs = parser.add_subparsers(dest="verb", required=True, parser_class=Parser)
    groups = {name: verbs.add_parser(name, help=text, description=text).add_subparsers(
        dest="system", required=True, parser_class=Parser) for name, text in GROUPS.items()}
    for module in SHARED:
        for verb in importlib.import_module(f"selfcal.cli.{module}").VERBS:
            _add_verb(verbs, verb.name, verb)
    for system in registry.SYSTEMS:
        for verb in system.load("cli").VERBS:
            _add_verb(groups[verb.name] if verb.name in groups else verbs,
                      system.name if verb.name in groups else verb.name, verb)
    return parser


INPUT_ARGUMENTS = ("recording", "source", "scan", "datasets", "reference", "spec", "heldout")
OUTPUT_ARGUMENTS = ("out", "json", "report", "png", "out_tum", "markdown")


def check_outputs_apart_from_inputs(args) -> None:
    """An output may not replace an input: not the same path, not a folder holding an input, not an existing file
    inside an input folder (``--out REC/imu0/data.csv`` would destroy the recording being read)."""
    from pathlib import Path

    def paths(value):
        return [Path(v).resolve() for v in (value if isinstance(value, (list, tuple)) else [value]) if v]

    inputs = [p for name in INPUT_ARGUMENTS for p in paths(getattr(args, name, None))]
    for name in OUTPUT_ARGUMENTS:
        for out in paths(getattr(args, name, None)):
            for source in inputs:
                if out == source or source.is_relative_to(out) or (out.is_relative_to(source) and out.exists()):
                    raise UsageError(f"{name.replace('_', '-')} {out} would overwrite the input {source}: "
                                     "write it somewhere else")


class Terminated(BaseException):
    """SIGTERM as an exception, so that every ``finally`` and atomic writer removes its temporaries on the way out
    (a killed audit or scan left hidden temporary files)."""


def _terminate(signum, frame):
    raise Terminated()


def main(argv=None) -> int:
    import signal

    from selfcal.core.errors import USER_ERRORS
    previous = signal.signal(signal.SIGTERM, _terminate) if threading_is_main() else None
    try:
        args = build_parser().parse_args(argv)
        logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                            format="%(levelname)s %(name)s: %(message)s", stream=sys.stderr)
        check_outputs_apart_from_inputs(args)
        code = args.run(args)
    except USER_ERRORS as err:
        print(f"selfcal: error: {' '.join(str(err).split())}", file=sys.stderr)
        return 1
    except OSError as err:  # a full disk, a read-only file system, a name too long: the system's reason, one line
        where = f"{err.filename}: " if getattr(err, "filename", None) else ""
        print(f"selfcal: error: {where}{' '.join((err.strerror or str(err)).split())}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("selfcal: interrupted", file=sys.stderr)
        return 130
    except Terminated:
        print("selfcal: terminated", file=sys.stderr)
        return 143
    except Exception as err:  # noqa: BLE001 - the last line of defence: a bug, still one line (traceback under -v)
        if "-v" in (argv if argv is not None else sys.argv[1:]) or "--verbose" in (argv or sys.argv[1:]):
            import traceback
            traceback.print_exc()
        print(f"selfcal: internal error ({type(err).__name__}): {' '.join(str(err).split())[:300]}; this is a bug, "
              "please report it with the command (-v shows where)", file=sys.stderr)
        return 2
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
    return code or 0


def threading_is_main() -> bool:
    """Signal handlers can only be set from the main thread (tests may call main() from another)."""
    import threading
    return threading.current_thread() is threading.main_thread()


if __name__ == "__main__":
    sys.exit(main())
