"""Importer for the UTIAS MRCLAM dataset [1]_: one robot of one dataset folder per recording.

A dataset folder holds ``Barcodes.dat``, ``Landmark_Groundtruth.dat`` and, per robot N in 1..5,
``RobotN_Odometry.dat``, ``RobotN_Groundtruth.dat`` and ``RobotN_Measurement.dat``
(whitespace-separated text, ``#`` comments). The recording holds:

- ``/ground_truth/landmarks``: the 15 landmarks (ids = subject numbers 6..20), once, stamped
  with the earliest time in the recording;
- ``/ground_truth/pose``: the Vicon poses in ``world``;
- ``/odom``: the odometry velocities integrated with a unicycle model, forward Euler between
  consecutive timestamps (each sample's velocities held until the next sample), from (0, 0, 0)
  at the first odometry sample. Repeated timestamps give one pose;
- ``/landmarks/range_bearing``: one scan per measurement timestamp. Barcodes map to subjects
  through ``Barcodes.dat``; sightings of robots (subjects 1..5) and unknown barcodes are dropped.
  Sigmas are 0: the dataset states none.

Times are the dataset's Unix-epoch seconds with millisecond resolution, converted exactly to
integer nanoseconds by rounding to the millisecond. Equal stamps are written in the order
landmark map, ground truth, odometry, scan.

References
----------
.. [1] K. Y. K. Leung, Y. Halpern, T. D. Barfoot, H. H. T. Liu, "The UTIAS multi-robot
   cooperative localization and mapping dataset", IJRR 30(8):969-974, 2011.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Final

import numpy as np
from numpy.typing import NDArray

from recorder.errors import RecorderError
from recorder.messages import (
    TOPIC_GROUND_TRUTH_LANDMARKS,
    TOPIC_GROUND_TRUTH_POSE,
    TOPIC_ODOM,
    TOPIC_RANGE_BEARING,
    GroundTruthPose,
    LandmarkMap,
    Message,
    OdometryPose,
    RangeBearingScan,
)
from recorder.writer import Recorder

IMPORTER: Final = "mrclam"
DATASET: Final = "MRCLAM Dataset6"
ROBOTS: Final = range(1, 6)  # subjects 1..5 are the robots; the landmarks are subjects 6..20
NS_PER_MS: Final = 1_000_000

Progress = Callable[[int, int], None]


@dataclass(frozen=True, slots=True)
class ImportSummary:
    """What :func:`import_mrclam` wrote."""

    path: Path
    robot: int
    messages: int
    odometry_poses: int
    ground_truth_poses: int
    scans: int
    measurements_kept: int
    robot_sightings_dropped: int
    unknown_barcodes_dropped: int
    landmarks: int
    start_ns: int
    end_ns: int


def _time_ns(token: str) -> int:
    """Unix seconds (ms resolution) -> int ns, exactly: round to the millisecond first."""
    seconds = float(token)
    if not math.isfinite(seconds) or seconds < 0:
        raise ValueError(f"time {token!r} is not a finite, nonnegative number of seconds")
    return round(seconds * 1000.0) * NS_PER_MS


def _float(token: str) -> float:
    value = float(token)
    if not math.isfinite(value):
        raise ValueError(f"{token!r} is not a finite number")
    return value


def _nonnegative(token: str) -> float:
    value = _float(token)
    if value < 0:
        raise ValueError(f"{token!r} is negative")
    return value


_PARSERS: Final[dict[str, Callable[[str], float | int]]] = {"t": _time_ns, "i": int, "f": _float, "n": _nonnegative}


def _read_dat(path: Path, columns: tuple[str, ...], kinds: str, *,
              sorted_by_time: bool = False) -> list[list[float | int]]:
    """Columns of a whitespace-separated ``.dat`` file; ``kinds`` gives each column's type.

    ``t`` is a time (to int ns), ``i`` an integer, ``f`` a finite float, ``n`` a nonnegative one. Raises RecorderError
    naming the file and line of anything malformed, or of a time that goes backwards.
    """
    if not path.is_file():
        msg = (f"{path} is missing: an MRCLAM dataset folder holds Barcodes.dat, Landmark_Groundtruth.dat and "
               f"RobotN_Odometry.dat, RobotN_Groundtruth.dat, RobotN_Measurement.dat for N = 1..5; "
               f"pass the folder that holds them (see ../shared/data/mrclam-dataset6/README.md)")
        raise RecorderError(msg)
    parsers = [_PARSERS[k] for k in kinds]
    out: list[list[float | int]] = [[] for _ in kinds]
    try:
        text = path.read_text(encoding="ascii")
    except (OSError, UnicodeDecodeError) as err:
        raise RecorderError(f"{path} cannot be read as MRCLAM text: {err}") from err
    last_time = -1
    for lineno, line in enumerate(text.splitlines(), start=1):
        tokens = line.split()
        if not tokens or tokens[0].startswith("#"):
            continue
        where = f"{path}:{lineno}"
        if len(tokens) != len(kinds):
            msg = (f"{where}: expected {len(kinds)} columns ({', '.join(columns)}), got {len(tokens)}: "
                   f"{line.strip()!r}; fix or delete the line")
            raise RecorderError(msg)
        for col, (name, parse, token) in enumerate(zip(columns, parsers, tokens, strict=True)):
            try:
                out[col].append(parse(token))
            except ValueError as err:
                msg = f"{where}: column {col + 1} ({name}) is {token!r}, not valid ({err}); fix or delete the line"
                raise RecorderError(msg) from err
        if sorted_by_time:
            if int(out[0][-1]) < last_time:
                raise RecorderError(f"{where}: time goes backwards; the rows of {path.name} must be in time order")
            last_time = int(out[0][-1])
    if not out[0]:
        raise RecorderError(f"{path} holds no data rows: it is empty or truncated; restore it from the dataset")
    return out


def _integrate_odometry(t_ns: NDArray[np.int64], v_mps: NDArray[np.float64], w_radps: NDArray[np.float64]
                        ) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """Distinct stamps (m,) and poses (m, 3) from forward-Euler unicycle integration, from (0, 0, 0)."""
    dt_s = np.diff(t_ns) / 1e9
    yaw = np.concatenate([[0.0], np.cumsum(w_radps[:-1] * dt_s)])
    x = np.concatenate([[0.0], np.cumsum(v_mps[:-1] * dt_s * np.cos(yaw[:-1]))])
    y = np.concatenate([[0.0], np.cumsum(v_mps[:-1] * dt_s * np.sin(yaw[:-1]))])
    stamps, first = np.unique(t_ns, return_index=True)  # a repeated stamp has dt = 0: the same pose
    yaw_wrapped = (yaw + np.pi) % (2.0 * np.pi) - np.pi
    return stamps, np.stack([x, y, yaw_wrapped], -1)[first]


def _scans(t_ns: NDArray[np.int64], subjects: NDArray[np.int64], ranges: NDArray[np.float64],
           bearings: NDArray[np.float64]) -> list[RangeBearingScan]:
    """One scan per distinct stamp (input sorted by time)."""
    stamps, starts = np.unique(t_ns, return_index=True)
    bounds = [*starts.tolist(), len(t_ns)]
    return [RangeBearingScan(int(stamps[i]), ranges[a:b], bearings[a:b], subjects[a:b])
            for i, (a, b) in enumerate(itertools.pairwise(bounds))]


def import_mrclam(data_dir: Path, robot: int, out: Path, progress: Progress | None = None) -> ImportSummary:
    """Import one robot of an MRCLAM dataset folder into the recording ``out``.

    Parameters
    ----------
    data_dir : the dataset folder (e.g. ``../shared/data/mrclam-dataset6``).
    robot : which robot, 1..5.
    out : the recording to create; must not exist.
    progress : called as ``progress(done, total)`` in messages written.

    Returns
    -------
    ImportSummary : counts (messages per topic, measurements kept and dropped) and time span.

    Raises
    ------
    RecorderError : a missing folder or file, a bad robot number, a malformed line (named by
        file and line), or ``out`` already exists.
    """
    if isinstance(robot, bool) or not isinstance(robot, (int, np.integer)) or robot not in ROBOTS:
        raise RecorderError(f"robot must be one of 1..5 (MRCLAM has five robots), got {robot!r}")
    robot = int(robot)
    data_dir = Path(data_dir)
    if not data_dir.is_dir():
        msg = (f"MRCLAM folder {data_dir} does not exist or is not a folder: pass the folder holding "
               f"Barcodes.dat, Landmark_Groundtruth.dat and Robot{robot}_*.dat")
        raise RecorderError(msg)
    rec = Recorder(out, source={"importer": IMPORTER, "dataset": DATASET, "robot": robot},
                   parameters={"odometry_model": "unicycle, forward Euler between consecutive timestamps",
                               "time_resolution_ms": 1},
                   robot={"name": f"Robot{robot}", "sensor": "monocular camera, barcode range-bearing"})

    subject, barcode = _read_dat(data_dir / "Barcodes.dat", ("subject", "barcode"), "ii")
    lm_id, lm_x, lm_y, _, _ = _read_dat(data_dir / "Landmark_Groundtruth.dat",
                                        ("subject", "x [m]", "y [m]", "x std-dev [m]", "y std-dev [m]"), "iffff")
    prefix = data_dir / f"Robot{robot}"
    od_t, od_v, od_w = _read_dat(Path(f"{prefix}_Odometry.dat"), ("time [s]", "forward velocity [m/s]",
                                 "angular velocity [rad/s]"), "tff", sorted_by_time=True)
    gt_t, gt_x, gt_y, gt_yaw = _read_dat(Path(f"{prefix}_Groundtruth.dat"), ("time [s]", "x [m]", "y [m]",
                                         "orientation [rad]"), "tfff", sorted_by_time=True)
    me_t, me_code, me_r, me_b = _read_dat(Path(f"{prefix}_Measurement.dat"), ("time [s]", "barcode",
                                          "range [m]", "bearing [rad]"), "tinf", sorted_by_time=True)

    landmark_subjects = sorted(set(map(int, lm_id)))
    to_subject = {int(b): int(s) for s, b in zip(subject, barcode, strict=True)}
    subjects = np.array([to_subject.get(int(b), -1) for b in me_code], dtype=np.int64)
    keep = np.isin(subjects, landmark_subjects)
    robot_sightings = int(np.isin(subjects, list(ROBOTS)).sum())
    unknown = len(subjects) - int(keep.sum()) - robot_sightings
    ranges = np.asarray(me_r, dtype=np.float64)

    landmark_ids, positions = np.asarray(lm_id, dtype=np.int64), np.column_stack([lm_x, lm_y])
    if len(set(lm_id)) != len(lm_id):
        raise RecorderError(f"{data_dir / 'Landmark_Groundtruth.dat'} lists a subject twice; each landmark once")
    odom_t, odom = _integrate_odometry(np.asarray(od_t, dtype=np.int64), np.asarray(od_v), np.asarray(od_w))
    gt_stamps = np.asarray(gt_t, dtype=np.int64)
    scans = _scans(np.asarray(me_t, dtype=np.int64)[keep], subjects[keep], ranges[keep],
                   np.asarray(me_b, dtype=np.float64)[keep])
    scan_t = np.array([s.stamp_ns for s in scans], dtype=np.int64)
    start_ns = int(min(odom_t[0], gt_stamps[0], scan_t[0] if len(scans) else odom_t[0]))
    end_ns = int(max(odom_t[-1], gt_stamps[-1], scan_t[-1] if len(scans) else odom_t[-1]))

    # One time order for all topics (ties: map, ground truth, odometry, scan) so chunks do not overlap.
    times = np.concatenate([[start_ns], gt_stamps, odom_t, scan_t])
    kinds = np.concatenate([[0], np.full(len(gt_stamps), 1), np.full(len(odom_t), 2), np.full(len(scan_t), 3)])
    index = np.concatenate([[0], np.arange(len(gt_stamps)), np.arange(len(odom_t)), np.arange(len(scan_t))])
    order = np.lexsort((index, kinds, times))

    def messages() -> Iterator[tuple[str, Message]]:
        gt_rows, odom_rows = np.column_stack([gt_x, gt_y, gt_yaw]).tolist(), odom.tolist()
        for kind, i, stamp in zip(kinds[order].tolist(), index[order].tolist(), times[order].tolist(), strict=True):
            if kind == 0:
                yield TOPIC_GROUND_TRUTH_LANDMARKS, LandmarkMap(stamp, landmark_ids, positions)
            elif kind == 1:
                yield TOPIC_GROUND_TRUTH_POSE, GroundTruthPose(stamp, *gt_rows[i])
            elif kind == 2:
                yield TOPIC_ODOM, OdometryPose(stamp, *odom_rows[i])
            else:
                yield TOPIC_RANGE_BEARING, scans[i]

    total = len(order)
    every = max(1, total // 200)
    with rec:
        for done, (topic, message) in enumerate(messages(), start=1):
            rec.write(topic, message)
            if progress is not None and (done % every == 0 or done == total):
                progress(done, total)
        written = rec.message_count
    return ImportSummary(path=Path(out), robot=robot, messages=written, odometry_poses=len(odom_t),
                         ground_truth_poses=len(gt_stamps), scans=len(scans), measurements_kept=int(keep.sum()),
                         robot_sightings_dropped=robot_sightings, unknown_barcodes_dropped=unknown,
                         landmarks=len(landmark_ids), start_ns=start_ns, end_ns=end_ns)
