"""`slamreplay inspect`: what a recording holds, and whether it is healthy.

Health is checked for real: the framing (magic at both ends), the summary, a full pass over
every chunk with CRC validation, and the first message of every mapped topic decoded.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from slamreplay.recorder.errors import RecorderError
from slamreplay.recorder.sensor_model import SensorModel
from slamreplay.recorder.writer import METADATA_NAME
from slamreplay.replay.engine.pipeline import robots_in
from slamreplay.replay.engine.reader import RecordingReader, check_framing, resolve_mcap_path
from slamreplay.replay.errors import ReplayError


def empty_contradiction(metadata: Mapping[str, Mapping[str, str]], topics: list[str]) -> str | None:
    """Why a recording with no messages cannot be whole (None: nothing says it should hold any)."""
    if topics:
        return f"it declares {len(topics)} channel(s) ({', '.join(sorted(topics)[:4])})"
    source = metadata.get(METADATA_NAME, {}).get("source")
    if source is not None:
        return f"its {METADATA_NAME} metadata says it was produced by {source}"
    return None


def inspect_recording(path: str | Path, topic_map: Mapping[str, str] | None = None) -> dict[str, Any]:
    """A JSON-friendly report; ``health`` is ``ok``, ``truncated``, ``corrupt`` or ``empty`` with ``problems``.

    ``empty``: no messages although the file declares channels or its ``slamreplay.recording``
    metadata names what produced it (a recording that was recorded holds messages).

    Raises ReplayError when the path is missing, empty or not an MCAP at all.
    """
    mcap_path = resolve_mcap_path(Path(path))
    try:
        check_framing(mcap_path)
    except ReplayError as err:
        if "truncated" not in str(err):
            raise
        return {"path": str(mcap_path), "size_bytes": mcap_path.stat().st_size, "health": "truncated",
                "problems": [str(err)], "topics": []}
    problems: list[str] = []
    try:
        reader = RecordingReader(mcap_path, topic_map)
    except ReplayError as err:
        return {"path": str(mcap_path), "size_bytes": mcap_path.stat().st_size, "health": "corrupt",
                "problems": [str(err)], "topics": []}
    info = reader.info
    try:
        scanned = sum(1 for _ in reader.raw([t.file_topic for t in info.topics]))
        if scanned != info.message_count:
            problems.append(f"the summary counts {info.message_count} messages but {scanned} were read")
    except ReplayError as err:
        problems.append(str(err))
    for topic in info.logical_topics():
        try:
            next(reader.messages([topic]), None)
        except ReplayError as err:
            problems.append(str(err))
    health = "ok" if not problems else "corrupt"
    if info.message_count == 0 and not problems:
        why = empty_contradiction(info.metadata, [t.file_topic for t in info.topics])
        if why is not None:
            health = "empty"
            problems.append(f"the recording holds no messages, yet {why}: it is not a complete recording. If it "
                            f"came out of `slamreplay recover`, the damage left nothing readable")
    models: dict[str, dict[str, Any] | None] = {}
    for robot in ["", *robots_in(info)]:  # the recording's one robot, or each of several
        try:
            model = SensorModel.from_record(info.metadata.get(METADATA_NAME, {}), f"/robot{robot}" if robot else "")
        except RecorderError as err:
            model = None
            problems.append(str(err))
            health = "corrupt"
        models[robot] = None if model is None else {"values": model.values(), "source": model.source,
                                                    "lines": model.describe()}
    duration_s = (info.end_ns - info.start_ns) / 1e9
    return {
        "path": str(info.path),
        "size_bytes": info.size_bytes,
        "health": health,
        "problems": problems,
        "profile": info.profile,
        "library": info.library,
        "message_count": info.message_count,
        "chunk_count": info.chunk_count,
        "start_ns": info.start_ns,
        "end_ns": info.end_ns,
        "duration_s": duration_s,
        "topics": [
            {"topic": t.file_topic, "read_as": t.logical_topic, "schema": t.schema_name,
             "encoding": t.message_encoding, "messages": t.message_count,
             "rate_hz": round(t.message_count / duration_s, 3) if duration_s > 0 else None}
            for t in info.topics
        ],
        "metadata": info.metadata,
        # what pipelines use where the user sets nothing (`slamreplay.replay.engine.pipeline.resolve_layers`);
        # None: not stated
        "sensor_model": models.pop(""),
        # a multi-robot recording (topics under /robotN/): each robot's model, by N
        "robot_sensor_models": models,
    }
