"""The metric registry: one definition per metric, one name per number, NEES judged by its distance from
consistency, and the names of earlier versions still readable."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import pytest

from slamreplay.api.cli.command import main
from slamreplay.replay.engine.pipeline import pipeline_plugins
from slamreplay.replay.evaluation.score import metric_specs
from slamreplay.replay.metric_registry import (
    METRICS,
    RENAMED,
    MetricSpec,
    current_name,
    normalize,
    spec,
    target_distance,
)
from slamreplay.replay.runs.compare import Side, compare
from slamreplay.replay.runs.diff import diff_runs, judge_metric
from slamreplay.replay.runs.suite_run import normalized_row

GOLDEN = Path(__file__).parent.parent / "golden"


def builtin_pipelines() -> dict[str, Any]:
    return {n: p.load() for n, p in pipeline_plugins().items() if p.origin == "built-in"}


def test_every_builtin_metric_is_the_registry_s() -> None:
    """Each built-in pipeline's metric specs are the registry's, so no metric is defined twice."""
    for name, cls in builtin_pipelines().items():
        for metric, s in metric_specs(cls).items():
            assert s == spec(metric), f"{name}: {metric} is defined outside the registry"


@pytest.mark.parametrize("path", sorted(GOLDEN.glob("*_metrics.json")), ids=lambda p: p.stem)
def test_no_two_measured_metrics_of_a_run_are_the_same_number(path: Path) -> None:
    """The golden runs: no two measured (floating-point) metrics hold the same value; counts may coincide."""
    doc = json.loads(path.read_text())["metrics"]
    measured = {k: v["value"] for k, v in doc.items() if v["rel_tolerance"] > 0}
    names = sorted(measured)
    same = {(a, b) for i, a in enumerate(names) for b in names[i + 1:]
            if math.isclose(measured[a], measured[b], rel_tol=1e-9, abs_tol=1e-12)}
    # equal by the data, not by definition: dead reckoning's error grows steadily on that recording
    assert same - {("robot_final_error_m", "robot_max_error_m")} == set()


def test_old_names_are_gone_from_the_registry_and_map_onto_current_ones() -> None:
    """No renamed or retired name is registered; each maps onto a registered metric (robot numbers kept)."""
    for old, new in RENAMED.items():
        assert old not in METRICS
        spec(new.replace("{k}", "2"))
    assert current_name("robot_ate_rmse_m") == "ape_rmse_m"
    assert current_name("robot4_ate_rmse_m") == "robot4_ape_rmse_m"
    assert current_name("landmark_rmse_m") == "landmark_rmse_m"
    assert "ape_origin_rmse_m" not in METRICS


def test_target_distance_is_symmetric_on_a_log_scale() -> None:
    """Twice too confident and twice too cautious are equally far from consistent; zero is infinitely far."""
    assert target_distance(2.0, 2.0) == 0.0
    assert target_distance(4.0, 2.0) == pytest.approx(target_distance(1.0, 2.0)) == pytest.approx(math.log(2))
    assert target_distance(0.0, 2.0) == math.inf


def test_a_target_needs_better_target() -> None:
    """A spec with a target and another direction (or a target direction without a value) is refused."""
    with pytest.raises(ValueError, match="target"):
        MetricSpec("lower", "", "x", target=2.0)
    with pytest.raises(ValueError, match="target"):
        MetricSpec("target", "", "x")
    with pytest.raises(ValueError, match="> 0"):
        MetricSpec("target", "", "x", target=0.0)


NEES = {"tolerance": 1e-6, "rel_tolerance": 1e-3, "target": 2.0}


@pytest.mark.parametrize(("a", "b", "verdict"), [
    (1.55, 380.8, "worse"),  # 190 times overconfident: the case the issue found passing the gate
    (2.0, 0.5, "worse"),  # four times too cautious is worse too
    (2.5, 2.1, "better"),
    (0.8, 1.9, "better"),
    (1.0, 4.0, "changed"),  # as far off on the other side
    (2.0, 2.0001, "same"),  # within the tolerance
])
def test_diff_judges_a_nees_by_its_distance_from_its_target(a: float, b: float, verdict: str) -> None:
    """``diff``'s rule on a NEES (target 2): further from 2, either way, is worse."""
    assert judge_metric(a, b, "target", NEES)[2] == verdict


def nees_rows(values: list[float], code: str, rmse: float = 0.05) -> list[dict[str, Any]]:
    return [{"recording": "landmarks", "recording_seed": i + 1, "pipeline": "dslam", "variant": "default",
             "seed": 0, "config": {}, "status": "succeeded", "error": None, "run_dir": f"/tmp/runs/{code}{i}",
             "code_version": code, "metrics": {"landmark_nees_mean": v, "landmark_rmse_m": rmse},
             "better": {"landmark_nees_mean": "target", "landmark_rmse_m": "lower"},
             "targets": {"landmark_nees_mean": 2.0}, "tolerance": {"landmark_nees_mean": 1e-6, "landmark_rmse_m": 1e-6},
             "rel_tolerance": {"landmark_nees_mean": 1e-3, "landmark_rmse_m": 1e-3},
             "units": {"landmark_nees_mean": "", "landmark_rmse_m": "m"}} for i, v in enumerate(values)]


def test_compare_calls_an_overconfident_filter_a_regression() -> None:
    """Three seeds whose NEES goes from about 2 to about 40 (the estimates unchanged): a regression, and the
    way back is an improvement."""
    a, b = nees_rows([1.7, 2.3, 1.9], "a"), nees_rows([35.0, 52.0, 41.0], "b")
    c = compare(Side("A", a, "results", ["a"]), Side("B", b, "results", ["b"]))
    verdicts = {r.metric: r.verdict for r in c.results}
    assert verdicts == {"landmark_nees_mean": "regression", "landmark_rmse_m": "unchanged"}
    assert next(r for r in c.results if r.metric == "landmark_nees_mean").direction == "~2"
    back = compare(Side("B", b, "results", ["b"]), Side("A", a, "results", ["a"]))
    assert {r.metric: r.verdict for r in back.results}["landmark_nees_mean"] == "improvement"


def test_compare_calls_an_overcautious_filter_a_regression() -> None:
    """NEES from about 2 to about 0.2 (ten times too cautious): also a regression."""
    a, b = nees_rows([1.7, 2.3, 1.9], "a"), nees_rows([0.21, 0.18, 0.25], "b")
    c = compare(Side("A", a, "results", ["a"]), Side("B", b, "results", ["b"]))
    assert [r.metric for r in c.regressions] == ["landmark_nees_mean"]


def write_results(out: Path, rows: list[dict[str, Any]]) -> Path:
    out.mkdir()
    (out / "results.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    return out


def test_compare_cli_exits_1_on_a_nees_only_regression(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """`slamreplay compare A B` over two results directories that differ only in the NEES: exit 1, naming it."""
    a = write_results(tmp_path / "a", nees_rows([1.7, 2.3, 1.9], "a"))
    b = write_results(tmp_path / "b", nees_rows([35.0, 52.0, 41.0], "b"))
    assert main(["compare", str(a), str(b)]) == 1
    out = capsys.readouterr().out
    assert "landmark_nees_mean" in out and "REGRESSION" in out


# A row of results.jsonl as slamreplay 0.x wrote it before the registry (from a real dslam run of the golden
# test): three names for the ATE, the NEES without a direction.
OLD_ROW: dict[str, Any] = {
    "recording": "landmarks", "recording_seed": 1, "pipeline": "dslam", "variant": "default", "seed": 0,
    "config": {}, "status": "succeeded", "error": None, "run_dir": "/tmp/runs/old", "code_version": "5358294",
    "metrics": {"ape_origin_rmse_m": 0.028813122158333503, "ape_rmse_m": 0.02881312215833354,
                "robot_ate_rmse_m": 0.02881312215833354, "landmark_nees_mean": 1.7045826700641027,
                "landmark_rmse_m": 0.02395124414952395},
    "better": {"ape_origin_rmse_m": "lower", "ape_rmse_m": "lower", "robot_ate_rmse_m": "lower",
               "landmark_nees_mean": "none", "landmark_rmse_m": "lower"},
    "tolerance": dict.fromkeys(("ape_origin_rmse_m", "ape_rmse_m", "robot_ate_rmse_m", "landmark_nees_mean",
                                "landmark_rmse_m"), 1e-6),
    "rel_tolerance": dict.fromkeys(("ape_origin_rmse_m", "ape_rmse_m", "robot_ate_rmse_m", "landmark_nees_mean",
                                    "landmark_rmse_m"), 1e-3),
    "units": {"ape_origin_rmse_m": "m", "ape_rmse_m": "m", "robot_ate_rmse_m": "m", "landmark_nees_mean": "",
              "landmark_rmse_m": "m"},
}


def test_a_results_file_of_the_previous_version_reads_under_the_current_names(tmp_path: Path) -> None:
    """An old results.jsonl compares with a new one: one ATE, the NEES judged by its target, nothing missing."""
    row = normalized_row(OLD_ROW)
    assert sorted(row["metrics"]) == ["ape_rmse_m", "landmark_nees_mean", "landmark_rmse_m"]
    assert (row["better"]["landmark_nees_mean"], row["targets"]["landmark_nees_mean"]) == ("target", 2.0)
    old = write_results(tmp_path / "old", [OLD_ROW])
    new_row = {**OLD_ROW, "code_version": "new", "metrics": {"ape_rmse_m": 0.0288, "landmark_nees_mean": 60.0,
                                                             "landmark_rmse_m": 0.0240}}
    new_row = {**new_row, **{k: {m: v for m, v in OLD_ROW[k].items() if m in new_row["metrics"]}
                             for k in ("better", "tolerance", "rel_tolerance", "units")}}
    new = write_results(tmp_path / "new", [normalized_row(new_row)])
    from slamreplay.replay.runs.compare import load_side
    c = compare(load_side(old), load_side(new))
    verdicts = {r.metric: r.verdict for r in c.results}
    assert set(verdicts) == {"ape_rmse_m", "landmark_nees_mean", "landmark_rmse_m"}
    assert verdicts["landmark_nees_mean"] == "regression"  # one seed: the tolerance decides


def test_an_old_run_directory_diffs_against_a_new_one(tmp_path: Path) -> None:
    """An old run's metrics.json (three ATE names, NEES without a direction) diffs with no 'removed' metric."""
    entries = {name: {"value": OLD_ROW["metrics"][name], "better": OLD_ROW["better"][name], "unit": "m",
                      "tolerance": 1e-6, "rel_tolerance": 1e-3} for name in OLD_ROW["metrics"]}
    assert sorted(normalize(entries)) == ["ape_rmse_m", "landmark_nees_mean", "landmark_rmse_m"]
    runs = []
    for name, doc in (("old", entries), ("new", normalize(entries))):
        d = tmp_path / name
        d.mkdir()
        (d / "manifest.json").write_text(json.dumps({"status": "succeeded", "pipeline": "dslam"}))
        (d / "metrics.json").write_text(json.dumps({"format": 1, "pipeline": "dslam", "metrics": doc}))
        runs.append(d)
    d = diff_runs(*runs, compare_rrd=False)
    assert {m.name: m.verdict for m in d.metrics} == dict.fromkeys(
        ("ape_rmse_m", "landmark_nees_mean", "landmark_rmse_m"), "same")


def test_an_overconfident_ekf_is_worse_on_its_nees_alone(tmp_path: Path) -> None:
    """Known answer: scaling every noise sigma an EKF assumes by k leaves its estimates unchanged (the gain is
    invariant to a common scale of all variances) and scales its NEES by 1/k^2. With k = 0.3, `diff` finds
    exactly the two NEES worse (about 11 times the consistent run's) and every error metric the same."""
    from slamreplay.recorder.sim import LandmarkSimConfig, simulate_landmarks
    from slamreplay.replay.runs.run import run_recording

    rec = tmp_path / "sim.mcap"
    simulate_landmarks(rec, LandmarkSimConfig(duration_s=40.0), seed=1)
    a = run_recording(rec, "ekfslam", tmp_path / "a").run_dir
    k = 0.3
    model = {"translation_sigma_per_sqrt_m": 0.02 ** 0.5 / 10, "heading_sigma_per_sqrt_m": 0.02 ** 0.5 / 10,
             "range_sigma_m": 0.05, "bearing_sigma_rad": math.radians(1.0)}  # the simulator's (inspect shows it)
    b = run_recording(rec, "ekfslam", tmp_path / "b", config={key: k * v for key, v in model.items()}).run_dir
    d = diff_runs(a, b, compare_rrd=False)
    assert sorted(d.worse) == ["landmark_nees_mean", "robot_nees_mean"]
    assert {m.verdict for m in d.metrics if m.name not in d.worse} == {"same"}
    for m in d.metrics:
        if m.name in d.worse:
            assert m.a is not None and m.b is not None
            assert 0.8 / k**2 < m.b / m.a < 1.2 / k**2
