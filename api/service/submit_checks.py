"""Checks made when a job is submitted, so that a job that cannot run is refused at once (422) rather than
accepted and failed a moment later: its topic map is well formed, and its pipeline's required topics
are in the recording once the map is applied.

The recording's topics are in the store (read once, at upload), so the check opens no file. Its
answer names what is missing and which pipelines the recording fits as it is, in terms the
service offers (the job's ``topic_map`` field, not the CLI's ``--topic-map``).
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from typing import Any

from slamreplay.api.service.store import RecordingRow
from slamreplay.replay.engine.pipeline import Pipeline, pipelines_fitting
from slamreplay.replay.engine.reader import resolve_topic_map
from slamreplay.replay.errors import ReplayError

MAX_TOPIC_MAP = 100


def parse_topic_map(raw: Any) -> dict[str, str]:
    """A job's or form's topic map (an object, or its JSON text) as ``{file topic: slamreplay topic}``; ReplayError
    saying what is wrong."""
    if isinstance(raw, str):
        raw = raw.strip()
        if not raw:
            return {}
        try:
            raw = json.loads(raw)
        except json.JSONDecodeError as err:
            raise ReplayError(f'topic_map is not JSON ({err.msg}): give an object such as {{"/wheel/odom": "/odom"}}'
                              ) from None
    if raw is None:
        return {}
    if not isinstance(raw, Mapping):
        raise ReplayError('topic_map must be an object mapping file topics to slamreplay topics, '
                          'e.g. {"/wheel/odom": "/odom"}')
    bad = [k for k, v in raw.items() if not isinstance(k, str) or not isinstance(v, str) or not k or not v]
    if bad:
        raise ReplayError(f"topic_map entry {bad[0]!r}: file topics and slamreplay topics are non-empty strings")
    if len(raw) > MAX_TOPIC_MAP:
        raise ReplayError(f"topic_map has {len(raw)} entries: at most {MAX_TOPIC_MAP}")
    return {str(k): str(v) for k, v in raw.items()}


def logical_counts(rec: RecordingRow, topic_map: Mapping[str, str]) -> dict[str, int]:
    """Messages per slamreplay topic of a stored recording, read through ``topic_map`` (as the replay will read
    it: an explicit entry wins over the identity and the ROS 2 automatic mapping); ReplayError for a map that
    names a topic the file lacks or a target that is not a slamreplay topic."""
    channels = [(str(t["topic"]), str(t.get("schema_name", ""))) for t in rec.topics]
    try:
        mapping = resolve_topic_map(channels, topic_map)
    except ReplayError as err:
        raise ReplayError(f"{rec.filename}: {err}") from None
    counts: dict[str, int] = {}
    for t in rec.topics:
        logical = mapping.get(str(t["topic"]))
        if logical is not None:
            counts[logical] = counts.get(logical, 0) + int(t.get("messages", 0))
    return counts


def check_fit(rec: RecordingRow, pipeline: type[Pipeline], topic_map: Mapping[str, str]) -> None:
    """ReplayError naming the topics ``pipeline`` needs that ``rec`` lacks (through ``topic_map``), the pipelines
    whose needs the recording meets, and how a topic map would help.

    A pipeline that replays every robot of a recording at once maps the robots' topics itself when it
    runs; it is left to the run."""
    if getattr(pipeline, "multi_robot", False):
        return
    counts = logical_counts(rec, topic_map)
    missing = [t for t in pipeline.required_topics if counts.get(t, 0) == 0]
    if not missing:
        return
    fitting = [p for p in pipelines_fitting(logical_counts(rec, {})) if p != pipeline.name]
    unmapped = sorted(str(t["topic"]) for t in rec.topics if str(t["topic"]) not in topic_map and not t.get("read_as"))
    lacks = ", ".join(missing)
    offer = f"pipelines this recording fits: {', '.join(sorted(fitting))}" if fitting else \
        "no installed pipeline fits this recording as it is"
    hint = (f'; or map a topic of the file onto it with the job\'s topic_map, e.g. {{"{unmapped[0]}": "{missing[0]}"}}'
            if unmapped else "")
    raise ReplayError(f"pipeline {pipeline.name} needs {lacks}, which {rec.filename} does not have"
                      f"{' (with the topic_map given)' if topic_map else ''}; {offer}{hint}")
