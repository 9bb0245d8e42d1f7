"""Importer for Victoria Park in its iSAM/GTSAM graph form [1]_ [2]_ (``victoria_park.txt``).

The file holds ``ODOMETRY i j dx dy dθ c_xx c_xy c_xθ c_yy c_yθ c_θθ`` (pose j in pose i's frame
and its covariance) and ``LANDMARK i l x y c_xx c_xy c_yy`` (landmark l as a Cartesian point in
pose i's frame, x forward, y left), with data association solved, in time order. Pose and
landmark ids share one integer space. The recording holds:

- ``/odom``: the odometry increments composed from (0, 0, 0), one pose per pose id;
- ``/landmarks/range_bearing``: one scan per pose that observes landmarks, the point turned into
  range ``hypot(x, y)`` and bearing ``atan2(y, x)``, ids = the file's landmark ids; sigmas from
  :func:`sensor_model` (measured; the file's own, looser, are :func:`gtsam_noise`);
- with a ``reference`` (the batch least-squares optimum of these same measurements, as
  ``slamreplay record victoria-park`` computes it: ``replay.evaluation.landmark_reference.recording_reference``;
  the file has no ground truth): ``/ground_truth/pose`` and ``/ground_truth/landmarks``, so that runs are
  scored against it, and ``ground_truth_is_estimate`` in the recording's source.

With ``merge_window_m`` > 0 (default 0: one scan per observing pose, as in the file), the
sightings of consecutive poses are gathered until the robot has driven that far by odometry and
written as one scan at the last pose, each moved into that pose's frame through the composed
odometry (a landmark seen twice: its latest sighting). Nine in ten of the file's scans see one
tree; D-SLAM maps features through recast measurements that relate features seen in one scan, so
it needs this on this file. The odometry between sightings in a window is treated as exact: a
departure that adds about 0.01 rad of heading error per 5 m window, against the stated bearing
sigma of 0.2 rad.

The file has no timestamps: pose number k (in file order) is stamped ``k * STEP_NS`` (a nominal
5 Hz; nothing in the pipelines depends on the rate).

References
----------
.. [1] J. Guivant, E. Nebot, "Optimization of the simultaneous localization and map-building
   algorithm for real-time implementation", IEEE Trans. Robotics and Automation 17(3), 2001.
.. [2] M. Kaess, A. Ranganathan, F. Dellaert, "iSAM: Incremental smoothing and mapping",
   IEEE T-RO 24(6), 2008 (the graph form); distributed with GTSAM as examples/Data/victoria_park.txt.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Final

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
from slamreplay.recorder.writer import GROUND_TRUTH_IS_ESTIMATE, Recorder

IMPORTER: Final = "victoria-park"
DATASET: Final = "Victoria Park (iSAM/GTSAM graph form)"
FILE_NAME: Final = "victoria_park.txt"
STEP_NS: Final = 200_000_000
Progress = Callable[[int, int], None]
F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


@dataclass(frozen=True, slots=True)
class VictoriaPark:
    """The file's content with poses numbered 0..n-1 in file order and landmarks by their own id."""

    pose_ids: I64  # (n,) the file's id of each pose
    odo_i: I64  # (m,) pose numbers
    odo_j: I64
    odo_z: F64  # (m, 3)
    odo_cov: F64  # (m, 3, 3)
    obs_pose: I64  # (k,) pose numbers
    obs_landmark: I64  # (k,) the file's landmark ids
    obs_xy: F64  # (k, 2) in the robot frame
    obs_cov: F64  # (k, 2, 2)

    @property
    def landmark_ids(self) -> I64:
        return np.unique(self.obs_landmark)

    def odometry_poses(self) -> F64:
        """Dead reckoning: the increments composed from (0, 0, 0), (n, 3)."""
        poses = np.zeros((len(self.pose_ids), 3))
        for i, j, z in zip(self.odo_i.tolist(), self.odo_j.tolist(), self.odo_z.tolist(), strict=True):
            x = poses[i]
            c, s = math.cos(x[2]), math.sin(x[2])
            poses[j] = [x[0] + c * z[0] - s * z[1], x[1] + s * z[0] + c * z[1], math.remainder(x[2] + z[2], math.tau)]
        return poses

    def ranges_bearings(self) -> F64:
        """(k, 2) range and bearing of each observation."""
        return np.column_stack([np.hypot(self.obs_xy[:, 0], self.obs_xy[:, 1]),
                                np.arctan2(self.obs_xy[:, 1], self.obs_xy[:, 0])])


def gtsam_noise() -> dict[str, float]:
    """The file's own noise as GTSAM's loader reads it (the reference's weights; the data folder's README).

    Odometry: the six numbers are a covariance, sigma 0.01 m forward, 0.002 m lateral, 0.002 rad
    per step. Landmarks: an x/y variance of 0.4 m², which GTSAM turns into sigma_range =
    sqrt(0.4) = 0.63 m and sigma_bearing = sqrt(0.4 / 10) = 0.2 rad.
    """
    return {"range_sigma_m": math.sqrt(0.4), "bearing_sigma_rad": math.sqrt(0.4 / 10.0)}


def sensor_model() -> dict[str, float]:
    """The data set's noise as pipeline config keys: landmarks measured about the batch optimum, odometry stated.

    Landmarks: 0.25 m in range and 0.049 rad in bearing, the sigmas the sightings show about GTSAM's
    optimum (the optimum under :func:`gtsam_noise`), corrected for what the optimum absorbs, as
    :func:`slamreplay.replay.evaluation.landmark_reference.measured_noise` computes at import (``slamreplay record
    victoria-park`` stores its values in the recording's parameters); the file's own convention says
    0.63 m and 0.2 rad. Odometry: the optimum absorbs its residuals almost whole, so its noise cannot
    be measured this way and the file's stands: 0.01 m and 0.002 rad per step, steps of 0.58 m on
    average (4.03 km over 6968), so 0.013 m and 0.0026 rad per square root of a metre.
    """
    return {"translation_sigma_per_sqrt_m": 0.013, "heading_sigma_per_sqrt_m": 0.0026,
            "heading_sigma_per_sqrt_rad": 0.0, "range_sigma_m": 0.25, "bearing_sigma_rad": 0.049}


# Bounds on what a line may hold, checked where it is read, so that the composed poses, the ranges and the
# reference's least-squares system stay finite and well conditioned. The real file: steps under 1.5 m and 0.13 rad,
# sightings 4.6 to 20.7 m away, variances 4e-6 to 0.4.
MAX_STEP_M: Final = 100.0  # |dx|, |dy| of one odometry increment
MAX_TURN_RAD: Final = math.pi  # |dtheta| of one increment
MAX_RANGE_M: Final = 1000.0  # |x|, |y| of a sighting (a SICK laser sees 80 m)
MIN_RANGE_M: Final = 0.01  # a sighting closer than this has no bearing
MIN_VARIANCE: Final = 1e-10  # eigenvalues of a covariance, and its entries: sigma 10 um .. 100 m (or rad)
MAX_VARIANCE: Final = 1e4
_INT64: Final = 1 << 63


def _float(tok: str, where: str, bound: float = math.inf) -> float:
    try:
        v = float(tok)
    except ValueError as err:
        raise RecorderError(f"{where}: {tok!r} is not a number; fix or delete the line") from err
    if not math.isfinite(v):
        raise RecorderError(f"{where}: {tok!r} is not finite; fix or delete the line")
    if abs(v) > bound:
        raise RecorderError(f"{where}: {tok!r} is beyond the +-{bound:g} this value takes; fix or delete the line")
    return v


def _int(tok: str, where: str) -> int:
    """A pose or landmark id: the file's ids are numbers 0, 1, 2... (a recording's landmark ids are >= 0)."""
    try:
        v = int(tok)
    except ValueError as err:
        raise RecorderError(f"{where}: {tok[:30]!r} is not an integer id; fix or delete the line") from err
    if not 0 <= v < _INT64:
        raise RecorderError(f"{where}: id {tok[:30]} is not an integer in 0..2**63-1; fix or delete the line")
    return v


def _covariance(tokens: list[str], where: str) -> list[float]:
    """The numbers of ``tokens`` when the upper triangle they form (row-major) is a covariance within the bounds."""
    values = [_float(t, where, MAX_VARIANCE) for t in tokens]
    n = 3 if len(values) == 6 else 2
    cov = np.zeros((n, n))
    cov[np.triu_indices(n)] = values
    eig = np.linalg.eigvalsh(cov, UPLO="U")
    if eig.min() <= 0:
        raise RecorderError(f"{where}: the covariance is not positive definite: the file is damaged; fix or delete "
                            f"the line")
    if not (eig.min() >= MIN_VARIANCE and eig.max() <= MAX_VARIANCE):
        raise RecorderError(f"{where}: the covariance has eigenvalues {eig.min():.3g} .. {eig.max():.3g}, outside "
                            f"{MIN_VARIANCE:g} .. {MAX_VARIANCE:g} (sigma 10 um .. 100 m): the file is damaged; fix "
                            f"or delete the line")
    return values


def read_victoria_park(path: str | Path) -> VictoriaPark:
    """Parse ``victoria_park.txt`` (or the folder holding it). RecorderError names a bad file or line."""
    path = Path(path)
    if path.is_dir():
        path = path / FILE_NAME
    if not path.is_file():
        raise RecorderError(f"{path} is missing: pass the folder holding {FILE_NAME} (e.g. "
                            f"../shared/data/victoria-park-isam) or the file itself")
    try:
        lines = path.read_text(encoding="ascii").splitlines()
    except (OSError, UnicodeDecodeError) as err:
        raise RecorderError(f"{path} cannot be read as Victoria Park text: {err}") from err
    number: dict[int, int] = {0: 0}
    odo: list[tuple[int, int, list[float]]] = []
    obs: list[tuple[int, int, list[float]]] = []
    for lineno, line in enumerate(lines, start=1):
        tok = line.split()
        if not tok or tok[0].startswith("#"):
            continue
        where = f"{path}:{lineno}"
        if tok[0] == "ODOMETRY" and len(tok) == 12:
            i, j = _int(tok[1], where), _int(tok[2], where)
            if i not in number:
                raise RecorderError(f"{where}: odometry from pose {i}, which no earlier line reaches")
            if j in number:
                raise RecorderError(f"{where}: pose {j} is reached twice; each pose once, in time order")
            step = [_float(tok[3], where, MAX_STEP_M), _float(tok[4], where, MAX_STEP_M),
                    _float(tok[5], where, MAX_TURN_RAD)]
            number[j] = len(number)
            odo.append((number[i], number[j], step + _covariance(tok[6:], where)))
        elif tok[0] == "LANDMARK" and len(tok) == 8:
            i = _int(tok[1], where)
            if i not in number:
                raise RecorderError(f"{where}: observation from pose {i}, which no earlier line reaches")
            x, y = _float(tok[3], where, MAX_RANGE_M), _float(tok[4], where, MAX_RANGE_M)
            if math.hypot(x, y) < MIN_RANGE_M:
                raise RecorderError(f"{where}: a landmark seen {math.hypot(x, y):.3g} m away, closer than "
                                    f"{MIN_RANGE_M} m, has no bearing; fix or delete the line")
            obs.append((number[i], _int(tok[2], where), [x, y] + _covariance(tok[5:], where)))
        else:
            raise RecorderError(f"{where}: expected `ODOMETRY i j dx dy dtheta` + 6 covariance numbers or `LANDMARK "
                                f"i l x y` + 3, got {line.strip()[:60]!r}; fix or delete the line")
    if not odo:
        raise RecorderError(f"{path} holds no ODOMETRY line: it is empty or not Victoria Park")
    o = np.array([v for _, _, v in odo])
    if not np.any(o[:, :2]):  # the noise model is per metre driven (sensor_model): it has no value then
        raise RecorderError(f"{path}: no ODOMETRY line moves the robot (every dx and dy is 0): nothing was driven, "
                            f"so there is no odometry noise per metre to state; it is not a Victoria Park file")
    c = o[:, 3:]
    odo_cov = np.array([[[a, b, d], [b, e, f], [d, f, g]] for a, b, d, e, f, g in c])
    lv = np.array([v for _, _, v in obs]).reshape(-1, 5)
    obs_cov = np.array([[[a, b], [b, d]] for a, b, d in lv[:, 2:]]).reshape(-1, 2, 2)
    ids = sorted(number, key=number.__getitem__)
    return VictoriaPark(np.array(ids, dtype=np.int64), np.array([i for i, _, _ in odo], dtype=np.int64),
                        np.array([j for _, j, _ in odo], dtype=np.int64), o[:, :3], odo_cov,
                        np.array([i for i, _, _ in obs], dtype=np.int64),
                        np.array([lm for _, lm, _ in obs], dtype=np.int64), lv[:, :2].copy(), obs_cov)


@dataclass(frozen=True, slots=True)
class ImportSummary:
    """What :func:`write_victoria_park` wrote."""

    path: Path
    poses: int
    scans: int
    observations: int
    landmarks: int
    path_length_m: float
    reference: bool


def _scan_groups(data: VictoriaPark, odom: F64, window_m: float) -> dict[int, tuple[F64, F64, I64]]:
    """Pose number -> (ranges, bearings, ids) of the scan written there (module docstring, merge_window_m)."""
    rb = data.ranges_bearings()
    order = np.argsort(data.obs_pose, kind="stable")
    poses = data.obs_pose[order]
    out: dict[int, tuple[F64, F64, I64]] = {}
    if window_m <= 0:
        for k in np.unique(poses).tolist():
            sel = order[poses == k]
            out[k] = (rb[sel, 0], rb[sel, 1], data.obs_landmark[sel])
        return out
    travelled = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(odom[:, :2], axis=0).T))])
    buffer: list[int] = []  # observation indices
    for o in order.tolist():
        buffer.append(o)
        start = int(data.obs_pose[buffer[0]])
        k = int(data.obs_pose[o])
        if travelled[k] - travelled[start] < window_m and o != order[-1]:
            continue
        latest: dict[int, int] = {}
        for b in buffer:  # a landmark seen twice in the window: its latest sighting
            latest[int(data.obs_landmark[b])] = b
        sel = np.array(sorted(latest.values()))
        src = odom[data.obs_pose[sel]]
        # each sighting into pose k's frame through the composed odometry: world point, then pose k's frame
        wx = src[:, 0] + rb[sel, 0] * np.cos(src[:, 2] + rb[sel, 1])
        wy = src[:, 1] + rb[sel, 0] * np.sin(src[:, 2] + rb[sel, 1])
        c, s = math.cos(odom[k, 2]), math.sin(odom[k, 2])
        lx, ly = c * (wx - odom[k, 0]) + s * (wy - odom[k, 1]), -s * (wx - odom[k, 0]) + c * (wy - odom[k, 1])
        out[k] = (np.hypot(lx, ly), np.arctan2(ly, lx), data.obs_landmark[sel])
        buffer = []
    return out


def write_victoria_park(data: VictoriaPark, out: str | Path, *, reference: tuple[F64, F64] | None = None,
                        reference_note: str = "", measured_model: dict[str, float] | None = None,
                        merge_window_m: float = 0.0,
                        progress: Progress | None = None) -> ImportSummary:
    """Write the recording; ``reference``: poses (n, 3) and landmarks (L, 2, in ``data.landmark_ids`` order).

    ``measured_model``: the noise measured about the reference (config keys), kept in the parameters
    beside the documented :func:`sensor_model`. ``merge_window_m`` > 0 gathers the sightings of
    consecutive poses until the robot has driven that far (by odometry) into one scan at the last of
    them (module docstring).
    """
    if not math.isfinite(merge_window_m) or merge_window_m < 0:
        raise RecorderError(f"merge_window_m must be >= 0 metres, got {merge_window_m}")
    n = len(data.pose_ids)
    odom = data.odometry_poses()
    model = sensor_model()
    lm_ids = data.landmark_ids
    if reference is not None and (reference[0].shape != (n, 3) or reference[1].shape != (len(lm_ids), 2)):
        raise RecorderError(f"reference must be ({n}, 3) poses and ({len(lm_ids)}, 2) landmarks")
    source = {"importer": IMPORTER, "dataset": DATASET}
    if reference is not None:
        source["ground_truth"] = reference_note or "batch least-squares optimum of the same measurements"
        source[GROUND_TRUTH_IS_ESTIMATE] = True
    rec = Recorder(out, source=source, parameters={"stamp_step_ns": STEP_NS, "file_noise_gtsam": gtsam_noise(),
                                                  "measured_noise": measured_model or {},
                                                  "merge_window_m": merge_window_m},
                   robot={"name": "ACFR utility vehicle", "sensor": "SICK laser, tree trunks as point landmarks"},
                   sensor_model=SensorModel(**model, source="landmarks: measured about GTSAM's batch optimum; "
                                            "odometry: the file's stated noise (recorder/importers/victoria_park.py)"))
    groups = _scan_groups(data, odom, merge_window_m)
    scans = 0
    every = max(1, n // 200)
    with rec:
        if reference is not None:
            rec.write(TOPIC_GROUND_TRUTH_LANDMARKS, LandmarkMap(0, lm_ids, reference[1]))
        for k in range(n):
            stamp = k * STEP_NS
            msgs: list[tuple[str, Message]] = []
            if reference is not None:
                msgs.append((TOPIC_GROUND_TRUTH_POSE, GroundTruthPose(stamp, *reference[0][k].tolist())))
            msgs.append((TOPIC_ODOM, OdometryPose(stamp, *odom[k].tolist())))
            if k in groups:
                ranges, bearings, ids = groups[k]
                msgs.append((TOPIC_RANGE_BEARING, RangeBearingScan(stamp, ranges, bearings, ids, model["range_sigma_m"],
                                                                   model["bearing_sigma_rad"])))
                scans += 1
            for topic, msg in msgs:
                rec.write(topic, msg)
            if progress is not None and (k % every == 0 or k == n - 1):
                progress(k + 1, n)
    length = float(np.sum(np.hypot(data.odo_z[:, 0], data.odo_z[:, 1])))
    return ImportSummary(Path(out), n, scans, len(data.obs_pose), len(lm_ids), length, reference is not None)
