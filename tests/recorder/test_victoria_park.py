"""Victoria Park (iSAM form): parsing, the recording, scan merging, bad input; the real file where it is present."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from slamreplay.api.cli.command import main
from slamreplay.recorder.errors import RecorderError
from slamreplay.recorder.importers.victoria_park import read_victoria_park, sensor_model, write_victoria_park
from slamreplay.recorder.messages import GroundTruthPose, LandmarkMap, OdometryPose, RangeBearingScan
from slamreplay.replay.engine.reader import RecordingReader

REAL = Path(__file__).resolve().parents[3] / "shared" / "data" / "victoria-park-isam"
COV = "0.0001 0 0 4e-06 0 4e-06"
SMALL = f"""ODOMETRY 0 1 1.0 0 0 {COV}
LANDMARK 1 2 3.0 4.0 0.4 0 0.4
ODOMETRY 1 3 1.0 0 1.5707963267948966 {COV}
LANDMARK 3 2 4.0 -2.0 0.4 0 0.4
LANDMARK 3 4 0.0 5.0 0.4 0 0.4
ODOMETRY 3 5 2.0 0 0 {COV}
"""


def _small(tmp_path: Path) -> Path:
    (tmp_path / "victoria_park.txt").write_text(SMALL)
    return tmp_path


def test_parse_and_record(tmp_path: Path) -> None:
    """Non-contiguous ids numbered in order, odometry composed, points turned into range and bearing with ids."""
    data = read_victoria_park(_small(tmp_path))
    assert data.pose_ids.tolist() == [0, 1, 3, 5] and data.landmark_ids.tolist() == [2, 4]
    np.testing.assert_allclose(data.odometry_poses(), [[0, 0, 0], [1, 0, 0], [2, 0, math.pi / 2], [2, 2, math.pi / 2]],
                               atol=1e-12)
    ref = (data.odometry_poses(), np.array([[4.0, 4.0], [-3.0, 0.0]]))
    summary = write_victoria_park(data, tmp_path / "vp.mcap", reference=ref)
    assert (summary.poses, summary.scans, summary.observations, summary.landmarks) == (4, 2, 3, 2)
    msgs = [(e.topic, e.msg) for e in RecordingReader(tmp_path / "vp.mcap").messages()]
    assert isinstance(msgs[0][1], LandmarkMap) and msgs[0][1].landmark_ids.tolist() == [2, 4]
    odom = [m for _, m in msgs if isinstance(m, OdometryPose)]
    assert [o.stamp_ns for o in odom] == [0, 200_000_000, 400_000_000, 600_000_000]
    assert len([m for _, m in msgs if isinstance(m, GroundTruthPose)]) == 4
    scans = [m for _, m in msgs if isinstance(m, RangeBearingScan)]
    assert scans[0].stamp_ns == 200_000_000 and scans[0].landmark_ids.tolist() == [2]
    assert scans[0].ranges_m[0] == pytest.approx(5.0) and scans[0].bearings_rad[0] == pytest.approx(math.atan2(4, 3))
    assert scans[1].landmark_ids.tolist() == [2, 4] and scans[1].ranges_m[0] == pytest.approx(math.sqrt(20))
    assert scans[0].range_sigma_m == pytest.approx(sensor_model()["range_sigma_m"])


def test_merge_window_gathers_sightings_into_one_frame(tmp_path: Path) -> None:
    """With a 5 m window the three sightings become one scan at the last pose, each moved into its frame."""
    data = read_victoria_park(_small(tmp_path))
    write_victoria_park(data, tmp_path / "vp.mcap", merge_window_m=5.0)
    scans = [e.msg for e in RecordingReader(tmp_path / "vp.mcap").messages(["/landmarks/range_bearing"])]
    assert len(scans) == 1 and scans[0].stamp_ns == 2 * 200_000_000  # the last sighting, not the end of the file
    s = scans[0]
    # landmark 2 seen last from pose 3 at (4, -2); landmark 4 at (0, 5)
    assert s.landmark_ids.tolist() == [2, 4]
    np.testing.assert_allclose(s.ranges_m, [math.sqrt(20), 5.0])
    with pytest.raises(RecorderError, match="merge_window_m"):
        write_victoria_park(data, tmp_path / "x.mcap", merge_window_m=-1.0)


@pytest.mark.parametrize(("text", "match"), [
    ("ODOMETRY 0 1 1.0 0\n", "expected `ODOMETRY"),
    (f"ODOMETRY 0 1 1.0 nan 0 {COV}\n", "not finite"),
    (f"ODOMETRY 7 8 1.0 0 0 {COV}\n", "no earlier line reaches"),
    (f"ODOMETRY 0 1 1.0 0 0 {COV}\nODOMETRY 0 1 1.0 0 0 {COV}\n", "reached twice"),
    ("", "holds no ODOMETRY"),
    ("ODOMETRY 0 1 1.0 0 0 -1 0 0 4e-06 0 4e-06\n", "not positive definite"),
])
def test_bad_files(tmp_path: Path, text: str, match: str) -> None:
    """Each malformed file names the problem (with file and line where there is one)."""
    (tmp_path / "victoria_park.txt").write_text(text)
    with pytest.raises(RecorderError, match=match):
        read_victoria_park(tmp_path)


def test_cli_bad_folder_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A folder without the file: one line, exit 2, nothing written."""
    assert main(["record", "victoria-park", str(tmp_path), "--out", str(tmp_path / "vp.mcap")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "victoria_park.txt" in err
    assert not (tmp_path / "vp.mcap").exists()


@pytest.mark.skipif(not REAL.is_dir(), reason="../shared/data/victoria-park-isam is not beside the repository")
def test_real_file_statistics() -> None:
    """The shipped file: the counts and dead-reckoning end point its README states."""
    data = read_victoria_park(REAL)
    assert (len(data.pose_ids), len(data.odo_i), len(data.landmark_ids), len(data.obs_pose)) == (6969, 6968, 151, 3640)
    np.testing.assert_allclose(data.odometry_poses()[-1, :2], [-187.6, -102.3], atol=0.1)
    rb = data.ranges_bearings()
    assert rb[:, 0].min() > 4.5 and rb[:, 0].max() < 20.8


def test_cli_records_with_the_reference_as_ground_truth(tmp_path: Path) -> None:
    """`record victoria-park` on a small file: the reference (batch optimum) is the ground truth; exact
    measurements make it the odometry itself, and the measured noise is stored."""
    import json

    from mcap.reader import make_reader

    assert main(["record", "victoria-park", str(_small(tmp_path)), "--out", str(tmp_path / "vp.mcap"), "-q"]) == 0
    gt = [e.msg for e in RecordingReader(tmp_path / "vp.mcap").messages(["/ground_truth/pose"])]
    data = read_victoria_park(tmp_path)
    np.testing.assert_allclose([m.xy_yaw for m in gt], data.odometry_poses(), atol=1e-6)
    lm = next(RecordingReader(tmp_path / "vp.mcap").messages(["/ground_truth/landmarks"])).msg
    np.testing.assert_allclose(lm.positions_m, [[4.0, 4.0], [-3.0, 0.0]], atol=1e-6)
    with open(tmp_path / "vp.mcap", "rb") as f:
        meta = {m.name: m.metadata for m in make_reader(f).iter_metadata()}["slamreplay.recording"]
    assert "batch least-squares optimum" in json.loads(meta["source"])["ground_truth"]
    assert set(json.loads(meta["parameters"])["measured_noise"]) >= {"range_sigma_m", "bearing_sigma_rad"}
