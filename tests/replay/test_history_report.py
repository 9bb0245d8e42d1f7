"""History plots' y axes: padded around the data, never past a metric's registered least or greatest value."""

from __future__ import annotations

import re

import pytest

from slamreplay.replay.metric_registry import METRICS, MetricSpec, axis_bounds
from slamreplay.replay.runs.history_report import plot_svg, y_range


def test_y_range_known_answers() -> None:
    """NEES 0.5..170 and a count stuck at 0 start at 0, a fraction stops at 1, an unknown metric is padded as before;
    data past a bound (a bug the plot must show) are not cut."""
    assert y_range(0.5, 170.0, axis_bounds("landmark_nees_mean")) == pytest.approx((0.0, 170.0 + 0.08 * 169.5))
    assert y_range(0.0, 0.0, axis_bounds("false_landmarks")) == pytest.approx((0.0, 0.08))
    assert y_range(0.9, 1.0, axis_bounds("loop_closure_recall")) == pytest.approx((0.892, 1.0))
    assert y_range(0.5, 170.0, axis_bounds("a_plugins_metric")) == pytest.approx((0.5 - 13.56, 183.56))
    assert y_range(-2.0, 3.0, (0.0, 1.0)) == pytest.approx((-2.4, 3.4))
    assert axis_bounds("robot_ate_rmse_m") == (0.0, None)  # an old name: the registry's current one
    assert axis_bounds("robot2_nees_mean") == (0.0, None) and axis_bounds("mosaic_ncc") == (-1.0, 1.0)
    assert all(s.minimum is not None for s in METRICS.values())  # every built-in metric says where it starts
    with pytest.raises(ValueError, match="minimum must be below its maximum"):
        MetricSpec("lower", "", "x", minimum=1.0, maximum=1.0)


def test_plot_axis_labels_not_negative() -> None:
    """The plot of a NEES from 0.5 to 170 labels its axis from 0, and every point lies inside the plot."""
    values = [{0: 0.5, 1: 0.7}, {0: 170.0, 1: 160.0}, {0: 2.0}]
    svg = plot_svg(values, [], bounds=axis_bounds("landmark_nees_mean"))
    labels = re.findall(r"fill='#666'>([^<]*)</text>", svg)
    assert labels[-1] == "0" and not any(label.startswith("-") for label in labels)
    ys = [float(y) for y in re.findall(r"cy='([-\d.]+)'", svg)]
    assert ys and all(6 - 1e-9 <= y <= 90 - 6 + 1e-9 for y in ys)
    assert re.findall(r"fill='#666'>([^<]*)</text>", plot_svg(values, []))[-1].startswith("-")  # without bounds
