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
from typing import Any, Final

import numpy as np
from numpy.typing import NDArray

from slamreplay.recorder.errors import RecorderError
from slamreplay.recorder.messages import (
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
from slamreplay.recorder.sensor_model import SensorModel
from slamreplay.recorder.writer import Recorder, refuse_existing

IMPORTER: Final = "mrclam"
DATASET: Final = "MRCLAM Dataset6"
ROBOTS: Final = range(1, 6)  # subjects 1..5 are the robots; the landmarks are subjects 6..20
NS_PER_MS: Final = 1_000_000

Progress = Callable[[int, int], None]


@dataclass(frozen=True, slots=True)
class ImportSummary:
    """What :func:`import_mrclam` wrote."""

    path: Path
    robot: int | str  # 1..5, or "all"
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


# Bounds on the values of a line, checked where it is read so that the arrays built from the file hold int64
# and the integration, interpolation and noise fit stay finite. A time beyond MAX_TIME_S (the year 2255) does
# not fit int64 nanoseconds; MRCLAM's arena is 15 x 8 m, its robots drive under 1 m/s and its ranges stay under
# 10 m, so MAX_MAGNITUDE (m, m/s, rad, rad/s) is far above any real value and far below float overflow.
MAX_TIME_S: Final = 9.0e9
MAX_MAGNITUDE: Final = 1.0e6
_INT64: Final = 1 << 63


def _time_ns(token: str) -> int:
    """Unix seconds (ms resolution) -> int ns, exactly: round to the millisecond first."""
    seconds = float(token)
    if not 0 <= seconds <= MAX_TIME_S:  # also NaN
        raise ValueError(f"time {token!r} is not a number of seconds in 0..{MAX_TIME_S:.0e} (Unix time)")
    return round(seconds * 1000.0) * NS_PER_MS


def _int(token: str) -> int:
    value = int(token)
    if not -_INT64 <= value < _INT64:
        raise ValueError(f"{token!r} does not fit a 64-bit integer")
    return value


def _subject(token: str) -> int:
    value = _int(token)
    if value < 0:  # a recording's landmark ids are >= 0 (-1 marks an unknown one)
        raise ValueError(f"{token!r} is negative: subjects are numbered from 1")
    return value


def _float(token: str) -> float:
    value = float(token)
    if not abs(value) <= MAX_MAGNITUDE:  # also NaN and infinities
        raise ValueError(f"{token!r} is not a finite number within +-{MAX_MAGNITUDE:.0e}")
    return value


def _nonnegative(token: str) -> float:
    value = _float(token)
    if value < 0:
        raise ValueError(f"{token!r} is negative")
    return value


_PARSERS: Final[dict[str, Callable[[str], float | int]]] = {"t": _time_ns, "i": _int, "s": _subject, "f": _float,
                                                             "n": _nonnegative}


def _read_dat(path: Path, columns: tuple[str, ...], kinds: str, *,
              sorted_by_time: bool = False) -> list[list[float | int]]:
    """Columns of a whitespace-separated ``.dat`` file; ``kinds`` gives each column's type.

    ``t`` is a time (to int ns), ``i`` a 64-bit integer, ``s`` a nonnegative one (a subject), ``f`` a float within
    MAX_MAGNITUDE, ``n`` a nonnegative one. Raises RecorderError naming the file and line of anything malformed,
    or of a time that goes backwards.
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


# How the sensor model is measured at import time (`measure_sensor_model`).
ODOMETRY_SEGMENT_M: Final = 1.0  # odometry compared with ground truth over segments of this path length...
ODOMETRY_SEGMENT_RAD: Final = 0.5  # ... or of this much turning, whichever comes first
OUTLIER_SIGMAS: Final = 5.0  # a residual farther than this many robust sigmas from the median is an outlier


def _truth_at(t_ns: NDArray[np.int64], gt_t: NDArray[np.int64], gt: NDArray[np.float64]) -> NDArray[np.float64]:
    """Ground-truth poses (n, 3) linearly interpolated at ``t_ns`` (yaw unwrapped first); NaN outside its span."""
    yaw = np.unwrap(gt[:, 2])
    out = np.stack([np.interp(t_ns, gt_t, gt[:, 0]), np.interp(t_ns, gt_t, gt[:, 1]), np.interp(t_ns, gt_t, yaw)], -1)
    out[(t_ns < gt_t[0]) | (t_ns > gt_t[-1])] = np.nan
    return out


def _between(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """⊖a ⊕ b row by row (n, 3), yaw wrapped."""
    c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
    dx, dy = b[:, 0] - a[:, 0], b[:, 1] - a[:, 1]
    return np.stack([c * dx + s * dy, -s * dx + c * dy, np.remainder(b[:, 2] - a[:, 2] + np.pi, 2 * np.pi) - np.pi], -1)


def _robust_sigma(residuals: NDArray[np.float64]) -> tuple[float, NDArray[np.bool_]]:
    """(RMS of the inliers about zero, inlier mask); inliers lie within OUTLIER_SIGMAS MAD-sigmas of the median.

    The RMS about zero, not the spread about the median: a filter knows no bias, so the sigma it is
    given must cover the dataset's systematic error (MRCLAM's ranges read a few cm long) as well.
    """
    med = float(np.median(residuals))
    mad_sigma = 1.4826 * float(np.median(np.abs(residuals - med)))
    inlier = np.abs(residuals - med) <= OUTLIER_SIGMAS * max(mad_sigma, 1e-9)
    return float(np.sqrt(np.mean(residuals[inlier] ** 2))), inlier


def measure_sensor_model(odom_t: NDArray[np.int64], odom: NDArray[np.float64], gt_t: NDArray[np.int64],
                         gt: NDArray[np.float64], meas_t: NDArray[np.int64], meas_subject: NDArray[np.int64],
                         ranges: NDArray[np.float64], bearings: NDArray[np.float64], landmark_ids: NDArray[np.int64],
                         landmarks: NDArray[np.float64]) -> SensorModel:
    """The robot's odometry and range-bearing noise, measured against the dataset's ground truth.

    - Odometry: the path is cut into segments of ``ODOMETRY_SEGMENT_M`` travelled or ``ODOMETRY_SEGMENT_RAD``
      turned (by the ground truth); each segment's odometry increment is compared with the truth's. The
      model's variances (``algorithms/common/motion.py``: ``s_t^2 d`` along the track, ``s_h^2 d + s_r^2
      |dtheta|`` in heading) are fitted to the squared along-track and heading errors (the latter by
      non-negative least squares), after dropping the segments whose
      error is an outlier (Vicon dropouts). Scale errors of the odometry land in the fitted noise, as they
      must for a filter that models no bias.
    - Range and bearing: residuals of every landmark measurement against the range and bearing predicted
      from the interpolated true pose and the true landmark; sigma is the RMS of the inliers about zero
      (``_robust_sigma``), ``outlier_rate`` the fraction of range or bearing residuals beyond
      ``OUTLIER_SIGMAS`` robust sigmas.
    """
    odometry = _measure_odometry(odom_t, odom, gt_t, gt)
    ranging = _measure_range_bearing(gt_t, gt, meas_t, meas_subject, ranges, bearings, landmark_ids, landmarks)
    said = [f"{odometry.pop('segments')} odometry segments" if odometry else "too little motion to measure odometry",
            f"{ranging.pop('measurements')} landmark measurements" if ranging else "too few landmark measurements"]
    return SensorModel(**odometry, **ranging, source=f"measured at import against the Vicon ground truth "
                       f"({', '.join(said)}; recorder/importers/mrclam.py: measure_sensor_model)")


MIN_SAMPLES: Final = 20  # fewer odometry segments or landmark measurements than this: that part is not measured


def _measure_odometry(odom_t: NDArray[np.int64], odom: NDArray[np.float64], gt_t: NDArray[np.int64],
                      gt: NDArray[np.float64]) -> dict[str, Any]:
    from scipy.optimize import nnls

    truth_odom = _truth_at(odom_t, gt_t, gt)
    ok = ~np.isnan(truth_odom[:, 0])
    o, g = odom[ok], truth_odom[ok]
    if len(g) < 2:
        return {}
    steps = np.hypot(*np.diff(g[:, :2], axis=0).T)
    turns = np.abs(np.diff(g[:, 2]))
    cuts, dist, turn = [0], 0.0, 0.0
    for k, (d, a) in enumerate(zip(steps.tolist(), turns.tolist(), strict=True), start=1):
        dist, turn = dist + d, turn + a
        if dist >= ODOMETRY_SEGMENT_M or turn >= ODOMETRY_SEGMENT_RAD:
            cuts.append(k)
            dist, turn = 0.0, 0.0
    idx = np.asarray(cuts)
    if len(idx) <= MIN_SAMPLES:
        return {}
    err = _between(_between(g[idx[:-1]], g[idx[1:]]), _between(o[idx[:-1]], o[idx[1:]]))
    seg_d = np.add.reduceat(steps, idx[:-1])[: len(err)]
    seg_a = np.abs(_between(g[idx[:-1]], g[idx[1:]])[:, 2])
    e_h2 = err[:, 2] ** 2
    _, keep_t = _robust_sigma(np.abs(err[:, 0]) / np.sqrt(np.maximum(seg_d, 1e-3)))
    _, keep_h = _robust_sigma(np.sqrt(e_h2 / np.maximum(seg_d + seg_a, 1e-3)))
    keep = keep_t & keep_h
    # along-track only: E[ex^2] = s_t^2 d. The lateral error of a segment comes mostly from its heading error,
    # which the filter propagates itself when it composes the segment's many small increments.
    s_t2 = float(np.sum(err[keep, 0] ** 2) / np.sum(seg_d[keep]))
    (s_h2, s_r2), _ = nnls(np.column_stack([seg_d[keep], seg_a[keep]]), e_h2[keep])
    return {"translation_sigma_per_sqrt_m": math.sqrt(s_t2), "heading_sigma_per_sqrt_m": math.sqrt(s_h2),
            "heading_sigma_per_sqrt_rad": math.sqrt(s_r2), "segments": int(keep.sum())}


def _measure_range_bearing(gt_t: NDArray[np.int64], gt: NDArray[np.float64], meas_t: NDArray[np.int64],
                           meas_subject: NDArray[np.int64], ranges: NDArray[np.float64],
                           bearings: NDArray[np.float64], landmark_ids: NDArray[np.int64],
                           landmarks: NDArray[np.float64]) -> dict[str, Any]:
    lookup = {int(i): k for k, i in enumerate(landmark_ids.tolist())}
    pose = _truth_at(meas_t, gt_t, gt)
    have = ~np.isnan(pose[:, 0])
    if have.sum() < MIN_SAMPLES:
        return {}
    lm = landmarks[[lookup[int(i)] for i in meas_subject[have]]]
    p = pose[have]
    r_pred = np.hypot(lm[:, 0] - p[:, 0], lm[:, 1] - p[:, 1])
    b_pred = np.arctan2(lm[:, 1] - p[:, 1], lm[:, 0] - p[:, 0]) - p[:, 2]
    r_res = ranges[have] - r_pred
    b_res = np.remainder(bearings[have] - b_pred + np.pi, 2 * np.pi) - np.pi
    sigma_r, in_r = _robust_sigma(r_res)
    sigma_b, in_b = _robust_sigma(b_res)
    return {"range_sigma_m": sigma_r, "bearing_sigma_rad": sigma_b, "outlier_rate": float(np.mean(~(in_r & in_b))),
            "min_range_m": float(ranges.min()), "max_range_m": float(ranges.max()), "measurements": int(have.sum())}


@dataclass(frozen=True, slots=True)
class _Robot:
    """One robot's streams, ready to write."""

    gt_t: NDArray[np.int64]
    gt: NDArray[np.float64]
    odom_t: NDArray[np.int64]
    odom: NDArray[np.float64]
    scans: list[RangeBearingScan]
    kept: int
    robot_sightings: int
    unknown: int
    model: SensorModel


def _load_robot(data_dir: Path, robot: int, to_subject: dict[int, int], landmark_ids: NDArray[np.int64],
                positions: NDArray[np.float64]) -> _Robot:
    prefix = data_dir / f"Robot{robot}"
    od_t, od_v, od_w = _read_dat(Path(f"{prefix}_Odometry.dat"), ("time [s]", "forward velocity [m/s]",
                                 "angular velocity [rad/s]"), "tff", sorted_by_time=True)
    gt_t, gt_x, gt_y, gt_yaw = _read_dat(Path(f"{prefix}_Groundtruth.dat"), ("time [s]", "x [m]", "y [m]",
                                         "orientation [rad]"), "tfff", sorted_by_time=True)
    me_t, me_code, me_r, me_b = _read_dat(Path(f"{prefix}_Measurement.dat"), ("time [s]", "barcode",
                                          "range [m]", "bearing [rad]"), "tinf", sorted_by_time=True)
    subjects = np.array([to_subject.get(int(b), -1) for b in me_code], dtype=np.int64)
    keep = np.isin(subjects, landmark_ids)
    robot_sightings = int(np.isin(subjects, list(ROBOTS)).sum())
    ranges = np.asarray(me_r, dtype=np.float64)
    odom_t, odom = _integrate_odometry(np.asarray(od_t, dtype=np.int64), np.asarray(od_v), np.asarray(od_w))
    gt_stamps, gt = np.asarray(gt_t, dtype=np.int64), np.column_stack([gt_x, gt_y, gt_yaw])
    meas_t, bearings = np.asarray(me_t, dtype=np.int64)[keep], np.asarray(me_b, dtype=np.float64)[keep]
    scans = _scans(meas_t, subjects[keep], ranges[keep], bearings)
    model = measure_sensor_model(odom_t, odom, gt_stamps, gt, meas_t, subjects[keep], ranges[keep], bearings,
                                 landmark_ids, positions)
    return _Robot(gt_stamps, gt, odom_t, odom, scans, int(keep.sum()), robot_sightings,
                  len(subjects) - int(keep.sum()) - robot_sightings, model)


def robot_namespace(robot: int) -> str:
    """Where robot ``robot``'s topics go in an all-robots recording: ``/robotN`` (``/robot1/odom`` ...)."""
    return f"/robot{robot}"


def import_mrclam(data_dir: Path, robot: int | str, out: Path, progress: Progress | None = None) -> ImportSummary:
    """Import one robot, or all five, of an MRCLAM dataset folder into the recording ``out``.

    Parameters
    ----------
    data_dir : the dataset folder (e.g. ``../shared/data/mrclam-dataset6``).
    robot : which robot, 1..5, or ``"all"``: every robot's topics under its namespace
        (``/robot1/odom``, ``/robot1/ground_truth/pose``, ``/robot1/landmarks/range_bearing`` ...,
        `robot_namespace`), the landmark map once at ``/ground_truth/landmarks``, and each robot's
        sensor model under its namespace. `slamreplay run --robot N` replays one robot of it.
    out : the recording to create; must not exist.
    progress : called as ``progress(done, total)`` in messages written.

    Returns
    -------
    ImportSummary : counts (messages per topic, measurements kept and dropped, summed over robots) and span.

    Raises
    ------
    RecorderError : a missing folder or file, a bad robot number, a malformed line (named by
        file and line), or ``out`` already exists.
    """
    if robot == "all":
        robots = list(ROBOTS)
    elif isinstance(robot, bool) or not isinstance(robot, (int, np.integer)) or robot not in ROBOTS:
        raise RecorderError(f"robot must be one of 1..5 or 'all' (MRCLAM has five robots), got {robot!r}")
    else:
        robots = [int(robot)]
    data_dir = Path(data_dir)
    if not data_dir.is_dir():
        msg = (f"MRCLAM folder {data_dir} does not exist or is not a folder: pass the folder holding "
               f"Barcodes.dat, Landmark_Groundtruth.dat and Robot{robots[0]}_*.dat")
        raise RecorderError(msg)
    refuse_existing(Path(out))  # before minutes of reading

    subject, barcode = _read_dat(data_dir / "Barcodes.dat", ("subject", "barcode"), "si")
    lm_id, lm_x, lm_y, _, _ = _read_dat(data_dir / "Landmark_Groundtruth.dat",
                                        ("subject", "x [m]", "y [m]", "x std-dev [m]", "y std-dev [m]"), "sffff")
    if len(set(lm_id)) != len(lm_id):
        raise RecorderError(f"{data_dir / 'Landmark_Groundtruth.dat'} lists a subject twice; each landmark once")
    to_subject = {int(b): int(s) for s, b in zip(subject, barcode, strict=True)}
    landmark_ids, positions = np.asarray(lm_id, dtype=np.int64), np.column_stack([lm_x, lm_y])
    data = [_load_robot(data_dir, k, to_subject, landmark_ids, positions) for k in robots]
    single = len(robots) == 1
    namespaces = [""] if single else [robot_namespace(k) for k in robots]

    # One time order for all topics (ties: map, ground truth, odometry, scan, then robot) so chunks do not overlap.
    parts_t, parts_kind, parts_robot, parts_index = [], [], [], []
    for r, d in enumerate(data):
        scan_t = np.array([s.stamp_ns for s in d.scans], dtype=np.int64)
        for kind, stamps in ((1, d.gt_t), (2, d.odom_t), (3, scan_t)):
            parts_t.append(stamps)
            parts_kind.append(np.full(len(stamps), kind))
            parts_robot.append(np.full(len(stamps), r))
            parts_index.append(np.arange(len(stamps)))
    all_t = np.concatenate(parts_t)
    start_ns, end_ns = int(all_t.min()), int(all_t.max())
    times = np.concatenate([[start_ns], all_t])
    kinds = np.concatenate([[0], *parts_kind])
    owner = np.concatenate([[0], *parts_robot])
    index = np.concatenate([[0], *parts_index])
    order = np.lexsort((index, owner, kinds, times))

    def messages() -> Iterator[tuple[str, Message]]:
        rows = [(d.gt.tolist(), d.odom.tolist()) for d in data]
        for kind, r, i, stamp in zip(kinds[order].tolist(), owner[order].tolist(), index[order].tolist(),
                                     times[order].tolist(), strict=True):
            ns = namespaces[r]
            if kind == 0:
                yield TOPIC_GROUND_TRUTH_LANDMARKS, LandmarkMap(stamp, landmark_ids, positions)
            elif kind == 1:
                yield ns + TOPIC_GROUND_TRUTH_POSE, GroundTruthPose(stamp, *rows[r][0][i])
            elif kind == 2:
                yield ns + TOPIC_ODOM, OdometryPose(stamp, *rows[r][1][i])
            else:
                yield ns + TOPIC_RANGE_BEARING, data[r].scans[i]

    names = [f"Robot{k}" for k in robots]
    rec = Recorder(out, source={"importer": IMPORTER, "dataset": DATASET, "robot": robots[0] if single else "all"},
                   parameters={"odometry_model": "unicycle, forward Euler between consecutive timestamps",
                               "time_resolution_ms": 1, **({} if single else {"robots": dict(zip(namespaces, names,
                                                                                                   strict=True))})},
                   robot={"name": names[0], "sensor": "monocular camera, barcode range-bearing"} if single else
                   {"names": names, "sensor": "monocular camera, barcode range-bearing (each robot)"},
                   sensor_model=data[0].model if single else {ns: d.model for ns, d in zip(namespaces, data,
                                                                                            strict=True)})
    total = len(order)
    every = max(1, total // 200)
    with rec:
        for done, (topic, message) in enumerate(messages(), start=1):
            rec.write(topic, message)
            if progress is not None and (done % every == 0 or done == total):
                progress(done, total)
        written = rec.message_count
    return ImportSummary(path=Path(out), robot=robots[0] if single else "all", messages=written,
                         odometry_poses=sum(len(d.odom_t) for d in data),
                         ground_truth_poses=sum(len(d.gt_t) for d in data), scans=sum(len(d.scans) for d in data),
                         measurements_kept=sum(d.kept for d in data),
                         robot_sightings_dropped=sum(d.robot_sightings for d in data),
                         unknown_barcodes_dropped=sum(d.unknown for d in data),
                         landmarks=len(landmark_ids), start_ns=start_ns, end_ns=end_ns)
