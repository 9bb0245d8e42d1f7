"""sim-corridor: determinism, camera geometry, odometry drift, collisions, world round trips, config, CLI."""

from __future__ import annotations

import dataclasses
import itertools
import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import write_tiny_recording
from readback import by_topic, poses, read_recording

from slamreplay.api.cli.command import main
from slamreplay.recorder.errors import RecorderError
from slamreplay.recorder.messages import (
    TOPIC_CAMERA_CALIBRATION,
    TOPIC_CAMERA_IMAGE,
    TOPIC_GROUND_TRUTH_POSE,
    TOPIC_ODOM,
    CameraCalibration,
    CameraImage,
    assert_msg_equal,
)
from slamreplay.recorder.sim.corridor import (
    CorridorConfig,
    CorridorWorld,
    WheelOdometry,
    drive_route,
    simulate_corridor,
    world_from_file,
    world_from_metadata,
)
from slamreplay.recorder.sim.corridor_plan import TOURS
from slamreplay.recorder.sim.unicycle import arc_step, wrap_angle
from slamreplay.replay.engine.reader import RecordingReader

SMALL = CorridorConfig(route="left", speed_mps=1.0, turn_rate_dps=60.0, camera_rate_hz=1.0, odom_rate_hz=10.0)
NO_DRIFT = {"odom_wheel_ratio_error": 0.0, "odom_wheelbase_error": 0.0, "odom_scale_error": 0.0, "odom_sigma_m": 0.0,
            "odom_sigma_rad": 0.0, "odom_sigma_rad_per_m": 0.0}


@pytest.fixture(scope="module")
def small_recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("corridor") / "small.mcap"
    simulate_corridor(path, SMALL, seed=3)
    return path


def texture_folder(path: Path, stripe: bool) -> str:
    """A folder with one black texture, with a white vertical stripe in the middle if ``stripe``."""
    path.mkdir()
    img = np.zeros((256, 192), np.uint8)
    if stripe:
        img[:, 90:102] = 255
    cv2.imwrite(str(path / "t.png"), img)
    return str(path)


def test_deterministic_and_complete(small_recording: Path, tmp_path: Path) -> None:
    """Same seed, same messages; poses and odometry at every step, an image every few steps, one calibration."""
    summary = simulate_corridor(tmp_path / "b.mcap", SMALL, seed=3)
    a, b = read_recording(small_recording), read_recording(tmp_path / "b.mcap")
    assert len(a) == len(b) == summary.messages
    for (ta, la, ma), (tb, lb, mb) in zip(a, b, strict=True):
        assert (ta, la) == (tb, lb)
        assert_msg_equal(ma, mb)
    images = by_topic(a, TOPIC_CAMERA_IMAGE, CameraImage)
    stamps, _ = poses(a, TOPIC_GROUND_TRUTH_POSE)
    odom_stamps, _ = poses(a, TOPIC_ODOM)
    assert len(images) == summary.images == math.ceil(summary.poses / 10) and len(stamps) == summary.poses
    assert np.array_equal(stamps, odom_stamps) and np.all(np.diff(stamps) == 100_000_000)
    assert {im.stamp_ns for im in images} <= set(stamps.tolist())
    assert images[0].pixels.shape == (240, 320) and images[0].compression == "jpeg"
    (calib,) = by_topic(a, TOPIC_CAMERA_CALIBRATION, CameraCalibration)
    np.testing.assert_allclose(calib.K, SMALL.camera_matrix)
    assert SMALL.focal_px == pytest.approx(160.0 / math.tan(math.radians(23.0)))
    assert summary.path_length_m == pytest.approx(34.0, abs=1.5)  # the left loop, corners cut


def test_other_seed_differs(small_recording: Path, tmp_path: Path) -> None:
    """Another seed gives other walls, images and odometry."""
    simulate_corridor(tmp_path / "c.mcap", SMALL, seed=4)
    a, c = read_recording(small_recording), read_recording(tmp_path / "c.mcap")
    ia, ic = by_topic(a, TOPIC_CAMERA_IMAGE, CameraImage), by_topic(c, TOPIC_CAMERA_IMAGE, CameraImage)
    assert not np.array_equal(ia[5].pixels, ic[5].pixels)
    assert not np.allclose(poses(a, TOPIC_ODOM)[1][-1], poses(c, TOPIC_ODOM)[1][-1])


def test_wall_height_in_image(tmp_path: Path) -> None:
    """Facing a wall d metres away, the wall spans f * wall_height / d rows (within a pixel)."""
    cfg = CorridorConfig(texture=texture_folder(tmp_path / "black", stripe=False), plain_fraction=0.0)
    world = CorridorWorld.from_config(cfg, 0)
    pose = np.array([6.1, 0.0, math.pi])  # the south corridor, looking west at the west wall (x = -0.9)
    depth, panel, _ = world.ray_cast(pose)
    assert depth[160] == pytest.approx(7.0) and np.all(panel >= 0)
    img = world.render(pose)
    for col in (130, 160, 190):  # on the end wall (the side walls are nearer, and taller than the image)
        rows = int(np.count_nonzero(img[:, col] < 30))
        assert abs(rows - cfg.focal_px * cfg.wall_height_m / depth[col]) <= 1.0, (col, rows)
    horizon = int(np.flatnonzero(img[:, 160] < 30).max()) + 1  # first floor row
    assert abs(horizon - (119.5 + cfg.focal_px * cfg.camera_height_m / 7.0)) <= 1.0


def test_markers_at_predicted_columns(tmp_path: Path) -> None:
    """Stripes at known wall points appear at column cx - f tan(bearing) (the camera's left is +y)."""
    cfg = CorridorConfig(texture=texture_folder(tmp_path / "stripe", stripe=True), plain_fraction=0.0)
    world = CorridorWorld.from_config(cfg, 0)
    pose = np.array([2.0, -0.3, 0.35])  # south corridor, looking a little to the left of east
    img = world.render(pose).astype(np.int32)
    depth, panel, _ = world.ray_cast(pose)
    row = img[120]  # the camera's height, on every wall
    bright = np.flatnonzero(row > 30)  # black walls read about 5; thin far stripes are blurred by the mip-map
    runs = np.split(bright, np.flatnonzero(np.diff(bright) > 1) + 1)
    centres = np.array([(r * row[r]).sum() / row[r].sum() for r in runs if len(r)])
    checked = 0
    for k, (x0, y0, x1, y1) in enumerate(world.walls):
        for along in (0.25, 0.75):  # stripe of each quarter tile of the 2 x 2 montage
            p = np.array([x0 + along * (x1 - x0), y0 + along * (y1 - y0)])
            d = p - pose[:2]
            bearing = float(wrap_angle(math.atan2(d[1], d[0]) - pose[2]))
            u = 159.5 - cfg.focal_px * math.tan(bearing)
            if not 3 <= u <= 316:
                continue
            col = round(u)
            if panel[col] != k or abs(depth[col] - math.hypot(*d) * math.cos(bearing)) > 0.05:
                continue  # hidden behind another wall
            assert np.min(np.abs(centres - u)) <= 1.0, (k, along, u)
            checked += 1
    assert checked >= 4


def test_render_noise_and_brightness_seeded() -> None:
    """The noise-free image is a pure function of the pose; noisy ones depend on the generator only."""
    world = CorridorWorld.from_config(CorridorConfig(), 1)
    pose = [3.0, 0.1, 0.2]
    assert np.array_equal(world.render(pose), world.render(pose))
    a = world.render(pose, np.random.default_rng(5))
    assert np.array_equal(a, world.render(pose, np.random.default_rng(5)))
    assert 0.5 < np.abs(a.astype(float) - world.render(pose)).mean() < 10.0


def test_enough_keypoints() -> None:
    """Images along the route hold enough texture for STAR keypoints (the loop-closure front end)."""
    cfg = CorridorConfig(route="outer")
    world = CorridorWorld.from_config(cfg, 0)
    truth = drive_route(world.route, cfg, np.random.default_rng(0))
    star = cv2.xfeatures2d.StarDetector_create()
    counts = np.array([len(star.detect(world.render(p, np.random.default_rng(0)))) for p in truth[::150]])
    assert np.median(counts) >= 50 and counts.max() <= 300, counts


def test_twins_look_alike() -> None:
    """Some runs of three panels are repeated elsewhere on purpose; most panels differ."""
    world = CorridorWorld.from_config(CorridorConfig(twins=3), 2)
    rows = [tuple(r) for r in world.panel_tiles.tolist()]
    repeats = sum(rows[i:i + 3] == rows[j:j + 3] for i in range(len(rows) - 2) for j in range(i + 3, len(rows) - 2))
    assert repeats >= 1 and len(set(rows)) > 0.8 * len(rows)


def test_straight_run_heading_bias_is_step_size_consistent() -> None:
    """A wheel diameter ratio error e turns the odometry by e L / B over L metres, whatever the step."""
    cfg = CorridorConfig(**{**NO_DRIFT, "odom_wheel_ratio_error": 0.01})
    for step in (0.01, 0.1):
        odo = WheelOdometry(cfg, np.random.default_rng(0))
        for _ in range(round(10.0 / step)):
            odo.step([step, 0.0, 0.0])
        assert odo.pose[2] == pytest.approx(0.01 * 10.0 / cfg.wheel_base_m, rel=1e-9)  # counter-clockwise
    cfg = CorridorConfig(**{**NO_DRIFT, "odom_wheelbase_error": 0.02, "odom_scale_error": 0.01})
    odo = WheelOdometry(cfg, np.random.default_rng(0))
    for _ in range(100):
        odo.step(arc_step(0.0, 0.0, 2 * math.pi / 100, 1.0))  # one turn on the spot
    assert odo.pose[2] == pytest.approx(2 * math.pi * 1.01 / 1.02, rel=1e-9)
    odo = WheelOdometry(cfg, np.random.default_rng(0))
    odo.step([2.0, 0.0, 0.0])
    assert odo.pose[0] == pytest.approx(2.02)


def test_random_drift_grows_with_distance_not_steps() -> None:
    """The random distance error has a std of sigma sqrt(L), for fine and coarse steps alike."""
    cfg = CorridorConfig(**{**NO_DRIFT, "odom_sigma_m": 0.05})
    rng = np.random.default_rng(0)
    for steps in (4, 64):
        finals = []
        for _ in range(300):
            odo = WheelOdometry(cfg, rng)
            for _ in range(steps):
                odo.step([4.0 / steps, 0.0, 0.0])
            finals.append(odo.pose[0])
        assert np.std(finals) == pytest.approx(0.05 * 2.0, rel=0.15)


def test_zero_drift_odometry_equals_truth(tmp_path: Path) -> None:
    """With every odometry error 0 the recorded odometry is the ground truth."""
    simulate_corridor(tmp_path / "z.mcap", dataclasses.replace(SMALL, **NO_DRIFT), seed=1)
    msgs = read_recording(tmp_path / "z.mcap")
    _, truth = poses(msgs, TOPIC_GROUND_TRUTH_POSE)
    _, odom = poses(msgs, TOPIC_ODOM)
    np.testing.assert_allclose(odom[:, :2], truth[:, :2], atol=1e-9)
    np.testing.assert_allclose(wrap_angle(odom[:, 2] - truth[:, 2]), 0.0, atol=1e-9)


def test_default_drift_is_moderate(small_recording: Path) -> None:
    """Default odometry drifts, by a few percent of the distance at most."""
    msgs = read_recording(small_recording)
    _, truth = poses(msgs, TOPIC_GROUND_TRUTH_POSE)
    _, odom = poses(msgs, TOPIC_ODOM)
    err = float(np.hypot(*(odom[-1, :2] - truth[-1, :2])))
    assert 0.0 < err < 0.05 * 34.0


@pytest.mark.parametrize("tour", sorted(TOURS))
def test_routes_stay_clear_of_walls(tour: str) -> None:
    """Every tour is driven in free space, at least 0.3 m (a robot's radius and more) from any wall."""
    cfg = CorridorConfig(route=tour)
    world = CorridorWorld.from_config(cfg, 0)
    truth = drive_route(world.route, cfg, np.random.default_rng(7))
    assert np.all(world.free_mask(truth[:, :2], clearance_m=0.3))
    assert np.hypot(*(truth[-1, :2] - world.route[-1])) < 0.1  # it got home
    assert world.is_free([0.0, 0.0], 0.5) and not world.is_free([3.0, 5.0]) and not world.is_free([3.0, 0.85], 0.3)


def test_default_route_revisits_both_ways() -> None:
    """The default route drives the south corridor east three times and the north one both ways."""
    route = CorridorWorld.from_config(CorridorConfig(), 0).route
    legs = list(itertools.pairwise(route))
    east_south = sum(a[1] == b[1] == 0 and a[0] <= 0 and b[0] >= 7 for a, b in legs)
    north = {np.sign(b[0] - a[0]) for a, b in legs if a[1] == b[1] == 10 and abs(b[0] - a[0]) > 5}
    assert east_south == 3 and north == {-1.0, 1.0}


def test_world_from_metadata_round_trip(small_recording: Path) -> None:
    """The recording's metadata rebuilds the same world (either the whole metadata or its record)."""
    info = RecordingReader(small_recording).info
    world, config, seed = world_from_metadata(info.metadata)
    assert (config, seed) == (SMALL, 3)
    again, _, _ = world_from_metadata(info.metadata["slamreplay.recording"])
    original = CorridorWorld.from_config(SMALL, 3)
    assert np.array_equal(world.walls, original.walls) and np.array_equal(again.panel_tiles, original.panel_tiles)
    assert np.array_equal(world.render([1.0, 0.0, 0.0]), original.render([1.0, 0.0, 0.0]))


def test_world_from_metadata_errors(tmp_path: Path) -> None:
    """Another source, or a missing field, is a RecorderError that says so."""
    info = RecordingReader(write_tiny_recording(tmp_path / "tiny.mcap")).info
    with pytest.raises(RecorderError, match="not a sim-corridor recording"):
        world_from_metadata(info.metadata)
    with pytest.raises(RecorderError, match="no 'parameters'"):
        world_from_metadata({"source": json.dumps({"simulator": "sim-corridor"}), "seed": "1"})
    with pytest.raises(RecorderError, match="invalid sim-corridor config"):
        world_from_metadata({"source": '{"simulator": "sim-corridor"}', "seed": "1", "parameters": '{"laps": 0}'})


def test_world_file_round_trip(tmp_path: Path) -> None:
    """to_json / world_from_file / from_json name the same world; bad files are RecorderErrors."""
    world = CorridorWorld.from_config(dataclasses.replace(SMALL, twins=1), 9)
    (tmp_path / "w.json").write_text(world.to_json())
    again, config, seed = world_from_file(tmp_path / "w.json")
    assert seed == 9 and config == world.config and np.array_equal(again.panel_tiles, world.panel_tiles)
    assert np.array_equal(CorridorWorld.from_json(world.to_json()).walls, world.walls)
    (tmp_path / "s.json").write_text('{"seed": 2}')
    assert world_from_file(tmp_path / "s.json")[1] == CorridorConfig()
    (tmp_path / "bad.json").write_text('{"config": {}}')
    with pytest.raises(RecorderError, match="seed"):
        world_from_file(tmp_path / "bad.json")
    with pytest.raises(RecorderError, match="cannot read"):
        world_from_file(tmp_path / "none.json")
    (tmp_path / "unk.json").write_text('{"seed": 1, "config": {"colour": 3}}')
    with pytest.raises(RecorderError, match="colour"):
        world_from_file(tmp_path / "unk.json")


def test_texture_errors(tmp_path: Path) -> None:
    """A missing texture folder and one without images are RecorderErrors."""
    with pytest.raises(RecorderError, match="does not exist"):
        CorridorWorld.from_config(CorridorConfig(texture=str(tmp_path / "none")), 0)
    (tmp_path / "empty").mkdir()
    with pytest.raises(RecorderError, match="no readable images"):
        CorridorWorld.from_config(CorridorConfig(texture=str(tmp_path / "empty")), 0)


def test_config_validation() -> None:
    """Each config error names its field."""
    for kwargs, match in [({"image_width": 8}, "image_width"), ({"hfov_deg": 179.0}, "hfov_deg"),
                          ({"camera_height_m": 3.0}, "camera_height_m"), ({"corridor_width_m": 0.5}, "corridor_width"),
                          ({"route": "left,moon"}, "moon"), ({"laps": 0}, "laps"), ({"speed_mps": 0.0}, "speed_mps"),
                          ({"odom_rate_hz": 7.0}, "integer multiple"), ({"odom_sigma_m": -1.0}, "odom_sigma_m"),
                          ({"odom_wheel_ratio_error": 0.5}, "odom_wheel_ratio_error"),
                          ({"compression": "gif"}, "compression"), ({"plain_fraction": 2.0}, "plain_fraction"),
                          ({"laps": 1.5}, "laps"), ({"noise_sigma": float("nan")}, "noise_sigma")]:
        with pytest.raises(ValueError, match=match):
            CorridorConfig(**kwargs)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="must be finite|turns"):
        WheelOdometry(CorridorConfig(), np.random.default_rng(0)).step([0.1, 0.0, 4.0])


def test_cli_writes_a_readable_recording(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """`slamreplay record sim-corridor` writes a recording; a bad option is exit 2 with one line."""
    out = tmp_path / "cli.mcap"
    code = main(["record", "sim-corridor", "--out", str(out), "--seed", "2", "--route", "left", "--speed-mps", "1.0",
                 "--camera-rate-hz", "1", "--odom-rate-hz", "10", "--compression", "png"])
    err = capsys.readouterr().err
    assert code == 0 and "images" in err
    reader = RecordingReader(out)
    assert world_from_metadata(reader.info.metadata)[2] == 2
    images = [e.msg for e in reader.messages([TOPIC_CAMERA_IMAGE])]
    assert len(images) > 30 and all(isinstance(m, CameraImage) and m.compression == "png" for m in images)
    code = main(["record", "sim-corridor", "--out", str(tmp_path / "x.mcap"), "--hfov-deg", "200"])
    err = capsys.readouterr().err
    assert code == 2 and "hfov_deg" in err and not (tmp_path / "x.mcap").exists()
