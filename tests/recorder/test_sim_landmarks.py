"""Tests for the sim-landmarks simulator (recorder/sim/landmarks.py)."""

from __future__ import annotations

import dataclasses
import json
import math
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.reader import make_reader
from numpy.typing import NDArray
from readback import by_topic, poses, read_recording

from slamreplay.recorder.messages import (
    TOPIC_GROUND_TRUTH_LANDMARKS,
    TOPIC_GROUND_TRUTH_POSE,
    TOPIC_ODOM,
    TOPIC_RANGE_BEARING,
    LandmarkMap,
    Message,
    RangeBearingScan,
    assert_msg_equal,
)
from slamreplay.recorder.sim import LandmarkSimConfig, simulate_landmarks
from slamreplay.recorder.sim.landmarks import EPOCH_NS, landmark_positions, simulate_motion

NOISE_FREE: dict[str, Any] = {"range_sigma_m": 0.0, "bearing_sigma_deg": 0.0, "odom_speed_sigma_mps": 0.0,
                              "odom_turn_sigma_radps": 0.0}

def compose(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """SE(2) a ⊕ b for a (3,) and b (n, 3)."""
    c, s = math.cos(a[2]), math.sin(a[2])
    return np.column_stack([a[0] + c * b[:, 0] - s * b[:, 1], a[1] + s * b[:, 0] + c * b[:, 1], a[2] + b[:, 2]])


def wrap(a: NDArray[np.float64]) -> NDArray[np.float64]:
    """Angles wrapped to [-pi, pi)."""
    return (a + np.pi) % (2 * np.pi) - np.pi


@pytest.fixture(scope="module")
def paper_run(tmp_path_factory: pytest.TempPathFactory) -> list[tuple[str, int, Message]]:
    """The paper scenario with default noise, shortened to 300 s."""
    out = tmp_path_factory.mktemp("sim") / "paper.mcap"
    simulate_landmarks(out, LandmarkSimConfig(duration_s=300.0), seed=7)
    return read_recording(out)


@pytest.fixture(scope="module")
def noise_free_run(tmp_path_factory: pytest.TempPathFactory) -> list[tuple[str, int, Message]]:
    """The paper scenario without any noise, 120 s."""
    out = tmp_path_factory.mktemp("sim") / "clean.mcap"
    simulate_landmarks(out, LandmarkSimConfig(duration_s=120.0, **NOISE_FREE), seed=3)
    return read_recording(out)


def test_same_seed_gives_identical_messages(tmp_path: Path) -> None:
    """Two runs with one seed decode to identical messages and log times; another seed differs."""
    cfg = LandmarkSimConfig(duration_s=60.0)
    runs = []
    for name, seed in (("a", 11), ("b", 11), ("c", 12)):
        simulate_landmarks(tmp_path / f"{name}.mcap", cfg, seed=seed)
        runs.append(read_recording(tmp_path / f"{name}.mcap"))
    a, b, c = runs
    assert len(a) == len(b)
    for (ta, la, ma), (tb, lb, mb) in zip(a, b, strict=True):
        assert (ta, la) == (tb, lb)
        assert_msg_equal(ma, mb)
    _, gt_a = poses(a, TOPIC_GROUND_TRUTH_POSE)
    _, gt_c = poses(c, TOPIC_GROUND_TRUTH_POSE)
    assert not np.allclose(gt_a, gt_c)


def test_paper_geometry(paper_run: list[tuple[str, int, Message]]) -> None:
    """196 landmarks on a 14 x 14 grid 3 m apart, centred in the 40 m square; robot starts bottom-left."""
    (lm,) = by_topic(paper_run, TOPIC_GROUND_TRUTH_LANDMARKS, LandmarkMap)
    assert len(lm) == 196
    np.testing.assert_array_equal(lm.landmark_ids, np.arange(196))
    xs, ys = np.unique(lm.positions_m[:, 0]), np.unique(lm.positions_m[:, 1])
    np.testing.assert_allclose(xs, 0.5 + 3.0 * np.arange(14))
    np.testing.assert_allclose(ys, 0.5 + 3.0 * np.arange(14))
    _, gt = poses(paper_run, TOPIC_GROUND_TRUTH_POSE)
    assert gt[0, 0] < 3.0 and gt[0, 1] < 3.0


def test_recording_layout(tmp_path: Path) -> None:
    """Map first at the epoch, ground truth then odometry at equal stamps, times nondecreasing; metadata."""
    cfg = LandmarkSimConfig(duration_s=20.0)
    calls: list[tuple[int, int]] = []
    summary = simulate_landmarks(tmp_path / "r.mcap", cfg, seed=5, progress=lambda d, t: calls.append((d, t)))
    msgs = read_recording(tmp_path / "r.mcap")
    assert msgs[0][0] == TOPIC_GROUND_TRUTH_LANDMARKS and msgs[0][1] == EPOCH_NS
    assert [t for t, _, _ in msgs[1:3]] == [TOPIC_GROUND_TRUTH_POSE, TOPIC_ODOM]
    log_times = [lt for _, lt, _ in msgs]
    assert log_times == sorted(log_times)
    assert all(isinstance(m.stamp_ns, int) and m.stamp_ns == lt for _, lt, m in msgs)
    gt_t, _ = poses(msgs, TOPIC_GROUND_TRUTH_POSE)
    odom_t, odom = poses(msgs, TOPIC_ODOM)
    np.testing.assert_array_equal(gt_t, odom_t)
    np.testing.assert_array_equal(np.diff(gt_t), 100_000_000)
    np.testing.assert_array_equal(odom[0], [0.0, 0.0, 0.0])
    scan_t = [m.stamp_ns for m in by_topic(msgs, TOPIC_RANGE_BEARING, RangeBearingScan)]
    np.testing.assert_array_equal(np.diff(scan_t), 200_000_000)
    assert summary.messages == len(msgs) == 1 + 2 * 201 + 101
    assert calls[-1] == (201, 201) and [d for d, _ in calls] == sorted(d for d, _ in calls)
    with open(tmp_path / "r.mcap", "rb") as f:
        meta = next(m for m in make_reader(f).iter_metadata() if m.name == "slamreplay.recording").metadata
    assert json.loads(meta["source"]) == {"simulator": "sim-landmarks"}
    assert meta["seed"] == "5"
    assert json.loads(meta["parameters"]) == dataclasses.asdict(cfg)


def test_observations_within_sensor_limits(paper_run: list[tuple[str, int, Message]]) -> None:
    """Every reported range is within 5 m and every bearing within +-90 degrees."""
    scans = by_topic(paper_run, TOPIC_RANGE_BEARING, RangeBearingScan)
    ranges = np.concatenate([s.ranges_m for s in scans])
    bearings = np.concatenate([s.bearings_rad for s in scans])
    assert len(ranges) > 1000
    assert ranges.min() >= 0.0 and ranges.max() <= 5.0
    assert np.abs(bearings).max() <= math.pi / 2


def test_noise_free_scans_match_ground_truth(noise_free_run: list[tuple[str, int, Message]]) -> None:
    """Without noise, each scan holds exactly the landmarks in range and view, at their true range and bearing."""
    (lm,) = by_topic(noise_free_run, TOPIC_GROUND_TRUTH_LANDMARKS, LandmarkMap)
    gt_t, gt = poses(noise_free_run, TOPIC_GROUND_TRUTH_POSE)
    pose_at = dict(zip(gt_t.tolist(), gt, strict=True))
    scans = by_topic(noise_free_run, TOPIC_RANGE_BEARING, RangeBearingScan)
    for scan in scans:
        p = pose_at[scan.stamp_ns]
        d = lm.positions_m - p[:2]
        r = np.hypot(d[:, 0], d[:, 1])
        b = wrap(np.arctan2(d[:, 1], d[:, 0]) - p[2])
        surely = np.flatnonzero((r <= 5.0 - 1e-9) & (np.abs(b) <= math.pi / 2 - 1e-9))
        maybe = np.flatnonzero((r <= 5.0 + 1e-9) & (np.abs(b) <= math.pi / 2 + 1e-9))
        ids = scan.landmark_ids
        assert set(surely) <= set(ids) <= set(maybe)
        np.testing.assert_allclose(scan.ranges_m, r[ids], atol=1e-9)
        np.testing.assert_allclose(wrap(scan.bearings_rad - b[ids]), 0.0, atol=1e-9)
        assert scan.range_sigma_m == 0.0 and scan.bearing_sigma_rad == 0.0
    assert sum(len(s) for s in scans) > 500


def test_noise_free_odometry_is_ground_truth(noise_free_run: list[tuple[str, int, Message]]) -> None:
    """Without odometry noise, /odom composed onto the first true pose reproduces the ground truth."""
    _, gt = poses(noise_free_run, TOPIC_GROUND_TRUTH_POSE)
    _, odom = poses(noise_free_run, TOPIC_ODOM)
    dr = compose(gt[0], odom)
    np.testing.assert_allclose(dr[:, :2], gt[:, :2], atol=1e-6)
    np.testing.assert_allclose(wrap(dr[:, 2] - gt[:, 2]), 0.0, atol=1e-9)


def test_motion_limits_and_stationary_phase(paper_run: list[tuple[str, int, Message]]) -> None:
    """Still for the first 5 s while scanning; then 0.2 m/s with turn rates within 0.1 rad/s."""
    gt_t, gt = poses(paper_run, TOPIC_GROUND_TRUTH_POSE)
    _, odom = poses(paper_run, TOPIC_ODOM)
    dt = np.diff(gt_t) / 1e9
    speed = np.hypot(*np.diff(gt[:, :2], axis=0).T) / dt
    turn = wrap(np.diff(gt[:, 2])) / dt
    still = gt_t[1:] <= EPOCH_NS + 5_000_000_000
    assert still.sum() == 50
    np.testing.assert_array_equal(speed[still], 0.0)
    np.testing.assert_array_equal(odom[: still.sum() + 1], 0.0)
    assert speed[~still] == pytest.approx(0.2, abs=1e-4)
    assert np.abs(turn).max() <= 0.1 + 1e-9
    scans = by_topic(paper_run, TOPIC_RANGE_BEARING, RangeBearingScan)
    early = [s for s in scans if s.stamp_ns <= EPOCH_NS + 5_000_000_000]
    assert len(early) == 26 and all(len(s) >= 2 for s in early)


@pytest.mark.parametrize("overrides", [{}, {"landmarks": 50}, {"max_turn_rate_radps": 0.05},
                                       {"area_m": 20.0, "landmarks": 36}])
def test_robot_stays_inside_the_square(overrides: dict[str, Any]) -> None:
    """Over many seeds of a long run the true trajectory never leaves the square."""
    cfg = LandmarkSimConfig(duration_s=1800.0, **overrides)
    for seed in range(6):
        _, _, path = simulate_motion(cfg, 18000, np.random.default_rng(seed))
        assert path[:, :2].min() > 0.5 and path[:, :2].max() < cfg.side_m - 0.5


def test_noise_matches_configured_sigmas(paper_run: list[tuple[str, int, Message]]) -> None:
    """Range, bearing, speed and turn-rate residuals have about the configured standard deviations."""
    cfg = LandmarkSimConfig()
    (lm,) = by_topic(paper_run, TOPIC_GROUND_TRUTH_LANDMARKS, LandmarkMap)
    gt_t, gt = poses(paper_run, TOPIC_GROUND_TRUTH_POSE)
    pose_at = dict(zip(gt_t.tolist(), gt, strict=True))
    dr, db = [], []
    for scan in by_topic(paper_run, TOPIC_RANGE_BEARING, RangeBearingScan):
        assert scan.range_sigma_m == 0.05 and scan.bearing_sigma_rad == pytest.approx(math.radians(1.0))
        p, q = pose_at[scan.stamp_ns], lm.positions_m[scan.landmark_ids]
        dr.append(scan.ranges_m - np.hypot(*(q - p[:2]).T))
        db.append(wrap(scan.bearings_rad - np.arctan2(*(q - p[:2]).T[::-1]) + p[2]))
    range_res, bearing_res = np.concatenate(dr), np.concatenate(db)
    assert len(range_res) > 3000
    assert np.std(range_res) == pytest.approx(cfg.range_sigma_m, rel=0.1)
    assert np.std(bearing_res) == pytest.approx(math.radians(cfg.bearing_sigma_deg), rel=0.1)
    assert abs(np.mean(range_res)) < 0.005
    _, odom = poses(paper_run, TOPIC_ODOM)
    moving = slice(51, None)
    odom_speed = np.hypot(*np.diff(odom[:, :2], axis=0).T)[moving] / 0.1
    odom_turn = np.diff(odom[:, 2])[moving] / 0.1
    true_turn = wrap(np.diff(gt[:, 2]))[moving] / 0.1
    assert np.std(odom_speed - 0.2) == pytest.approx(cfg.odom_speed_sigma_mps, rel=0.1)
    assert np.std(wrap((odom_turn - true_turn) * 0.1) / 0.1) == pytest.approx(cfg.odom_turn_sigma_radps, rel=0.1)


def test_odometry_bias_scales_distance(tmp_path: Path) -> None:
    """A +5 % speed bias without noise makes odometry travel 5 % further than the robot."""
    cfg = LandmarkSimConfig(duration_s=60.0, odom_speed_bias=0.05, **NOISE_FREE)
    simulate_landmarks(tmp_path / "b.mcap", cfg, seed=1)
    msgs = read_recording(tmp_path / "b.mcap")
    lengths = [np.hypot(*np.diff(poses(msgs, t)[1][:, :2], axis=0).T).sum()
               for t in (TOPIC_ODOM, TOPIC_GROUND_TRUTH_POSE)]
    assert lengths[0] == pytest.approx(1.05 * lengths[1], rel=1e-6)


def test_area_rule() -> None:
    """The square stays 40 m for up to 196 landmarks, grows to fit more at 3 m spacing, or is as given."""
    assert LandmarkSimConfig(landmarks=50).side_m == 40.0
    big = LandmarkSimConfig(landmarks=1000)
    assert big.side_m == (32 - 1) * 3.0 + 1.0
    pos = landmark_positions(big)
    assert pos.shape == (1000, 2) and pos.min() >= 0.5 - 1e-9 and pos.max() <= big.side_m - 0.5 + 1e-9
    assert LandmarkSimConfig(area_m=60.0).side_m == 60.0


@pytest.mark.parametrize(("overrides", "match"), [
    ({"duration_s": 0.0}, "duration_s"),
    ({"duration_s": float("nan")}, "duration_s"),
    ({"landmarks": 0}, "landmarks"),
    ({"landmarks": 2.5}, "landmarks"),
    ({"area_m": 30.0}, "area_m"),
    ({"area_m": 12.0, "landmarks": 4}, "area_m"),
    ({"landmark_spacing_m": -1.0}, "landmark_spacing_m"),
    ({"speed_mps": 0.0}, "speed_mps"),
    ({"max_turn_rate_radps": 0.0}, "max_turn_rate_radps"),
    ({"sensor_range_m": 0.0}, "sensor_range_m"),
    ({"sensor_fov_deg": 400.0}, "sensor_fov_deg"),
    ({"range_sigma_m": -0.1}, "range_sigma_m"),
    ({"bearing_sigma_deg": -1.0}, "bearing_sigma_deg"),
    ({"odom_speed_sigma_mps": -1.0}, "odom_speed_sigma_mps"),
    ({"odom_turn_sigma_radps": float("inf")}, "odom_turn_sigma_radps"),
    ({"odom_speed_bias": 0.9}, "odom_speed_bias"),
    ({"stationary_s": -1.0}, "stationary_s"),
    ({"odom_rate_hz": 0.0}, "odom_rate_hz"),
    ({"scan_rate_hz": -5.0}, "scan_rate_hz"),
    ({"landmarks": 8_371_841}, r"landmarks must be in \[1, 100,000\]"),  # the fuzzer's: 24 GB in the service
    # (recorder/sim/bounds.py; the corridor's and the seabed's in test_sim_bounds below)
    ({"duration_s": 1e7}, r"100,000,000 samples, more than 2,000,000"),
    ({"scan_rate_hz": 1e6, "duration_s": 10.0}, "10,000,000 samples"),
])
def test_config_validation(overrides: dict[str, Any], match: str) -> None:
    """Each bad parameter raises ValueError naming it."""
    with pytest.raises(ValueError, match=match):
        LandmarkSimConfig(**overrides)


def test_scales_to_100k_landmarks(tmp_path: Path) -> None:
    """100,000 landmarks and a short run record quickly, with consistent observations."""
    cfg = LandmarkSimConfig(landmarks=100_000, duration_s=30.0)
    start = time.perf_counter()
    summary = simulate_landmarks(tmp_path / "big.mcap", cfg, seed=2)
    print(f"100k landmarks, 30 s: simulated in {time.perf_counter() - start:.2f} s ({summary.messages} messages)")
    msgs = read_recording(tmp_path / "big.mcap")
    (lm,) = by_topic(msgs, TOPIC_GROUND_TRUTH_LANDMARKS, LandmarkMap)
    assert len(lm) == 100_000
    scans = by_topic(msgs, TOPIC_RANGE_BEARING, RangeBearingScan)
    assert len(scans) == 151 and summary.observations == sum(len(s) for s in scans) > 0
    assert summary.area_m == (317 - 1) * 3.0 + 1.0


@pytest.mark.parametrize(("sim", "overrides", "match"), [
    ("corridor", {"image_height": 127058998962946049}, r"from 32 x 24 to 4096 x 4096"),  # the fuzzer's: 24 GB
    ("corridor", {"laps": 100_000}, r"images .*: 192,750,000, more than 100,000"),
    ("corridor", {"twins": 10**6}, r"twins must be at most 100"),
    ("seabed", {"image_px": 100_000}, r"image_px must be an integer from 32 to 4096"),
    ("seabed", {"legs": 10**6}, r"images .*more than 100,000"),
    ("seabed", {"leg_spacing": 1.0, "legs": 2000, "image_spacing": 1.0, "metres_per_pixel": 0.001},
     r"seabed pixels to render .*more than 256,000,000"),
])
def test_sim_bounds(sim: str, overrides: dict[str, Any], match: str) -> None:
    """What one simulation may ask for is bounded (recorder/sim/bounds.py), each error naming what to do."""
    from slamreplay.recorder.sim.corridor_config import CorridorConfig
    from slamreplay.recorder.sim.seabed_config import SeabedSimConfig

    with pytest.raises(ValueError, match=match):
        (CorridorConfig if sim == "corridor" else SeabedSimConfig)(**overrides)
