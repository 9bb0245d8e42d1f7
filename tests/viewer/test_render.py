"""Runs drawn by the real Rerun viewer (headless, Mesa's software Vulkan): orientation read off the pixels,
and no view of any pipeline blank at the end of a run. Needs Debian packages: run by `make test-viewer`."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import psutil
import pytest

from slamreplay.algorithms.observe import LineStrips
from slamreplay.api.cli.command import main as cli
from slamreplay.replay.engine import views
from slamreplay.replay.engine.observer import RerunObserver
from slamreplay.replay.errors import ReplayError
from slamreplay.replay.tools.snapshot import check_graphics, snapshot
from tests.replay.view_runs import make_runs

pytestmark = pytest.mark.viewer


@pytest.fixture(scope="module", autouse=True)
def graphics() -> None:
    try:
        check_graphics()
    except ReplayError as err:
        pytest.skip(f"no Vulkan driver for the headless viewer ({err}); `make test-viewer` installs one")


def mask_of(img: np.ndarray, rgb: tuple[int, int, int], tol: int = 40) -> np.ndarray:
    bgr = np.array(rgb[::-1], dtype=int)
    return np.all(np.abs(img.astype(int) - bgr) <= tol, axis=2)


def test_world_is_right_handed_on_screen(tmp_path: Path) -> None:
    """An L in the world: +x arm (blue, 4 m) points right and +y arm (green, 2 m) points up on the PNG."""
    rrd = tmp_path / "l.rrd"
    obs = RerunObserver(rrd, "orientation", kind="test")
    obs.set_time(0, 0)
    obs.log("world/trajectory/estimate", LineStrips((np.array([[0.0, 0.0], [4.0, 0.0]]),)))
    obs.log("world/graph/loops", LineStrips((np.array([[0.0, 0.0], [0.0, 2.0]]),)))
    bounds = obs.write_summary("### orientation\n")
    obs.send_layout(views.layout(views.tab("Map", views.map_view("Map", "world", bounds))))
    obs.close()
    (shot,) = snapshot(rrd, tmp_path / "png", size=(800, 600))
    img = cv2.imread(str(shot.path))
    blue, green = mask_of(img, views.ESTIMATE), mask_of(img, views.ACCEPTED)
    assert blue.sum() > 200 and green.sum() > 100
    by, bx = np.nonzero(blue)
    gy, gx = np.nonzero(green)
    assert np.ptp(bx) > 3 * np.ptp(by)  # the x arm is horizontal
    assert np.ptp(gy) > 3 * np.ptp(gx)  # the y arm is vertical
    corner_x, corner_y = gx.mean(), gy.max()  # the y arm starts at the corner and goes up (rows decrease)
    assert bx.mean() > corner_x + 50 and abs(by.mean() - corner_y) < 15


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    return make_runs(tmp_path_factory.mktemp("render"))


@pytest.mark.parametrize("pipeline", ["odometry", "dslam", "ekfslam", "slsjf", "ifmi", "topometric", "topometric-nav"])
def test_no_view_is_blank_at_the_end(runs: dict[str, Path], pipeline: str, tmp_path: Path) -> None:
    """Every view of every tab draws something (more than 0.3 % of its pixels off its background)."""
    shots = snapshot(runs[pipeline], tmp_path, size=(1280, 720), per_view=True)
    tabs = [s for s in shots if " / " not in s.tab]
    assert tabs[0].tab == "Summary" and len(tabs) >= 2
    for shot in shots:
        img = cv2.imread(str(shot.path))
        assert img is not None and img.shape[0] > 50
        background = np.median(img.reshape(-1, 3), axis=0)
        busy = np.mean(np.max(np.abs(img.astype(int) - background), axis=2) > 30)
        assert busy > 0.003, f"{pipeline}: {shot.tab} looks blank ({busy:.4f} of its pixels drawn)"


def test_snapshot_cli_and_bad_input(runs: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
                                    ) -> None:
    """The command writes one PNG per tab; bad arguments are one-line errors with exit 2."""
    assert cli(["snapshot", str(runs["odometry"]), "--out", str(tmp_path / "s"), "--size", "961x541"]) == 0
    assert sorted(p.name for p in (tmp_path / "s").glob("*.png")) == ["01-summary.png", "02-map-over-time.png",
                                                                       "03-data.png"]
    left = [p for p in psutil.process_iter(["cmdline"]) if "961x541" in " ".join(p.info["cmdline"] or [])]
    assert not left, "the headless viewer (and its child binary) must be gone after a snapshot"
    assert cli(["snapshot", str(runs["odometry"]), "--out", str(tmp_path / "t"), "--at", "99999999"]) == 2
    assert "the run's steps are" in capsys.readouterr().err
