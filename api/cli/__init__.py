"""The command line: ``slamreplay`` and its commands, a module per command group.

``command`` builds the parser from every group's ``add_*_parser`` and dispatches (``slamreplay =
slamreplay.api.cli:main``, re-exported here); ``record_cli`` (record, inspect, recover), ``run_cli``
(run, navigate, diff, trajectory, snapshot), ``serve_cli`` (serve), ``demo``, ``suite_cli``, ``history_cli``,
``external_cli``, ``pipelines_cli``, ``graph_cli``, ``cache_cli``, ``live_cli`` (record live), ``push_cli``
and ``users_cli`` each own one group. ``cli_parser`` (the suggesting parser), ``hints`` (what to run next),
``progress`` (bars on a terminal, plain lines off one) and ``listen`` (the server's socket) serve them all.
It imports the service only to start it, to manage people in its store, and for the executors a local
suite run shares with the service (``tests/test_layers.py``).
"""

from slamreplay.api.cli.command import main

__all__ = ["main"]
