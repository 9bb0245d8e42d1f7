"""``slamreplay evaluate``: a trajectory estimated elsewhere, scored into a run directory.

A TUM file, a KITTI file (with its times), or a pose topic of a ROS 2 bag becomes a run of pipeline
``estimate`` on the recording whose ground truth it is scored against: the recording is replayed
(its ground truth only), the estimate is handed in at the end (``slamreplay.replay.tools.estimates``),
and ``run_recording`` writes the run as for any pipeline: ``trajectory.tum``, ``truth.tum``, the
trajectory metrics of the registry, ``run.rrd`` with the summary first, the manifest (with the
estimate file's sha256 under ``pipeline_origin``), atomically. ``diff``, ``compare`` and ``trajectory``
read it like any other run. Evaluating a run's own ``trajectory.tum`` reproduces its trajectory metrics.

Input is bounded and streamed: a file larger than ``max_bytes`` (:data:`MAX_ESTIMATE_BYTES` by default) is
refused before it is read, and files are read a line at a time. An estimate whose times (after ``t_offset``)
miss the recording's time span altogether is refused before anything is written, as evo refuses a pair without
matching times; one that covers less than ``min_coverage`` of the ground truth's span fails its run.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

from slamreplay.recorder.messages import TOPIC_GROUND_TRUTH_POSE
from slamreplay.replay.errors import ReplayError
from slamreplay.replay.runs.run import RunResult, run_recording, sha256_file
from slamreplay.replay.tools.estimates import (
    F64,
    I64,
    MAX_ESTIMATE_BYTES,
    Association,
    CoverageConfig,
    EstimateFormat,
    EstimateReplay,
    associate,
    read_kitti_ns,
    read_pose_topic,
    read_tum_ns,
    text_lines,
)

ESTIMATE_PIPELINE = "estimate"
FORMATS: tuple[EstimateFormat, ...] = ("tum", "kitti", "topic")


@dataclass(frozen=True, slots=True)
class EstimateConfig(CoverageConfig):
    """An estimate from a file has ``min_coverage`` only (its association is in the manifest)."""


def read_estimate(path: Path, fmt: EstimateFormat | None = None, *, topic: str | None = None,
                  times: Path | None = None, max_bytes: int = MAX_ESTIMATE_BYTES) -> tuple[I64, F64]:
    """(t_ns, poses (n, 3)) of an estimate file: ``tum`` (the default for a file), ``kitti`` (with ``times``,
    KITTI's times.txt), or ``topic`` of a ROS 2 bag (the default with ``topic``); ReplayError saying what is
    wrong. A TUM or KITTI file (and the times file) larger than ``max_bytes`` is refused before it is read."""
    fmt = fmt or ("topic" if topic is not None else "kitti" if path.suffix == ".kitti" else "tum")
    if not path.exists():
        raise ReplayError(f"estimate {path}: no such file")
    if fmt == "topic":
        if topic is None:
            raise ReplayError("a bag's estimate is read from a pose topic: give --topic (e.g. /slam/pose)")
        return read_pose_topic(path, topic)
    if topic is not None:
        raise ReplayError(f"--topic reads a pose topic of a ROS 2 bag; {path.name} is read as {fmt}: drop --topic "
                          f"or --format")
    if path.is_dir():
        raise ReplayError(f"estimate {path} is a folder: a ROS 2 bag? then give --topic")
    if fmt not in ("tum", "kitti"):
        raise ReplayError(f"--format must be one of {', '.join(FORMATS)}, got {fmt!r}")
    lines = text_lines(path, str(path), max_bytes)
    if fmt == "kitti":
        if times is None:
            raise ReplayError(f"a KITTI file ({path.name}) holds no times: give --times FILE (KITTI's times.txt, "
                              f"seconds, a line per pose)")
        try:
            return read_kitti_ns(lines, text_lines(times, f"times file {times}", max_bytes), str(path),
                                 f"times file {times}")
        except OSError as err:
            raise ReplayError(f"estimate {path} cannot be read: {err.strerror or err}") from None
    try:
        return read_tum_ns(lines, str(path))
    except OSError as err:
        raise ReplayError(f"estimate {path} cannot be read: {err.strerror or err}") from None


def estimate_pipeline(t_ns: I64, poses: F64, assoc: Association, origin: dict[str, Any]) -> type[EstimateReplay]:
    """A pipeline class, made for one run, whose trajectory is the given estimate after ``assoc``."""

    class FileEstimate(EstimateReplay):
        name: ClassVar[str] = ESTIMATE_PIPELINE
        summary: ClassVar[str] = "a trajectory estimated elsewhere (slamreplay evaluate), against /ground_truth/pose"
        required_topics: ClassVar[tuple[str, ...]] = (TOPIC_GROUND_TRUTH_POSE,)
        optional_topics: ClassVar[tuple[str, ...]] = ()
        start_topic: ClassVar[str] = TOPIC_GROUND_TRUTH_POSE
        Config: ClassVar[type] = EstimateConfig
        declared_origin: ClassVar[dict[str, Any]] = origin
        coverage_hint: ClassVar[str] = ("a clock offset? --t-offset-s S adds S seconds to the estimate's times "
                                        "(docs/external.md)")

        def estimate(self, t_gt: I64, gt: F64) -> tuple[I64, F64]:
            t, p = associate(t_ns, poses, t_gt, gt, assoc)
            if not len(t):
                raise ReplayError(f"no pose of the estimate is within {assoc.t_max_diff_ns} ns of a ground-truth "
                                  f"message (--t-max-diff-s)")
            self.ctx.log(f"estimate: {len(t):,} poses from {origin['entry_point']}, " +
                         ", ".join(f"{k} {v}" for k, v in assoc.as_dict().items()))
            return t, p

        def provenance(self) -> dict[str, Any]:
            return {"estimate": dict(origin), "association": assoc.as_dict()}

    return FileEstimate


def evaluate_estimate(estimate: str | Path, recording: str | Path, out_dir: str | Path, *,
                      fmt: EstimateFormat | None = None, topic: str | None = None, times: str | Path | None = None,
                      association: Association | None = None, run_id: str | None = None,
                      min_coverage: float | None = None, max_bytes: int = MAX_ESTIMATE_BYTES) -> RunResult:
    """Score the trajectory in ``estimate`` against ``recording``'s ground truth into the run ``out_dir``.

    ReplayError, before anything is written, when the estimate cannot be read (or is larger than
    ``max_bytes``), the recording has no ground truth, or no estimate time (after the association's offset)
    falls inside the recording's time span; the run directory is written as by ``run_recording`` (atomic
    files, manifest last), and the run fails when the estimate covers less than ``min_coverage`` (default
    :data:`~slamreplay.replay.tools.estimates.MIN_COVERAGE`) of the ground truth's time span.
    """
    path = Path(estimate)
    if not max_bytes > 0:
        raise ReplayError(f"--max-bytes must be > 0, got {max_bytes}")
    t_ns, poses = read_estimate(path, fmt, topic=topic, times=Path(times) if times is not None else None,
                                max_bytes=max_bytes)
    assoc = association or Association()
    file = path if path.is_file() else None
    origin = {"distribution": "estimate file", "version": "", "entry_point": str(path.resolve()),
              "format": fmt or ("topic" if topic else "tum"), "topic": topic or "",
              "sha256": sha256_file(file) if file is not None else "", "poses": str(len(t_ns))}
    from slamreplay.replay.engine.reader import RecordingReader
    from slamreplay.replay.engine.recording_file import check_recording

    check_recording(Path(recording))
    info = RecordingReader(recording).info
    if TOPIC_GROUND_TRUTH_POSE not in info.logical_topics():
        raise ReplayError(f"{Path(recording).name} has no {TOPIC_GROUND_TRUTH_POSE}: there is no ground truth to "
                          f"score an estimate against")
    first, last = int(t_ns[0]) + assoc.t_offset_ns, int(t_ns[-1]) + assoc.t_offset_ns
    if last < info.start_ns or first > info.end_ns:  # the truth lies within the recording: no pose can meet it
        offset = f" (after --t-offset-s {assoc.t_offset_ns / 1e9:g})" if assoc.t_offset_ns else ""
        raise ReplayError(f"{path.name}: no estimate time falls inside the recording's time span: the estimate runs "
                          f"from t={first / 1e9:.3f} to {last / 1e9:.3f} s{offset}, {Path(recording).name} from "
                          f"t={info.start_ns / 1e9:.3f} to {info.end_ns / 1e9:.3f} s: a clock offset? --t-offset-s S "
                          f"adds S seconds to the estimate's times")
    config = None if min_coverage is None else {"min_coverage": min_coverage}
    return run_recording(recording, estimate_pipeline(t_ns, poses, assoc, origin), out_dir, run_id=run_id,
                         config=config)


def association_from(t_offset_s: float = 0.0, t_max_diff_s: float | None = None,
                     alignment: str = "none") -> Association:
    """An :class:`Association` from command-line units (seconds); ReplayError for a bad value."""
    if t_max_diff_s is not None and not t_max_diff_s >= 0:
        raise ReplayError(f"--t-max-diff-s must be >= 0, got {t_max_diff_s}")
    if alignment not in ("none", "origin", "se2"):
        raise ReplayError(f"--align must be none, origin or se2, got {alignment!r}")
    return dataclasses.replace(Association(), t_offset_ns=round(t_offset_s * 1e9),
                               t_max_diff_ns=None if t_max_diff_s is None else round(t_max_diff_s * 1e9),
                               alignment=alignment)  # type: ignore[arg-type]

