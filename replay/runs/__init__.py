"""Runs and versions: a run directory (``run``: replay, score and write ``run.rrd``, ``metrics.json``,
``manifest.json``, atomically), suites of runs (``suite``, ``suite_run``), and what compares them: two runs
(``diff``, ``diff_view``, ``trajectory_eval``), two result sets with statistics (``compare``, ``report``),
two git revisions in cached worktrees (``revisions``). The top room: it may import every other one.
"""
