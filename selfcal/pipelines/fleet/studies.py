"""Monte Carlo studies on the fleet's engine: seeds in blocks, one dask task per block, joined in seed order."""
from __future__ import annotations

import contextlib
import math
import uuid
from collections.abc import Callable
from dataclasses import dataclass

from selfcal import registry
from selfcal.core.progress import quiet
from selfcal.pipelines.fleet.engine import dask_client, submit_ordered


@dataclass(frozen=True)
class Study:
    """A Monte Carlo study: ``block(n_runs, first_seed, **params)`` runs seeds ``first_seed ..`` one after the
    other; ``combine(blocks)`` joins the blocks' results (given in seed order) into one."""

    name: str
    block: Callable
    combine: Callable


STUDIES: dict[str, Study] = {}


def register_study(name: str, block: Callable, combine: Callable) -> Study:
    """Make a Monte Carlo study runnable by :func:`run_study` (``block`` must be a module-level function)."""
    STUDIES[name] = Study(name, block, combine)
    return STUDIES[name]


def studies() -> dict[str, Study]:
    """Every study by name (each system with fleet tasks registers its own; found through the registry)."""
    for system in registry.SYSTEMS:
        if system.fleet:
            system.load("pipelines")
    return STUDIES


def _run_block(study: Study, n_runs: int, first_seed: int, params: dict):
    return study.block(n_runs, first_seed, **params)


def run_study(study: str | Study, n_runs: int, first_seed: int = 1000, block_size: int | None = None,
              client=None, scheduler: str | None = None, workers: int | None = None,
              progress: Callable = quiet, **params):
    """Run a Monte Carlo study on dask: seeds ``first_seed .. first_seed + n_runs - 1`` in blocks.

    Parameters
    ----------
    study : str or Study
        A name in :func:`studies`, or a :class:`Study`.
    n_runs, first_seed :
        The seeds (run ``k`` uses ``first_seed + k``, exactly as the study run in one process does).
    block_size : int, optional
        Runs per dask task (default: ``n_runs`` split into 4 blocks per worker, at least 1): a block pays the
        study's set-up (e.g. the bound) once.
    client, scheduler, workers, progress :
        As in :func:`run_fleet`.
    **params
        Passed to the study (e.g. ``scenario=...``).

    Returns
    -------
    The study's combined result; raises the first block's exception if a block failed (a study with holes
    would not be the study asked for).
    """
    spec = studies()[study] if isinstance(study, str) else study
    if n_runs < 1:
        raise ValueError(f"n_runs must be at least 1, not {n_runs}")
    with contextlib.ExitStack() as stack:
        if client is None:
            client = stack.enter_context(dask_client(scheduler, workers))
        n_workers = max(1, len(client.scheduler_info().get("workers", {})))
        size = block_size or max(1, math.ceil(n_runs / (4 * n_workers)))
        starts = list(range(0, n_runs, size))
        arguments = [(spec, min(size, n_runs - s), first_seed + s, params) for s in starts]
        run_id = uuid.uuid4().hex[:8]
        keys = [f"{spec.name}-{run_id}-{first_seed + s}-{min(size, n_runs - s)}" for s in starts]
        blocks = submit_ordered(client, _run_block, arguments, progress, keys, "blocks of seeds")
    for block in blocks:
        if isinstance(block, BaseException):
            raise block
    return spec.combine(blocks)
