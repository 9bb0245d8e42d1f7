"""D-SLAM on a seeded in-memory landmark world: error and NEES bounds, unknown ids, determinism.

``landmark_world`` is shared with tests/algorithms/test_ekfslam.py.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from slamreplay.algorithms.common import se2
from slamreplay.algorithms.common.motion import OdometryNoise
from slamreplay.algorithms.dslam import DSlam, DSlamConfig, ScanStatus

F64 = NDArray[np.float64]
START = np.array([0.5, 0.5, 0.7])
NOISE = OdometryNoise(0.03, 0.03, 0.05)  # bounds the world's odometry noise below
SIGMA_R, SIGMA_B = 0.05, np.radians(1.0)


@dataclass(frozen=True)
class Step:
    increment: F64  # odometry increment (robot frame)
    pose: F64  # true pose in the world
    ranges: F64
    bearings: F64
    ids: NDArray[np.int64]


def landmark_world(seed: int, steps: int = 400, still: int = 20) -> tuple[F64, list[Step]]:
    """A 6x6 grid of landmarks 3 m apart; a robot standing ``still`` steps, then wandering at 0.2 m/s.

    One step is 0.2 s: odometry increments with Gaussian noise, then a 180-degree, 5 m scan.
    """
    rng = np.random.default_rng(seed)
    g = np.arange(6) * 3.0 + 1.0
    landmarks = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    pose, w, out = START.copy(), 0.0, []
    for k in range(steps):
        u = np.zeros(3)
        if k >= still:
            w = float(np.clip(0.9 * w + rng.normal(0, 0.05), -0.3, 0.3))
            to_centre = landmarks.mean(0) - pose[:2]
            if np.hypot(*to_centre) > 7:
                w = float(np.clip(se2.wrap_angle(np.arctan2(to_centre[1], to_centre[0]) - pose[2]), -0.3, 0.3))
            u = np.array([0.04, 0.0, 0.2 * w])
        pose = se2.compose(pose, u)
        odo = u + (rng.normal(0, [0.004, 0.001, 0.004]) if k >= still else 0.0)
        rel = se2.transform_points(se2.inverse(pose), landmarks)
        r, b = np.hypot(rel[:, 0], rel[:, 1]), np.arctan2(rel[:, 1], rel[:, 0])
        ids = np.flatnonzero((r < 5) & (np.abs(b) < np.pi / 2))
        rr, bb = r[ids] + rng.normal(0, SIGMA_R, len(ids)), b[ids] + rng.normal(0, SIGMA_B, len(ids))
        ok = rr > 0.2
        out.append(Step(odo, pose.copy(), rr[ok], bb[ok], ids[ok]))
    return landmarks, out


@dataclass(frozen=True)
class Score:
    mapped: int
    false: int
    rmse: float
    landmark_nees: float
    robot_nees: float
    final_error: float


def score(est: F64, cov: F64, ids: list[int], landmarks: F64, poses: list[F64], steps: list[Step]) -> Score:
    """Landmark RMSE/NEES against the truth in the map frame (known START), robot NEES over the run."""
    truth = se2.transform_points(se2.inverse(START), landmarks)
    if all(i >= 0 for i in ids):
        matched, false = truth[np.asarray(ids, dtype=np.int64)], 0
    else:
        dist, idx = cKDTree(truth).query(est)
        matched, false = truth[idx], int(np.sum(dist > 1.0)) + len(idx) - len(set(idx.tolist()))
    err = est - matched
    nees = np.einsum("ni,nij,nj->n", err, np.linalg.inv(cov), err)
    robot = []
    for (pose, pcov), step in zip(poses, steps, strict=True):
        e = se2.between(START, step.pose) - pose
        e[2] = se2.wrap_angle(e[2])
        if pcov[0, 0] > 0:
            robot.append(e @ np.linalg.solve(pcov, e))
    final = float(np.hypot(*(se2.between(START, steps[-1].pose) - poses[-1][0])[:2]))
    return Score(len(est), false, float(np.sqrt(np.mean(np.sum(err**2, 1)))), float(nees.mean()),
                 float(np.mean(robot)), final)


def run_dslam(seed: int, association: str = "known", recovery: str = "local", n: int = 400
              ) -> tuple[Score, DSlam, list]:
    """D-SLAM over one world of ``n`` steps; returns the score, the filter and the scan results."""
    landmarks, steps = landmark_world(seed, n)
    slam = DSlam(DSlamConfig(odometry_noise=NOISE, association=association, recovery=recovery))  # type: ignore[arg-type]
    results, poses = [], []
    for s in steps:
        slam.predict(s.increment)
        res = slam.observe(s.ranges, s.bearings, s.ids, SIGMA_R, SIGMA_B)
        results.append(res)
        poses.append((res.pose, res.pose_cov))
    slam.finalize()
    ids = slam.feature_ids if association == "known" else [-1] * slam.n
    return score(slam.estimates(), slam.marginal_covariances(), ids, landmarks, poses, steps), slam, results


def test_known_ids_error_and_nees_bounds() -> None:
    """Seeds 1-2: landmark RMSE < 10 cm, landmark NEES mean <= 3, robot NEES mean <= 4, final error < 20 cm."""
    for seed in (1, 2):
        s, slam, results = run_dslam(seed)
        assert s.mapped >= 15 and s.false == 0
        assert s.rmse < 0.10 and s.landmark_nees <= 3.0 and s.robot_nees <= 4.0 and s.final_error < 0.2
        statuses = {r.status for r in results}
        assert {ScanStatus.PHASE_I, ScanStatus.MAPPED} <= statuses
        assert all(r.anchors is not None for r in results if r.status is ScanStatus.MAPPED)
        assert slam.info.nnz_blocks < slam.n**2  # exactly sparse: far features are never linked


def test_unknown_ids_map_every_seen_landmark_once() -> None:
    """Unknown ids: every mapped feature is a distinct true landmark, with bounds close to known ids."""
    s, _, _ = run_dslam(1, association="unknown")
    assert s.false == 0 and s.mapped >= 15
    assert s.rmse < 0.12 and s.landmark_nees <= 3.0 and s.robot_nees <= 4.0


@pytest.mark.parametrize("recovery", ["pcg", "direct"])
def test_recovery_modes_agree(recovery: str) -> None:
    """The local, PCG and direct recoveries give the same map to 0.1 mm (their linearisation points differ)."""
    local, a, _ = run_dslam(3, n=200)
    other, b, _ = run_dslam(3, recovery=recovery, n=200)
    np.testing.assert_allclose(a.estimates(), b.estimates(), atol=1e-4)
    assert local.rmse == pytest.approx(other.rmse, abs=1e-4)


def test_runs_are_deterministic() -> None:
    """Same inputs, same results, bit for bit."""
    _, a, ra = run_dslam(4, n=150)
    _, b, rb = run_dslam(4, n=150)
    assert np.array_equal(a.estimates(), b.estimates())
    assert all(np.array_equal(x.pose, y.pose) and x.anchors == y.anchors for x, y in zip(ra, rb, strict=True))


def test_a_local_step_never_touches_the_whole_map(monkeypatch: pytest.MonkeyPatch) -> None:
    """Scans recovered locally use no global product of I (O(N)); the grid finds the same features as a scan of all."""
    from slamreplay.algorithms.dslam.information import InformationMatrix

    calls = [0]
    original = InformationMatrix.csr

    def counted(self: InformationMatrix):  # type: ignore[no-untyped-def]
        calls[0] += 1
        return original(self)

    monkeypatch.setattr(InformationMatrix, "csr", counted)
    _, steps = landmark_world(5, 200)
    slam = DSlam(DSlamConfig(odometry_noise=NOISE, association="unknown"))
    local = 0
    for s in steps:
        slam.predict(s.increment)
        before = calls[0]
        res = slam.observe(s.ranges, s.bearings, None, SIGMA_R, SIGMA_B)
        if res.recovery is not None and res.recovery.method == "local" and res.covariance is None:
            local += 1
            assert calls[0] == before
        centre = res.pose[:2]
        brute = np.flatnonzero(np.hypot(*(slam.estimates() - centre).T) <= 6.0).tolist()
        assert slam.within(centre, 6.0) == brute
    assert local > 100
