"""Replay: recordings through pipelines, into run directories that are scored and compared.

Four rooms, each a sub-package, and the rule of which may import which (``tests/test_layers.py``):

- ``engine``: reads a recording (``reader``), steps one pipeline over it message by message (``loop``),
  logs what the pipeline shows to Rerun (``observer``, ``views``) and keeps its trajectory
  (``trajectory``). The plugin contract lives here (``pipeline``). It imports no other room.
- ``evaluation``: scores what the engine produced against the recording's ground truth: APE/RPE
  (``evaluate``), the error and NEES helpers pipelines use (``metrics``), the reference maps of real
  datasets (``landmark_reference``), and ``score``, which adds the trajectory metrics to a replay.
  It may import the engine.
- ``runs``: a run directory (``run``: replay, score, write ``run.rrd``, ``metrics.json``,
  ``manifest.json``), suites of runs, and what compares runs and versions: ``diff``, ``compare``,
  ``report``, ``revisions`` (git revisions in worktrees), ``trajectory_eval``. It may import every room.
- ``tools``: what works beside a run: ``inspect``, ``navigate`` (topo-metric navigation on a saved map),
  graph and map files, ``snapshot`` (a run drawn to PNG), the Victoria Park importer (``sources``) and
  the code fingerprint (``codeprint``). It may import the engine and evaluation.

``pipelines`` holds the built-in pipelines, found through entry points as a user's plugin is; they use
the engine, evaluation and tools. ``errors`` and ``metric_registry`` (every metric's name, unit and
direction: the one vocabulary) sit at the top: every room reads them, they import no room.

Plugins written against the old flat layout keep working: ``slamreplay.replay.pipeline``, ``reader``,
``metrics``, ``trajectory``, ``views`` and ``run`` are the same module objects as their new homes.
"""
