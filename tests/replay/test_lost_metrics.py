"""A lost metric is a regression: diff, compare and history fail the gate when B stops reporting one A had."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import write_tiny_recording

from slamreplay.api.cli.command import main
from slamreplay.replay.metric_registry import LOST, METRICS, optional_reason
from slamreplay.replay.runs.changepoints import detect_changes
from slamreplay.replay.runs.compare import Side, compare, format_table
from slamreplay.replay.runs.diff import diff_runs
from slamreplay.replay.runs.diff import format_table as diff_table
from slamreplay.replay.runs.history import Commit, history_of_versions
from slamreplay.replay.runs.report import render_html, render_markdown
from slamreplay.replay.runs.run import run_recording

TRAJECTORY = ("ape_rmse_m", "ape_se2_rmse_m", "ape_rot_rmse_deg", "rpe_step_trans_rmse_m", "rpe_step_rot_rmse_deg")


@pytest.fixture(scope="module")
def good_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    tmp = tmp_path_factory.mktemp("lost")
    rec = write_tiny_recording(tmp / "r.mcap")
    return run_recording(rec, "ekfslam", tmp / "good", seed=1).run_dir


def _without(run: Path, dest: Path, names: tuple[str, ...]) -> Path:
    """A copy of ``run`` whose metrics.json lacks ``names`` (what a run that lost its time overlap reports)."""
    shutil.copytree(run, dest)
    doc = json.loads((dest / "metrics.json").read_text())
    for name in names:
        doc["metrics"].pop(name)
    (dest / "metrics.json").write_text(json.dumps(doc))
    return dest


def test_diff_names_lost_metrics_and_exits_1(good_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
                                             ) -> None:
    """Metrics in A and not in B: each WORSE (missing in B), in ``worse`` and ``lost``; the CLI exits 1."""
    present = set(json.loads((good_run / "metrics.json").read_text())["metrics"])
    gone = tuple(n for n in TRAJECTORY if n in present)
    assert len(gone) >= 3, f"ekfslam should report trajectory metrics, has {sorted(present)}"
    bad = _without(good_run, tmp_path / "bad", gone)
    d = diff_runs(good_run, bad, compare_rrd=False)
    assert sorted(d.lost) == sorted(gone)
    assert sorted(d.worse) == sorted(gone)
    assert all(m.verdict == LOST and m.note == "missing in B" for m in d.metrics if m.name in gone)
    text = diff_table(d)
    assert text.count("WORSE (missing in B)") == len(gone)
    assert f"Result: {len(gone)} metric(s) worse" in text
    assert main(["diff", str(good_run), str(bad)]) == 1
    out = capsys.readouterr().out
    assert all(name in out.splitlines()[-1] for name in gone)
    assert main(["diff", str(good_run), str(bad), "--json"]) == 1
    assert sorted(json.loads(capsys.readouterr().out)["lost"]) == sorted(gone)
    # the other way round a metric only B has is added, not worse
    back = diff_runs(bad, good_run, compare_rrd=False)
    assert not back.worse and {m.verdict for m in back.metrics if m.name in gone} == {"added"}


def test_an_optional_metric_may_be_left_out(good_run: Path, tmp_path: Path) -> None:
    """A metric the registry declares optional, left out by B: only in A, with the reason; the gate holds."""
    assert optional_reason("loop_closure_precision") and not optional_reason("ape_rmse_m")
    assert optional_reason("made_up", {"optional": "a plugin's reason"}) == "a plugin's reason"
    declared = [n for n, s in METRICS.items() if s.optional]
    assert "loop_closures_rejected" in declared and "landmark_rmse_m" not in declared
    b = tmp_path / "b"
    shutil.copytree(good_run, b)
    doc = json.loads((b / "metrics.json").read_text())
    a = tmp_path / "a"
    shutil.copytree(good_run, a)
    doc_a = json.loads((a / "metrics.json").read_text())
    doc_a["metrics"]["loop_closure_precision"] = {"value": 0.9, "better": "higher", "unit": "", "tolerance": 0.0}
    (a / "metrics.json").write_text(json.dumps(doc_a))
    (b / "metrics.json").write_text(json.dumps(doc))
    d = diff_runs(a, b, compare_rrd=False)
    (m,) = [m for m in d.metrics if m.name == "loop_closure_precision"]
    assert m.verdict == "removed" and "no loop closure" in m.note and not d.worse


def _rows(code: str, metrics: list[dict[str, float]], status: str = "succeeded") -> list[dict[str, Any]]:
    return [{"recording": "rec", "recording_seed": i + 1, "pipeline": "ext", "variant": "default", "seed": 0,
             "config": {}, "status": status, "error": None, "run_dir": f"/nowhere/{code}{i}", "code_version": code,
             "metrics": m, "better": {k: "lower" if k != "path_length_m" else "none" for k in m},
             "tolerance": {k: 1e-6 for k in m}, "units": {k: "m" for k in m}} for i, m in enumerate(metrics)]


GOOD = [{"ape_rmse_m": 0.015 + 0.001 * i, "path_length_m": 30.0} for i in range(3)]
LOSTROWS = [{"path_length_m": 30.0} for _ in range(3)]


def test_compare_calls_a_lost_metric_a_regression(tmp_path: Path) -> None:
    """compare: a metric every seed of A has and B has not is LOST, a regression in every output."""
    c = compare(Side("A", _rows("a", GOOD), "results", ["a"]), Side("B", _rows("b", LOSTROWS), "results", ["b"]))
    (r,) = [r for r in c.results if r.metric == "ape_rmse_m"]
    assert r.verdict == LOST and r.test == "missing in B (3 of 3 seeds)" and r.a_mean == pytest.approx(0.016)
    assert [x.metric for x in c.regressions] == ["ape_rmse_m"]
    assert "LOST" in format_table(c) and "Result: 1 regression(s)" in format_table(c)
    assert "lost** (missing in B)" in render_markdown(c, tmp_path)
    assert "<tr class='lost'>" in render_html(c, tmp_path)
    # lost on one seed of three is still lost
    partial = [GOOD[0], GOOD[1], LOSTROWS[2]]
    c2 = compare(Side("A", _rows("a", GOOD), "results", ["a"]), Side("B", _rows("b", partial), "results", ["b"]))
    assert [(r.metric, r.verdict, r.seeds) for r in c2.regressions] == [("ape_rmse_m", LOST, [[3, 0]])]


def test_history_flags_the_commit_that_lost_a_metric() -> None:
    """history: the commit where the cells still succeed but stop reporting a metric is a LOST change."""
    commits = [Commit(f"{k:040x}", f"2026-01-0{k}T00:00:00+00:00", f"c{k}", k) for k in range(1, 6)]
    versions = [(commits[0], _rows("c1", GOOD)), (commits[1], _rows("c2", GOOD)),
                (commits[2], _rows("c3", LOSTROWS)), (commits[3], _rows("c4", LOSTROWS)),
                (commits[4], _rows("c5", GOOD))]
    changes = detect_changes(history_of_versions(versions))
    lost = [ch for ch in changes if ch.verdict == LOST]
    assert [(ch.index, ch.metric, ch.mean_after) for ch in lost] == [(2, "ape_rmse_m", None)]
    assert lost[0].previous == commits[1].sha and lost[0].mean_before == pytest.approx(0.016)


def _noisy_rows(code: str, rng: np.random.Generator, scale: float = 1.0, seeds: int = 5) -> list[dict[str, Any]]:
    """A program that is not deterministic: eight correlated trajectory metrics, 5 % run-to-run noise."""
    base = {f"m{k}": 0.02 * (k + 1) for k in range(8)}
    rows = []
    for _ in range(seeds):
        shared = rng.normal(0.0, 0.04)
        rows.append({k: v * scale * (1 + shared + rng.normal(0.0, 0.03)) for k, v in base.items()})
    out = _rows(code, rows)
    for r in out:
        r["deterministic"] = False
        r["rel_tolerance"] = {k: 1e-3 for k in r["metrics"]}
    return out


def test_a_program_that_is_not_deterministic_is_judged_by_its_spread() -> None:
    """Unchanged code, 400 comparisons: at most ALPHA of them report a regression (Holm over the metrics; a test
    per metric alone would report about a fifth); a 30 % regression is still found; one seed gives no verdict."""
    rng = np.random.default_rng(7)
    alarms = sum(bool(compare(Side("A", _noisy_rows("a", rng), "results", ["a"]),
                              Side("B", _noisy_rows("b", rng), "results", ["b"])).regressions) for _ in range(400))
    assert alarms / 400 <= 0.07
    found = sum(bool(compare(Side("A", _noisy_rows("a", rng), "results", ["a"]),
                             Side("B", _noisy_rows("b", rng, 1.3), "results", ["b"])).regressions) for _ in range(50))
    assert found >= 45
    one = compare(Side("A", _noisy_rows("a", rng, seeds=1), "results", ["a"]),
                  Side("B", _noisy_rows("b", rng, 3.0, seeds=1), "results", ["b"]))
    assert not one.regressions and {r.verdict for r in one.results} == {"noise"}
    assert "no spread" in one.results[0].test and "not deterministic" in one.notes[0]


def test_a_run_that_lost_its_time_overlap_fails_and_diff_names_what_it_lost(
        good_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The reported case end to end: an estimate whose clock is 1000 s off fails its run (min_coverage), and
    diff GOOD BAD exits 1 naming every metric of A as missing in B, with B's one-line error."""
    from slamreplay.replay.errors import ReplayError
    from slamreplay.replay.runs.evaluate_run import evaluate_estimate

    rec = tmp_path / "r.mcap"
    write_tiny_recording(rec)
    good = run_recording(rec, "odometry", tmp_path / "odo").run_dir
    lines = []
    body = [ln for ln in (good / "trajectory.tum").read_text().splitlines() if not ln.startswith("#")]
    for line in body:
        t, *rest = line.split()
        lines.append(" ".join([f"{float(t) + 1000.0:.9f}", *rest]))
    (tmp_path / "late.tum").write_text("\n".join(lines) + "\n")
    with pytest.raises(ReplayError, match="time span"):
        evaluate_estimate(tmp_path / "late.tum", rec, tmp_path / "late")
    early = "\n".join(" ".join([f"{float(ln.split()[0]) + 2.0:.9f}", *ln.split()[1:]])
                      for ln in body) + "\n"
    (tmp_path / "early.tum").write_text(early)
    with pytest.raises(ReplayError, match=r"the estimate covers .* min_coverage"):
        evaluate_estimate(tmp_path / "early.tum", rec, tmp_path / "bad", min_coverage=0.99)
    d = diff_runs(good, tmp_path / "bad", compare_rrd=True)
    assert "ape_rmse_m" in d.lost and set(d.lost) == set(d.worse)
    assert d.rrd_equal is None and "did not succeed" in d.rrd_detail
    assert main(["diff", str(good), str(tmp_path / "bad")]) == 1
    out = capsys.readouterr().out
    assert "note: run B failed: " in out and "WORSE (missing in B)" in out
    with pytest.raises(ReplayError, match="did not succeed"):  # a baseline that failed is still bad input
        diff_runs(tmp_path / "bad", good)
