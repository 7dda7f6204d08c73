"""Command line: ``selfcal <verb> ...`` (:mod:`selfcal.cli.main`).

Parsing, progress and exit codes only; the work is in :mod:`selfcal.pipelines`.  Each system declares its own
verbs in ``cli/<system>.py``; verbs shared by all systems (audit, fleet, record, track, import) have a module
each.  No module here imports an estimator at import time: ``selfcal --help`` stays light.
"""
