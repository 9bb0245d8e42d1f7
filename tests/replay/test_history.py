"""The history store: commits selected, cells appended as they end, reused by a later call; failures recorded."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest

from slamreplay.replay.errors import ReplayError
from slamreplay.replay.runs import history as hist
from slamreplay.replay.runs.changepoints import detect_changes
from slamreplay.replay.runs.history_report import render_markdown, write_history_reports
from slamreplay.replay.runs.revisions import Revision
from slamreplay.replay.runs.suite import load_suite
from slamreplay.replay.runs.suite_run import CellJob


def git(repo: Path, *args: str) -> str:
    return subprocess.run(["git", "-c", "user.name=t", "-c", "user.email=t@t", "-C", str(repo), *args],
                          check=True, capture_output=True, text=True).stdout.strip()


@pytest.fixture
def repo(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> tuple[Path, list[str]]:
    """A repository of 6 commits, and their shas."""
    monkeypatch.setenv("SLAMREPLAY_CACHE", str(tmp_path / "cache"))
    r = tmp_path / "repo"
    r.mkdir()
    git(r, "init", "-q")
    shas = []
    for i in range(6):
        (r / "f.txt").write_text(f"{i}\n")
        git(r, "add", "f.txt")
        git(r, "commit", "-qm", f"commit {i}")
        shas.append(git(r, "rev-parse", "HEAD"))
    return r, shas


class FakeRuns:
    """Stands in for each revision's `slamreplay run`: writes a run directory whose landmark_rmse_m is
    ``level[sha] + 0.01 * seed``; counts the runs; fails the shas in ``broken``."""

    def __init__(self, level: dict[str, float], broken: frozenset[str] = frozenset()) -> None:
        self.level, self.broken = level, broken
        self.ran: list[str] = []

    def __call__(self, revision: Revision, job: CellJob) -> str | None:
        self.ran.append(revision.sha)
        job.run_dir.mkdir(parents=True, exist_ok=True)
        ok = revision.sha not in self.broken
        (job.run_dir / "manifest.json").write_text(json.dumps({"status": "succeeded" if ok else "failed",
                                                               "error": None if ok else "boom"}))
        value = self.level.get(revision.sha, 0.1) + 0.01 * job.cell.seed
        (job.run_dir / "metrics.json").write_text(json.dumps({"metrics": {"landmark_rmse_m": {
            "value": value, "better": "lower", "unit": "m", "tolerance": 1e-6, "rel_tolerance": 1e-3}}}))
        return None if ok else "boom"


def fake_revisions(monkeypatch: pytest.MonkeyPatch, unbuildable: set[str]) -> None:
    def prepare(repo: Path, rev: str, cache: Path, note: object = None) -> Revision:
        if rev in unbuildable:
            raise ReplayError(f"revision {rev[:10]} does not build: `pip install -e` failed")
        return Revision(rev, rev, repo, (), {})
    monkeypatch.setattr(hist, "prepare_revision", prepare)


def suite_file(tmp_path: Path) -> Path:
    (tmp_path / "r.mcap").write_bytes(b"any bytes: the fake runs never read it")
    s = tmp_path / "s.toml"
    s.write_text('seeds = [0, 1, 2]\n[recordings.r]\npath = "r.mcap"\n[pipelines.dslam]\n')
    return s


def test_select_commits(repo: tuple[Path, list[str]], tmp_path: Path) -> None:
    """A..B includes A; --every keeps the oldest and every Nth back from the newest; a file in its order."""
    r, shas = repo
    assert hist.select_commits(r, f"{shas[0]}..{shas[5]}") == shas
    assert hist.select_commits(r, f"{shas[0]}..HEAD", every=2) == [shas[0], shas[1], shas[3], shas[5]]
    assert hist.select_commits(r, "HEAD~1") == [shas[4]]
    f = tmp_path / "commits.txt"
    f.write_text(f"# mine\n{shas[3]}\n\nHEAD  # the tip\n")
    assert hist.select_commits(r, commits_file=f) == [shas[3], shas[5]]
    for kwargs, pattern in (({"revs": "HEAD..HEAD~3"}, "is not an ancestor"), ({"revs": "..HEAD"}, "give A..B"),
                            ({"revs": "nope..HEAD"}, "unknown revision"), ({"revs": "HEAD", "every": 0}, "--every"),
                            ({"commits_file": tmp_path / "none.txt"}, "cannot read")):
        with pytest.raises(ReplayError, match=pattern):
            hist.select_commits(r, **kwargs)  # type: ignore[arg-type]


def test_store_appended_reused_and_failures_recorded(repo: tuple[Path, list[str]], tmp_path: Path,
                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """Commit 2 does not build, commit 3's runs fail: both recorded, the others run; a second call over more
    commits runs only the new ones; a torn last line is run again; the level step at 4 is the one change."""
    r, shas = repo
    fake_revisions(monkeypatch, {shas[2]})
    runs = FakeRuns({s: (0.1 if i < 4 else 0.2) for i, s in enumerate(shas)}, broken=frozenset({shas[3]}))
    suite, out = load_suite(suite_file(tmp_path)), tmp_path / "h"
    notes: list[str] = []
    counts: list[tuple[int, int]] = []
    h = hist.run_history(suite, out, shas[:5], r, workers=2, run=runs, note=notes.append,
                         progress=lambda d, t: counts.append((d, t)))
    assert [c.sha for c in h.commits] == shas[:5] and [c.subject for c in h.commits][:2] == ["commit 0", "commit 1"]
    assert [h.status[s]["status"] for s in shas[:5]] == ["succeeded", "succeeded", "build_failed", "failed",
                                                         "succeeded"]
    assert "does not build" in h.status[shas[2]]["error"] and len(runs.ran) == 4 * 3
    assert counts[-1] == (15, 15) and any("commit 5/5 done" in n for n in notes)
    assert json.loads((out / "commits" / shas[0] / "suite.json").read_text())["finished"]
    lines = (out / hist.STORE).read_text().splitlines()
    (out / hist.STORE).write_text("\n".join(lines[:-1]) + "\n" + lines[-1][:20])  # a stop mid-line
    runs.ran.clear()
    h = hist.run_history(suite, out, shas, r, run=runs)
    assert sorted(set(runs.ran)) == sorted({shas[5]}) and len(runs.ran) == 3  # not 2 (build failed), not 3 (failed)
    assert len(h.commits) == 6 and h.status[shas[4]]["status"] == "succeeded"
    changes = detect_changes(h)
    assert [(ch.commit, ch.previous, ch.verdict) for ch in changes] == [(shas[4], shas[1], "regression")]
    linked = write_history_reports(h, changes, out)
    assert linked[0].report and (out / linked[0].report).is_file()
    page = (out / "index.html").read_text()
    assert "build_failed" in page and "does not build" in page and page.count("href='#c") >= 4
    md = render_markdown(h, linked, tmp_path, out, base_url="https://ci.example/1")
    assert f"](https://ci.example/1/h/{linked[0].report})" in md and "🔴 regression" in md
    runs.ran.clear()
    hist.run_history(suite, out, shas, r, run=runs, retry_failed=True)
    assert sorted(set(runs.ran)) == [shas[3]]  # the failed cells; the unbuildable commit is tried (and fails) again


def test_out_checks_and_cache_reuse(repo: tuple[Path, list[str]], tmp_path: Path,
                                    monkeypatch: pytest.MonkeyPatch) -> None:
    """--out must be new or a history's; runs that `compare rev:` cached for the same key are copied, not run."""
    r, shas = repo
    fake_revisions(monkeypatch, set())
    runs = FakeRuns({})
    suite = load_suite(suite_file(tmp_path))
    (tmp_path / "file").write_text("x")
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "mine.txt").write_text("x")
    for target, pattern in (("file", "is a file"), ("other", "holds other files")):
        with pytest.raises(ReplayError, match=pattern):
            hist.run_history(suite, tmp_path / target, shas[:1], r, run=runs)
    from slamreplay.replay.runs.suite_run import run_suite
    cached = tmp_path / "cache" / "results" / shas[0]

    def run_cells(todo: list[CellJob]) -> list[tuple[CellJob, str | None]]:
        return [(j, runs(Revision(shas[0], shas[0], r, (), {}), j)) for j in todo]

    run_suite(suite, cached, shas[0], run_cells)
    runs.ran.clear()
    h = hist.run_history(suite, tmp_path / "h", shas[:2], r, run=runs)
    assert runs.ran == [shas[1]] * 3 and all(x["cached"] for x in h.cells(shas[0]))


def test_backfilled_commits_in_git_order(repo: tuple[Path, list[str]], tmp_path: Path,
                                         monkeypatch: pytest.MonkeyPatch) -> None:
    """Commits 3-5 run first, 0-2 backfilled after (and the store's generations lost): the history, its report and
    its markdown read 0..5, the step judged from commit 2 to commit 3, a regression."""
    r, shas = repo
    fake_revisions(monkeypatch, set())
    runs = FakeRuns({s: (0.1 if i < 3 else 0.2) for i, s in enumerate(shas)})
    suite, out = load_suite(suite_file(tmp_path)), tmp_path / "h"
    hist.run_history(suite, out, shas[3:], r, run=runs)
    hist.run_history(suite, out, shas[:3], r, run=runs)
    store = out / hist.STORE

    def older_slamreplay(row: dict[str, object]) -> dict[str, object]:  # no generation; dates that mislead
        late = row["commit"] in shas[:3]
        return {**{k: v for k, v in row.items() if k != "generation"},
                "date": f"2030-01-0{shas.index(str(row['commit'])) + 1}T00:00:00+00:00" if late else row["date"]}

    lines = store.read_text().splitlines()
    store.write_text("".join(json.dumps(older_slamreplay(json.loads(x))) + "\n" for x in lines))
    assert [c.sha for c in hist.read_store(out).commits][3:] == shas[:3]  # by date, as the store misleads
    h = hist.run_history(suite, out, shas[:3], r, run=runs)  # nothing left to run: read back in git's order
    assert [c.sha for c in h.commits] == shas and not any(c.note for c in h.commits)
    changes = detect_changes(h)
    assert [(ch.previous, ch.commit, ch.verdict, ch.index) for ch in changes] == [(shas[2], shas[3], "regression", 3)]
    assert changes[0].mean_before == pytest.approx(0.11) and changes[0].mean_after == pytest.approx(0.21)
    linked = write_history_reports(h, changes, out, markdown=tmp_path / "summary.md")
    page = (out / "index.html").read_text()
    rows = [page.index(f"<tr id='c{k}'><td>{k + 1}</td><td><code>{s[:10]}</code> commit {k}") for k, s in
            enumerate(shas)]
    assert rows == sorted(rows)
    md = (tmp_path / "summary.md").read_text()
    assert f"`{shas[3][:10]}` commit 3 |" in md and "0.11 | 0.21 | +0.1" in md and linked[0].previous == shas[2]
