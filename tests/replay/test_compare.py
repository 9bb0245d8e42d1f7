"""Compare: regressions told from seed noise (known answers), reports, and error paths."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from slamreplay.replay.errors import ReplayError
from slamreplay.replay.runs.compare import Side, compare, judge, paired_test
from slamreplay.replay.runs.report import write_reports


def rows(values: list[float], *, metric: str = "landmark_rmse_m", better: str = "lower", tol: float = 1e-9,
         pipeline: str = "dslam", status: str = "succeeded", code: str = "a") -> list[dict[str, Any]]:
    return [{"recording": "landmarks", "recording_seed": i + 1, "pipeline": pipeline, "variant": "default",
             "seed": 0, "config": {}, "status": status, "error": None if status == "succeeded" else "boom",
             "run_dir": f"/tmp/runs/{code}{i}", "code_version": code,
             "metrics": {metric: v} if status == "succeeded" else {}, "better": {metric: better},
             "tolerance": {metric: tol}, "units": {metric: "m"}} for i, v in enumerate(values)]


def side(label: str, r: list[dict[str, Any]]) -> Side:
    return Side(label, r, "results", [label])


A = [0.050, 0.080, 0.060]


def test_identical_is_unchanged() -> None:
    """Identical A and B: p = 1, unchanged, no regression."""
    c = compare(side("A", rows(A)), side("B", rows(A, code="b")))
    (r,) = c.results
    assert (r.verdict, r.p_value, r.delta) == ("unchanged", 1.0, 0.0)
    assert not c.regressions


def test_clear_degradation_over_three_seeds_is_a_regression() -> None:
    """Every seed ~50 % worse with little scatter in the shift: significant and beyond tolerance."""
    b = [0.075, 0.121, 0.089]
    c = compare(side("A", rows(A)), side("B", rows(b, code="b")))
    (r,) = c.results
    assert r.verdict == "regression" and r.p_value is not None and r.p_value < 0.05
    assert r.delta == pytest.approx(sum(b) / 3 - sum(A) / 3)
    assert [x.metric for x in c.regressions] == ["landmark_rmse_m"]


def test_same_improvement_is_green() -> None:
    """The mirror image of a regression is an improvement."""
    c = compare(side("A", rows([0.075, 0.121, 0.089])), side("B", rows(A, code="b")))
    assert c.results[0].verdict == "improvement" and not c.regressions


def test_seed_noise_is_not_a_regression() -> None:
    """B worse on average but the sign flips across seeds: noise, not a regression."""
    b = [0.070, 0.068, 0.075]  # +0.020, -0.012, +0.015
    c = compare(side("A", rows(A)), side("B", rows(b, code="b")))
    (r,) = c.results
    assert r.delta is not None and r.delta > 0 and r.p_value is not None and r.p_value > 0.05
    assert r.verdict == "noise" and not c.regressions


def test_constant_shift_and_tolerance() -> None:
    """A deterministic shift has p = 0; within tolerance it is unchanged; higher-is-better flips the sign."""
    assert paired_test([1, 2, 3], [1.5, 2.5, 3.5])[0] == 0.0
    assert judge([1, 2, 3], [1.5, 2.5, 3.5], "lower", 0.0)[4] == "regression"
    assert judge([1, 2, 3], [1.5, 2.5, 3.5], "lower", 0.0, "1")[4] == "unchanged"
    assert judge([1, 2, 3], [1.5, 2.5, 3.5], "lower", 0.0, "30%")[4] == "unchanged"
    assert judge([1, 2, 3], [1.5, 2.5, 3.5], "lower", 0.0, "20%")[4] == "regression"
    assert judge([1, 2, 3], [1.5, 2.5, 3.5], "higher", 0.0)[4] == "improvement"
    assert judge([1, 2, 3], [1.5, 2.5, 3.5], "none", 0.0)[4] == "changed"


def test_one_seed_falls_back_to_tolerance() -> None:
    """With one pair the verdict is the tolerance's, as `diff` judges it."""
    tol, delta, p, test, verdict = judge([1.0], [1.2], "lower", 0.1)
    assert (tol, delta) == (0.1, pytest.approx(0.2))
    assert (p, verdict, test) == (None, "regression", "tolerance (one seed)")
    assert judge([1.0], [1.05], "lower", 0.1)[4] == "unchanged"


def test_failed_in_b_is_a_regression() -> None:
    """A cell that ran in A and failed in B counts as a regression."""
    c = compare(side("A", rows(A)), side("B", rows(A, status="failed", code="b")))
    assert [r.verdict for r in c.regressions] == ["failed"]
    assert {f["side"] for f in c.failures} == {"B"}


def test_failed_in_both_fails_the_gate() -> None:
    """A cell that fails in A and in B compares nothing: the gate still fails (every cell broken on both sides once
    gave "0 regression(s)", exit 0), its row saying that A failed too; a failure in A alone is not B's fault."""
    from slamreplay.replay.runs.compare import RUN_STATUS_BOTH

    c = compare(side("A", rows(A, status="failed")), side("B", rows(A, status="failed", code="b")))
    assert [(r.metric, r.verdict, len(r.seeds)) for r in c.regressions] == [(RUN_STATUS_BOTH, "failed", len(A))]
    assert {f["side"] for f in c.failures} == {"A", "B"}
    assert compare(side("A", rows(A, status="failed")), side("B", rows(A, code="b"))).regressions == []


def test_no_cell_in_common_and_unknown_tolerance() -> None:
    """Two results with nothing to match, or a tolerance for no metric: ReplayError."""
    with pytest.raises(ReplayError, match=r"no cell in common"):
        compare(side("A", rows(A)), side("B", rows(A, pipeline="odometry")))
    with pytest.raises(ReplayError, match=r"--tolerance names unknown metrics: nope"):
        compare(side("A", rows(A)), side("B", rows(A)), {"nope": "1"})


def test_reports(tmp_path: Path) -> None:
    """HTML: one self-contained file with the regression row red and an SVG; markdown: the table."""
    c = compare(side("A", rows(A + [0.07])), side("B", rows([0.075, 0.121, 0.089, 0.1], code="b")))
    c.commits = ["abc1234 degrade ranges"]
    html, md = tmp_path / "r.html", tmp_path / "s.md"
    write_reports(c, html, md)
    text = html.read_text()
    assert "<tr class='regression'>" in text and "tr.regression" in text and "#fde0e0" in text
    assert "<svg" in text and "abc1234 degrade ranges" in text
    assert "http://" not in text.replace('xmlns="http://www.w3.org/2000/svg"', "")
    assert "https://" not in text
    summary = md.read_text()
    assert "| landmarks/dslam/default | landmark_rmse_m |" in summary
    assert "🔴 **regression**" in summary and "1 regression(s)" in summary
    assert not list(tmp_path.glob(".*.tmp"))


def test_pair_rrds_are_written_once_and_linked(tmp_path: Path) -> None:
    """--rrd-dir: one file per succeeded A/B pair (same seeds), linked relative to each report."""
    from slamreplay.replay.runs.report import pair_file_links, write_pair_rrds

    a = rows(A)
    b = rows([0.075, 0.121, 0.089], code="b")
    b[2]["status"] = "failed"
    c = compare(side("A", a), side("B", b))
    calls: list[tuple[str, str]] = []

    def write(ra: Path, rb: Path, out: Path) -> None:
        calls.append((ra.name, rb.name))
        out.write_bytes(b"rrd")

    files = write_pair_rrds(c, tmp_path / "rrd", write)
    assert calls == [("a0", "b0"), ("a1", "b1")]  # the failed pair has no comparison file
    assert sorted(p.name for p in (tmp_path / "rrd").iterdir()) == ["a0--b0.rrd", "a1--b1.rrd"]
    assert write_pair_rrds(c, tmp_path / "rrd", write) == files and len(calls) == 2  # kept, not rewritten
    (tmp_path / "out").mkdir()
    write_reports(c, tmp_path / "out" / "r.html", tmp_path / "out" / "s.md", pair_file_links(files))
    html = (tmp_path / "out" / "r.html").read_text()
    assert 'href="../rrd/a0--b0.rrd"' in html and ">A/B r1s0</a>" in html and "a2--b2" not in html
    # a CI summary links only what lies under its own folder: ../rrd would be dead where it is read
    assert "../rrd" not in (tmp_path / "out" / "s.md").read_text()
    write_reports(c, None, tmp_path / "s.md", pair_file_links(files))
    assert "[A/B r2s0](rrd/a1--b1.rrd)" in (tmp_path / "s.md").read_text()
    write_reports(c, None, tmp_path / "s.md", pair_file_links(files), base_url="https://ci.example/job/7/")
    assert "[A/B r2s0](https://ci.example/job/7/rrd/a1--b1.rrd)" in (tmp_path / "s.md").read_text()


def test_markdown_summary_lists_regressions_first_and_folds_the_unchanged() -> None:
    """Regressions lead the summary's table; unchanged rows sit in a closed <details> after it."""
    from slamreplay.replay.runs.report import render_markdown

    def two(rmse: list[float], ape: list[float], code: str) -> list[dict[str, Any]]:
        out = rows(rmse, code=code)
        for r, x in zip(out, rows(ape, metric="ape_rmse_m", code=code), strict=True):
            for key in ("metrics", "better", "tolerance", "units"):
                r[key].update(x[key])
        return out

    a, b = two(A, A, "a"), two(A, [0.075, 0.121, 0.089], "b")
    text = render_markdown(compare(side("A", a), side("B", b)), Path("/nowhere"))
    table = [line for line in text.splitlines() if line.startswith("| landmarks")]
    assert "regression" in table[0] and "ape_rmse_m" in table[0]
    assert "unchanged" in table[1] and text.index("<details>") < text.index(table[1])


def test_variants_table_puts_each_variants_seeds_side_by_side() -> None:
    """suite run's closing table: mean ± sd per variant column, failed cells counted out, direction marked."""
    from slamreplay.replay.runs.compare import variants_table

    default = rows([0.1, 0.2, 0.3])
    paper = [{**r, "variant": "paper"} for r in rows([0.4, 0.6])] + [
        {**r, "variant": "paper"} for r in rows([0.0], status="failed")]
    nees = [{**r, "metrics": {**r["metrics"], "landmark_nees_mean": 2.0}, "better": {**r["better"],
                                                                                      "landmark_nees_mean": "none"}}
            for r in default]
    text = variants_table(nees + paper)
    lines = text.splitlines()
    assert lines[0] == "landmarks / dslam"
    assert "default (3/3 ok)" in lines[1] and "paper (2/3 ok)" in lines[1]
    rmse = next(line for line in lines if line.strip().startswith("landmark_rmse_m"))
    assert rmse.split()[1] == "l" and "0.2 ± 0.1" in rmse and "0.5 ± 0.14" in rmse
    nees_line = next(line for line in lines if line.strip().startswith("landmark_nees_mean"))
    assert "2 ± 0" in nees_line and nees_line.rstrip().endswith("-")  # no paper cell reports it
    assert variants_table([]) == ""
