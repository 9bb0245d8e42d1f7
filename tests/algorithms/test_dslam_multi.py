"""Multi-robot D-SLAM on a seeded three-robot landmark world: shared map error and NEES bounds, more landmarks
than one robot maps, exact sparsity, one robot equal to DSlam, error paths."""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import cache

import numpy as np
import pytest
from numpy.typing import NDArray

from slamreplay.algorithms.common import se2
from slamreplay.algorithms.common.motion import OdometryNoise
from slamreplay.algorithms.dslam import DSlam, DSlamConfig
from slamreplay.algorithms.dslam.multi import MultiDSlam

F64 = NDArray[np.float64]
SIGMA_R, SIGMA_B = 0.05, np.radians(1.0)
NOISE = OdometryNoise(0.03, 0.03, 0.05)  # bounds the world's odometry noise below
STARTS = {"1": np.array([4.0, 5.0, 0.3]), "2": np.array([14.0, 6.0, -1.0]), "3": np.array([24.0, 5.0, 2.0])}
START_SIGMA = np.array([0.01, 0.01, 0.005])  # the prior of the robots other than the reference


@dataclass(frozen=True)
class Step:
    robot: str
    increment: F64  # odometry increment (robot frame)
    pose: F64  # true pose in the world
    ranges: F64
    bearings: F64
    ids: NDArray[np.int64]


def landmarks() -> F64:
    """A 10 x 4 grid, 3 m apart: 28 m by 10 m."""
    gx, gy = np.arange(10) * 3.0 + 1.0, np.arange(4) * 3.0 + 1.0
    return np.stack(np.meshgrid(gx, gy), -1).reshape(-1, 2)


@cache
def world(seed: int, steps: int = 350, still: int = 15) -> tuple[Step, ...]:
    """Three robots, each wandering around its own third of the grid at 0.2 m/s, steps interleaved (one total
    order). One step is 0.2 s: noisy odometry, then a 180-degree, 5 m scan. Robot 1 stands ``still`` steps."""
    rng = np.random.default_rng(seed)
    lm = landmarks()
    poses = {k: p.copy() for k, p in STARTS.items()}
    turn = dict.fromkeys(STARTS, 0.0)
    out = []
    for k in range(steps):
        for name in STARTS:
            pose = poses[name]
            u = np.zeros(3)
            if name != "1" or k >= still:
                w = float(np.clip(0.9 * turn[name] + rng.normal(0, 0.05), -0.3, 0.3))
                home = STARTS[name][:2] + np.array([0.0, 0.5]) - pose[:2]
                if np.hypot(*home) > 4:
                    w = float(np.clip(se2.wrap_angle(np.arctan2(home[1], home[0]) - pose[2]), -0.3, 0.3))
                turn[name] = w
                u = np.array([0.04, 0.0, 0.2 * w])
            pose = poses[name] = se2.compose(pose, u)
            odo = u + (rng.normal(0, [0.004, 0.001, 0.004]) if np.any(u) else 0.0)
            rel = se2.transform_points(se2.inverse(pose), lm)
            r, b = np.hypot(rel[:, 0], rel[:, 1]), np.arctan2(rel[:, 1], rel[:, 0])
            ids = np.flatnonzero((r < 5) & (np.abs(b) < np.pi / 2))
            rr, bb = r[ids] + rng.normal(0, SIGMA_R, len(ids)), b[ids] + rng.normal(0, SIGMA_B, len(ids))
            out.append(Step(name, odo, pose.copy(), rr, bb, ids))
    return tuple(out)


def config() -> DSlamConfig:
    return DSlamConfig(odometry_noise=NOISE, default_range_sigma_m=SIGMA_R, default_bearing_sigma_rad=SIGMA_B)


def run_multi(steps: tuple[Step, ...], robots: tuple[str, ...] = ("1", "2", "3"), finalize: bool = True,
              robot_bootstrap: bool = True) -> tuple[MultiDSlam, list[set[int]]]:
    """Replay the steps of ``robots`` through MultiDSlam (map frame: robot 1's start); the features of each scan."""
    slam = MultiDSlam({k: config() for k in robots}, "1", robot_bootstrap=robot_bootstrap)
    origin = STARTS["1"]
    for k in robots:
        if k != "1":
            slam.start(k, se2.between(origin, STARTS[k]), np.diag(START_SIGMA**2))
    scans = []
    for s in steps:
        if s.robot not in robots:
            continue
        slam.predict(s.robot, s.increment)
        res = slam.observe(s.robot, s.ranges, s.bearings, s.ids)
        scans.append({int(f) for f in res.features.tolist() if f >= 0})
    if finalize:
        slam.finalize()
    return slam, scans


def map_errors(slam: MultiDSlam) -> tuple[F64, F64]:
    """World-frame errors (N, 2) of the mapped features and their NEES (N,)."""
    origin = STARTS["1"]
    est = se2.transform_points(origin, slam.estimates())
    err = est - landmarks()[np.asarray(slam.feature_ids)]
    rot = se2.rot(origin[2])
    covs = rot @ slam.marginal_covariances() @ rot.T
    return err, np.einsum("ni,nij,nj->n", err, np.linalg.inv(covs), err)


@pytest.mark.parametrize("seed", [1, 2])
def test_shared_map_is_accurate_and_consistent(seed: int) -> None:
    """Three robots, one map: landmark error and mean NEES within two-sided bounds."""
    slam, _ = run_multi(world(seed))
    err, nees = map_errors(slam)
    rmse = float(np.sqrt(np.mean(np.sum(err**2, axis=1))))
    assert slam.n == len(set(slam.feature_ids)) >= 36  # of 40
    assert 0.005 < rmse < 0.1
    assert 0.2 < float(nees.mean()) < 6.0  # the band of a shared-error mean NEES (docs/dslam.md), not 1.7-2.3
    for k in STARTS:  # each robot localized against the shared map
        state = slam.robot(k)
        true = [s.pose for s in world(seed) if s.robot == k][-1]
        assert np.hypot(*(se2.transform_points(STARTS["1"], state.pose[None, :2])[0] - true[:2])) < 0.2


def test_robots_together_map_more_than_one_alone() -> None:
    """Each robot explores its own third: the shared map holds more landmarks than any robot's own map."""
    steps = world(1)
    joint, _ = run_multi(steps)
    for k in STARTS:  # what robot k saw bounds what it could map alone
        own = {int(i) for s in steps if s.robot == k for i in s.ids.tolist()}
        assert joint.n > len(own) >= 8
    single, _ = run_multi(steps, ("1",))
    assert joint.n >= single.n + 20
    # only the first robot starts the map: robot 3's corner, never seen with two mapped landmarks, stays out
    first_only, _ = run_multi(steps, robot_bootstrap=False)
    assert single.n + 8 <= first_only.n <= joint.n - 8


def test_information_matrix_is_exactly_sparse() -> None:
    """The EIF (eqs. 9-10) holds only feature-feature links, each between two features one robot's scan saw."""
    slam, scans = run_multi(world(1), finalize=False)
    assert slam.info.n == slam.n  # no robot state in the map's EIF
    links = slam.info.links()
    assert len(links)
    for a, b in links.tolist():
        assert any(a in s and b in s for s in scans), (a, b)
    assert slam.info.nnz_blocks < 0.5 * slam.n**2


def test_one_robot_equals_dslam() -> None:
    """MultiDSlam with the reference robot alone is DSlam, to the last bit."""
    steps = [s for s in world(3, steps=200) if s.robot == "1"]
    single = DSlam(config())
    multi = MultiDSlam({"1": config()}, "1")
    for s in steps:
        single.predict(s.increment)
        multi.predict("1", s.increment)
        a = single.observe(s.ranges, s.bearings, s.ids)
        b = multi.observe("1", s.ranges, s.bearings, s.ids)
        assert a.status == b.status
    np.testing.assert_array_equal(single.estimates(), multi.estimates())
    np.testing.assert_array_equal(single.pose, multi.robot("1").pose)


def test_bad_configs_and_calls() -> None:
    """Wrong reference, a map setting that differs, composite scans, unknown ids, bad starts: ValueError."""
    cfg = config()
    with pytest.raises(ValueError, match="reference robot '9' is not one of"):
        MultiDSlam({"1": cfg}, "9")
    with pytest.raises(ValueError, match="at least one robot"):
        MultiDSlam({}, "1")
    with pytest.raises(ValueError, match=r"robot '2': recovery describes the shared map"):
        MultiDSlam({"1": cfg, "2": replace(cfg, recovery="direct")}, "1")
    with pytest.raises(ValueError, match="composite_max_scans must be 0"):
        MultiDSlam({"1": replace(cfg, composite_max_scans=10)}, "1")
    with pytest.raises(ValueError, match="association must be 'known'"):
        MultiDSlam({"1": replace(cfg, association="unknown")}, "1")
    slam = MultiDSlam({"1": cfg, "2": replace(cfg, default_range_sigma_m=0.2)}, "1")  # a robot's own noise: fine
    with pytest.raises(ValueError, match="robot '2' has no start pose"):
        slam.observe("2", [1.0], [0.0], [0])
    with pytest.raises(ValueError, match=r"robot must be one of \['1', '2'\], got '3'"):
        slam.predict("3", [0.1, 0.0, 0.0])
    with pytest.raises(ValueError, match="is the reference"):
        slam.start("1", np.zeros(3), np.eye(3))
    with pytest.raises(ValueError, match="pose must be 3 finite numbers"):
        slam.start("2", [0.0, np.nan, 0.0], np.eye(3))
    with pytest.raises(ValueError, match="symmetric positive semidefinite"):
        slam.start("2", np.zeros(3), -np.eye(3))
    slam.start("2", np.zeros(3), np.eye(3) * 1e-4)
    slam.observe("2", [1.0], [0.0], [0])
    with pytest.raises(ValueError, match="already observed"):
        slam.start("2", np.zeros(3), np.eye(3))
    with pytest.raises(ValueError, match="ranges"):
        slam.observe("1", [-1.0], [0.0], [0])
    slam.observe("1", [2.0], [0.5], [1])  # the failed call left no robot loaded
