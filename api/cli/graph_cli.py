"""``slamreplay graph optimize``: the pose-graph back end on g2o and TORO files."""

from __future__ import annotations

import argparse
import json
from typing import Any

# The choices of replay/tools/graph_io.py (SOLVERS, INITS, ROBUST), spelled here so that building the parser does not
# import the pose-graph solver (scipy) before every command; tests/api/test_cli_startup.py checks they agree.
SOLVERS = ("gn", "lm")
INITS = ("odometry", "chordal", "file")
ROBUST = ("none", "dcs", "huber", "cauchy")


def add_graph_parser(sub: Any) -> None:
    """Add the ``graph`` command group to the CLI's subparsers."""
    graph = sub.add_parser("graph", help="pose-graph tools (g2o VERTEX_SE2/EDGE_SE2, TORO VERTEX2/EDGE2)")
    gsub = graph.add_subparsers(dest="graph_command", required=True, metavar="GRAPH_COMMAND")
    opt = gsub.add_parser("optimize", help="optimize a 2D pose graph file (maximum likelihood, sparse GN/LM)",
                          description="Optimize a g2o or TORO 2D pose graph and write the result. chi2 follows "
                                      "g2o's EDGE_SE2 convention: e = t2v(Z^-1 X_i^-1 X_j), chi2 = sum e^T Omega e.")
    opt.add_argument("file", help="input graph (.g2o or TORO .graph)")
    opt.add_argument("--out", required=True, help="output graph; format from its extension (.g2o or .graph)")
    opt.add_argument("--solver", choices=SOLVERS, default="gn", help="Gauss-Newton or Levenberg-Marquardt (default gn)")
    opt.add_argument("--init", choices=INITS, default="odometry",
                     help="initial guess: odometry composition, chordal (rotations first), or the file's vertices")
    opt.add_argument("--robust", choices=ROBUST, default="dcs",
                     help="kernel on loop closures (default dcs: Dynamic Covariance Scaling with phi graduated "
                          "down to 1, then closures failing a chi-square gate are dropped and the rest re-solved "
                          "without a kernel; chi2_final is over the kept edges, edges_rejected counts the dropped)")
    opt.add_argument("--rrd", metavar="OUT.rrd", help="log the graph before and after and chi2 per iteration")
    opt.add_argument("--json", action="store_true", help="print the summary as JSON")
    opt.set_defaults(func=cmd_graph_optimize)


def cmd_graph_optimize(args: argparse.Namespace) -> int:
    from slamreplay.replay.errors import ReplayError
    from slamreplay.replay.tools.graph_io import GraphFileError, optimize_file

    try:
        summary = optimize_file(args.file, args.out, solver=args.solver, init=args.init, robust=args.robust,
                                rrd_path=args.rrd)
    except (GraphFileError, FileNotFoundError, FileExistsError) as err:
        raise ReplayError(str(err)) from err
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        for key in ("vertices", "edges", "chi2_initial", "chi2_final", "edges_rejected", "iterations", "status",
                    "time_s"):
            print(f"  {key:<14} {summary[key]}")
        print(f"wrote {args.out}" + (f"; open the log with: rerun {args.rrd}" if args.rrd else ""))
    return 0
