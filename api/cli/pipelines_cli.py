"""``slamreplay pipelines [NAME]``: every pipeline in brief, or one in full (needs, config keys, presets, metrics)."""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

from slamreplay.api.cli.cli_parser import EXIT_BAD_INPUT, EXIT_OK
from slamreplay.recorder.options import did_you_mean
from slamreplay.replay.errors import ReplayError


def add_pipelines_parser(sub: Any) -> None:
    """Add the ``pipelines`` command to the CLI's subparsers."""
    pl = sub.add_parser("pipelines", help="list pipelines, the topics they need and their config keys",
                        description="Without NAME: every installed pipeline, its topics, config keys, presets and "
                                    "metrics. With NAME: that pipeline in full, each metric with its unit, direction "
                                    "and meaning.")
    pl.add_argument("name", nargs="?", metavar="NAME", help="show this pipeline only (e.g. dslam)")
    pl.add_argument("--json", action="store_true", help="machine-readable output")
    pl.set_defaults(func=cmd_pipelines)


def _metric(m: Any) -> dict[str, Any]:
    out = {"better": m.better, "unit": m.unit, "description": m.description}
    if getattr(m, "target", None) is not None:
        out["target"] = m.target
    if getattr(m, "optional", ""):
        out["optional"] = m.optional
    return out


def _row(name: str, plugin: Any) -> dict[str, Any]:
    """What ``pipelines`` says of one pipeline (its ``--json`` object)."""
    from slamreplay.replay.engine.pipeline import config_schema
    from slamreplay.replay.evaluation.score import metric_specs

    where = {"name": name, "origin": plugin.origin, "distribution": plugin.distribution,
             "version": plugin.version, "entry_point": plugin.value}
    if plugin.error is not None:
        return {**where, "error": plugin.error}
    cls = plugin.load()
    return {**where, "error": None, "summary": cls.summary, "required_topics": list(cls.required_topics),
            "optional_topics": list(cls.optional_topics), "config": config_schema(cls.Config),
            "presets": {k: dict(v) for k, v in cls.presets.items()},
            "metrics": {k: _metric(m) for k, m in metric_specs(cls).items()}}


def _direction(m: dict[str, Any]) -> str:
    if m["better"] == "target":
        return f"best at {m.get('target')}"
    return "describes the run" if m["better"] == "none" else f"{m['better']} is better"


def _print_row(r: dict[str, Any], full: bool) -> None:
    if r["error"] is not None:
        print(f"{r['name']}: BROKEN ({r['origin']}, {r['entry_point']}): {r['error']}")
        return
    print(f"{r['name']}: {r['summary']}")
    print(f"  from:     {r['origin']}" + ("" if r["origin"] == "built-in" else f" ({r['entry_point']})"))
    print(f"  needs:    {', '.join(r['required_topics'])}")
    if r["optional_topics"]:
        print(f"  uses:     {', '.join(r['optional_topics'])}")
    for c in r["config"]:
        print(f"  --set {c['key']}=<{c['type']}>  (default {c['default']}) {c['help']}")
    if not r["config"]:
        print("  config:   (no keys)")
    for preset, values in r["presets"].items():
        print(f"  --preset {preset}: " + (", ".join(f"{k}={v}" for k, v in values.items())
                                        or "the defaults (they are already the paper's)"))
    if not full:
        print("  metrics:  " + ", ".join(f"{k} ({_direction(m)})" if m["better"] != "none" else k
                                         for k, m in r["metrics"].items()))
        return
    for k, m in r["metrics"].items():
        unit = f"{m['unit']}, " if m["unit"] else ""
        optional = f" [may be left out: {m['optional']}]" if m.get("optional") else ""
        print(f"  metric {k} ({unit}{_direction(m)}): {m['description']}{optional}")


def cmd_pipelines(args: argparse.Namespace) -> int:
    """List the pipelines (or show NAME); exit 2 when an installed pipeline plugin is broken."""
    if args.name is not None:  # a mistyped NAME is told from the entry points' names, before any pipeline loads
        from importlib.metadata import entry_points

        from slamreplay.replay.engine.declared import declaration_files

        names = sorted({ep.name for ep in entry_points(group="slamreplay.pipelines")})
        names = [] if declaration_files() else names  # declared pipelines (docs/external.md) are checked below
        if names and args.name not in names:
            raise ReplayError(f"unknown pipeline {args.name!r}{did_you_mean(args.name, names, True)}; known "
                              f"pipelines: {', '.join(names)}")
    from slamreplay.recorder.plugins import missing_builtins_hint
    from slamreplay.replay.engine.pipeline import PIPELINE_GROUP, pipeline_plugins

    plugins = pipeline_plugins()
    if not plugins:
        raise ReplayError(missing_builtins_hint(PIPELINE_GROUP))
    if args.name is not None:
        if args.name not in plugins:
            raise ReplayError(f"unknown pipeline {args.name!r}{did_you_mean(args.name, plugins, True)}; known "
                              f"pipelines: {', '.join(plugins)}")
        plugins = {args.name: plugins[args.name]}
    rows = [_row(name, plugin) for name, plugin in plugins.items()]
    broken = [plugins[r["name"]].describe() + " " + r["error"] for r in rows if r["error"] is not None]
    if args.json:
        print(json.dumps(rows[0] if args.name is not None else rows, indent=2, default=str))
    else:
        for r in rows:
            _print_row(r, full=args.name is not None)
    for line in broken:  # listed above; and one line each on stderr, exit 2: an installed plugin does not work
        print(f"slamreplay: error: {line}", file=sys.stderr)
    return EXIT_BAD_INPUT if broken else EXIT_OK
