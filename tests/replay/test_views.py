"""What a run's ``.rrd`` shows: right-handed map roots, the static summary, a filled view for every
part of every pipeline's layout, per-pipeline application ids, and the diff's overlay."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from rerun.chunk import RrdReader

from slamreplay.replay.engine import views
from slamreplay.replay.engine.pipeline import get_pipeline
from slamreplay.replay.errors import ReplayError
from slamreplay.replay.runs.diff_view import _RunContent, first_divergence, write_comparison_rrd
from tests.replay.view_runs import blueprint_views, matches, rrd_entities

pytestmark = pytest.mark.slow
PIPELINES = ("odometry", "dslam", "ekfslam", "slsjf", "ifmi", "topometric", "topometric-nav")


@pytest.fixture(scope="module")
def runs(pipeline_runs: dict[str, Path]) -> dict[str, Path]:
    return pipeline_runs


def test_role_colors_follow_the_palette() -> None:
    """Truth grey, estimate blue, dead reckoning orange, accepted green, rejected red; first match wins."""
    assert views.role_color("world/trajectory/truth") == views.TRUTH
    assert views.role_color("world/robot_truth") == views.TRUTH
    assert views.role_color("world/robot/prediction") == views.DEAD_RECKONING
    assert views.role_color("world/trajectory/odometry") == views.DEAD_RECKONING
    assert views.role_color("world/trajectory/estimate") == views.ESTIMATE
    assert views.role_color("camera/candidate/inliers") == views.ACCEPTED
    assert views.role_color("camera/candidate/outliers") == views.REJECTED
    assert views.role_color("world/graph/after/edges/rejected") == views.REJECTED
    assert views.role_color("metrics/nees_band/robot_95_low") == views.TRUTH
    # a multi-robot run: robot N's estimate in robot N's colour (as its series), its truth grey
    assert views.role_color("world/robots/robot1") == views.ESTIMATE
    assert views.role_color("world/robots/robot3/covariance") == views.ROBOT_COLORS[2]
    assert views.role_color("world/trajectory/robot2/estimate/tail") == views.ROBOT_COLORS[1]
    assert views.role_color("world/trajectory/robot2/truth") == views.TRUTH
    assert views.role_color("world/trajectory/robot2/odometry") == views.DEAD_RECKONING
    assert views.series_color("metrics/robot2_position_error_m") == views.ROBOT_COLORS[1]
    assert views.role_color("runs/A/world/trajectory/estimate") == views.RUN_A
    assert views.role_color("world/nav/global_path") == views.ACCEPTED
    assert views.role_color("world/map/edges") == views.MAP_PRIOR
    assert views.role_color("ifmi/pnr") is None
    assert views.series_color("ifmi/pnr") == views.series_color("ifmi/pnr")  # stable


def test_visual_bounds_flip_y_and_pad() -> None:
    """The world box (x 0..10, y 2..4) becomes a 2D-view box with y negated, padded by 6 % of the larger side."""
    b = views.extend_bounds(None, np.array([[0.0, 2.0], [10.0, 4.0], [np.nan, 100.0]]))
    assert b == (0.0, 10.0, 2.0, 4.0)
    vb = views.visual_bounds(b)
    assert vb is not None and views.visual_bounds(None) is None
    box = vb.range.as_arrow_array().to_pylist()[0]
    assert np.allclose(box["x_range"], [-0.6, 10.6]) and np.allclose(box["y_range"], [-4.6, -1.4])


@pytest.mark.parametrize("pipeline", PIPELINES)
def test_every_view_holds_data_and_the_summary_is_static(runs: dict[str, Path], pipeline: str) -> None:
    """Each view of the layout matches an entity with data; summary entities are static; map roots are flipped."""
    rrd = runs[pipeline] / "run.rrd"
    entities = rrd_entities(rrd)
    steps = [e["last_step"] for e in entities.values() if e["last_step"] is not None]
    assert steps, "the run logged nothing over time"
    for root in views.MAP_ROOTS:
        assert "Transform3D:scale" in entities[f"/{root}"]["columns"] and entities[f"/{root}"]["static"]
    summary = {p: e for p, e in entities.items() if p.startswith("/summary/")}
    assert "/summary/metrics" in summary and any(p.startswith("/summary/world/") for p in summary)
    assert all(e["static"] and e["last_step"] is None for e in summary.values())
    layout = get_pipeline(pipeline).blueprint(None)
    tabs = blueprint_views(layout)
    assert tabs[0][0] == "Summary"
    for tab, view, patterns in tabs:
        shown = [p for p, e in entities.items()
                 if any(matches(pat, p) for pat in patterns if not pat.startswith("-"))
                 and (e["static"] or e["last_step"] is not None) and e["columns"] - {"Transform3D:scale"}]
        assert shown, f"{pipeline}: view {view!r} of tab {tab!r} shows nothing ({patterns})"


def test_series_are_named_and_on_the_replay_timeline(runs: dict[str, Path]) -> None:
    """Every metrics series has a static legend name; the cross-track series uses replay steps, not 0..n-1."""
    entities = rrd_entities(runs["topometric-nav"] / "run.rrd")
    xt = entities["/metrics/cross_track_error_m"]
    assert "SeriesLines:names" in xt["columns"] and "Scalars:scalars" in xt["columns"]
    ground_truth_steps = []
    for ch in RrdReader(runs["topometric-nav"] / "run.rrd").stream():
        if str(ch.entity_path) == "/metrics/cross_track_error_m" and not ch.is_static:
            ground_truth_steps += ch.to_record_batch().column("step").to_pylist()
    assert len(ground_truth_steps) > 10
    assert ground_truth_steps[-1] > 2 * len(ground_truth_steps)  # images and odometry interleave: steps skip


def test_sensor_time_is_relative_to_the_recording_start(runs: dict[str, Path]) -> None:
    """sensor_time is a duration from the first message (sim recordings start at 1 s of epoch time)."""
    t = [x for ch in RrdReader(runs["odometry"] / "run.rrd").stream()  # every chunk: the rows come in several
         if str(ch.entity_path) == "/world/robot" and not ch.is_static
         for x in ch.to_record_batch().column("sensor_time").to_pylist()]
    if not t:
        pytest.fail("no /world/robot data")
    assert min(t).total_seconds() < 1.0 and 55.0 < max(t).total_seconds() < 62.0


def test_application_id_is_per_pipeline(runs: dict[str, Path]) -> None:
    """Runs of different pipelines carry different application ids (their layouts never collide)."""
    raw = {name: (runs[name] / "run.rrd").read_bytes() for name in ("dslam", "ifmi")}
    assert views.app_id("dslam").encode() in raw["dslam"] and views.app_id("ifmi").encode() in raw["ifmi"]
    assert views.app_id("ifmi").encode() not in raw["dslam"]


def test_diff_rrd_overlays_both_runs(runs: dict[str, Path], tmp_path: Path) -> None:
    """The comparison file holds A and B recoloured, one plot per series with both, and a delta table."""
    out = tmp_path / "cmp.rrd"
    write_comparison_rrd(runs["dslam"], runs["ekfslam"], out)
    entities = rrd_entities(out)
    assert {"/runs/A/summary/world/trajectory/estimate", "/runs/B/summary/world/trajectory/estimate"} <= set(entities)
    assert "/diff/summary" in entities and entities["/diff/summary"]["static"]
    text = next(ch.to_record_batch().column("TextDocument:text").to_pylist()[0][0]
                for ch in RrdReader(out).stream() if str(ch.entity_path) == "/diff/summary")
    assert "| `landmark_rmse_m` |" in text and "#### What changed" in text and "`pipeline`" in text
    assert "#### First divergence" in text and "step " in text
    with pytest.raises(ReplayError, match="already exists"):
        write_comparison_rrd(runs["dslam"], runs["ekfslam"], out)
    with pytest.raises(ReplayError, match="has no run.rrd"):
        write_comparison_rrd(tmp_path, runs["ekfslam"], tmp_path / "x.rrd")
    assert not (tmp_path / "x.rrd").exists() and not (tmp_path / ".x.rrd.partial").exists()


def test_first_divergence_of_a_run_with_itself_is_none(runs: dict[str, Path]) -> None:
    """The same run read twice never diverges; two different pipelines diverge at the first scan."""
    def content(run: Path) -> _RunContent:
        c = _RunContent()
        for ch in RrdReader(run / "run.rrd").stream():
            c.see(ch)
        return c

    a = content(runs["dslam"])
    assert first_divergence(a, content(runs["dslam"])) is None
    where = first_divergence(a, content(runs["ekfslam"]))
    assert where is not None and where[0] >= 0
