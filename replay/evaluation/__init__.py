"""Evaluation: what a replay produced, scored against the recording's ground truth.

``evaluate`` (APE and RPE with explicit alignment and pose relation, as evo defines them), ``score``
(the trajectory metrics added to a replay's own), ``metrics`` (error, RMSE and NEES-band helpers that
pipelines use, and the metrics.json format), ``nees_series`` (a run's NEES over time with its chi-square
band, the ``nees.json`` artifact), ``landmark_reference`` (the batch least-squares reference map
of a real dataset). Metric names, units and directions come from ``slamreplay.replay.metric_registry``.
It may import the engine, never ``runs`` or ``tools``.
"""
