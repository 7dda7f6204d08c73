"""How far a long step is: the library reports, the command line shows it, everything else stays quiet.

A long step takes a ``progress`` callable and calls it as each named stage starts, and inside a counted loop::

    progress("fit the base model")
    for i, frame in enumerate(frames):
        progress("frames", i, len(frames))

``progress(stage, done=None, total=None)``: ``stage`` names what runs now; ``done`` of ``total`` counts a loop
(the same ``stage`` on every call of the loop).  The library's default is :func:`quiet`; the command line
passes a :class:`TerminalProgress`, a tqdm bar on stderr that is off when stderr is not a terminal (a pipe, a
log file, a test's capture), so scripted runs print their results and nothing else.
"""
from __future__ import annotations

import logging
import sys

log = logging.getLogger("selfcal.progress")


def quiet(stage: str, done: int | None = None, total: int | None = None) -> None:
    """Report nothing: the library's default."""


class TerminalProgress:
    """A tqdm bar on stderr for one command: ``title: stage`` with elapsed time, and a counted bar in loops.

    Each new stage is also logged at INFO (``-v`` keeps the stage lines when stderr is a file).  Use it as a
    context manager; while it is open, log records are written above the bar instead of through it.

    Parameters
    ----------
    title : str
        What runs, as the user typed it (``qc``, ``smooth ship``).
    enabled : bool or None
        None (default): on when ``file`` is a terminal (tqdm's ``disable=None``); True / False force it.
    file : text stream, optional
        Where the bar is drawn (default ``sys.stderr``).
    """

    STAGE_FORMAT = "{desc} [{elapsed}]"
    COUNT_FORMAT = "{desc}: {percentage:3.0f}%|{bar}| {n_fmt}/{total_fmt} [{elapsed}<{remaining}]"

    def __init__(self, title: str, enabled: bool | None = None, file=None):
        self.title, self.enabled, self.file = title, enabled, file
        self.stage: str | None = None
        self.bar = None

    def __enter__(self) -> TerminalProgress:
        import contextlib

        from tqdm import tqdm
        from tqdm.contrib.logging import logging_redirect_tqdm
        self.bar = tqdm(desc=self.title, file=self.file or sys.stderr, disable=None if self.enabled is None
                        else not self.enabled, leave=False, bar_format=self.STAGE_FORMAT, dynamic_ncols=True)
        self._redirect = logging_redirect_tqdm() if not self.bar.disable else contextlib.nullcontext()
        self._redirect.__enter__()
        return self

    def __exit__(self, *exc) -> None:
        self._redirect.__exit__(*exc)
        self.bar.close()

    def __call__(self, stage: str, done: int | None = None, total: int | None = None) -> None:
        if self.bar is None:
            raise RuntimeError("TerminalProgress is used as a context manager: with TerminalProgress(...) as p")
        if stage != self.stage:
            self.stage = stage
            log.info("%s: %s", self.title, stage)
            self.bar.reset(total=total)
            self.bar.bar_format = self.COUNT_FORMAT if total else self.STAGE_FORMAT
            self.bar.set_description_str(f"{self.title}: {stage}", refresh=False)
            self.bar.refresh()
        if done is not None:
            self.bar.update(done - self.bar.n)  # tqdm redraws at most every 0.1 s: cheap inside a loop
