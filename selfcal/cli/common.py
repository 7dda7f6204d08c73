"""What every verb module shares: the verb declaration, the one-line-error parser, output helpers."""
from __future__ import annotations

import argparse
import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from selfcal.core.errors import SelfcalError

log = logging.getLogger("selfcal")


@dataclass(frozen=True)
class Verb:
    """One command a module declares.

    In a system's module, a ``name`` among :data:`selfcal.cli.main.GROUPS` (``calibrate``, ``smooth``,
    ``simulate``, ``measure``) is the command ``selfcal <name> <system>``; any other name is a top-level
    command ``selfcal <name>`` (as ``qc``).  ``arguments`` adds the command's options to its parser; ``run``
    takes the parsed arguments and returns the exit code (None: 0).
    """

    name: str
    help: str
    arguments: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], int | None]
    epilog: str | None = None


class UsageError(SelfcalError):
    """A mistake in the command line: reported in one line, exit code 1."""


class Parser(argparse.ArgumentParser):
    def error(self, message):  # argparse would print the usage and exit 2; we promise one line and exit 1
        raise UsageError(f"{message} (see: {self.prog} --help)")


def output(path) -> Path:
    """An output path whose folder exists (created if needed: `--out results/cal.yaml` just works)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    return path


def write_yaml(path, data: dict) -> None:
    import yaml

    from selfcal.io.atomic import atomic_write_text
    atomic_write_text(output(path), yaml.safe_dump(data, sort_keys=False, default_flow_style=None))
    log.info("wrote %s", path)


def plain(obj):
    """JSON for numpy scalars and arrays (``json.dumps(..., default=plain)``)."""
    import numpy as np
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


def positive_float(text: str) -> float:
    """argparse type: a finite number > 0 (a speed factor, a duration)."""
    import argparse
    import math
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not math.isfinite(value) or value <= 0:
        raise argparse.ArgumentTypeError(f"{text!r} must be a number > 0")
    return value
