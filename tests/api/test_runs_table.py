"""The runs table (/runs): paging, sorting, filters, metric conditions, URL state, CSV, labels, cancel/delete."""

from __future__ import annotations

import csv
import html
import io
import json
import re
import sqlite3
import warnings
from pathlib import Path
from urllib.parse import parse_qs, urlsplit

import pytest
from service_helpers import InlineExecutor

with warnings.catch_warnings():
    warnings.simplefilter("ignore", UserWarning)  # StarletteDeprecationWarning: it asks for httpx2; httpx works
    from fastapi.testclient import TestClient

from slamreplay.api.app import create_app
from slamreplay.api.service.runs_grammar import Clause, Condition, parse_where
from slamreplay.api.service.runs_query import RunsView, parse_conditions, parse_view
from slamreplay.api.service.settings import Settings
from slamreplay.api.service.store import RecordingRow, Store
from slamreplay.api.service.store_runs import Labels

SIM, HALL = "a" * 64, "b" * 64
COMMITS = ("abcd" + "1" * 36, "ef01" + "2" * 36)
# The jobs table as the first release made it: a database from then must open and work.
OLD_SCHEMA = """
CREATE TABLE IF NOT EXISTS recordings (
    id TEXT PRIMARY KEY, filename TEXT NOT NULL, size INTEGER NOT NULL, topics TEXT NOT NULL,
    message_count INTEGER NOT NULL, start_ns INTEGER NOT NULL, end_ns INTEGER NOT NULL, created REAL NOT NULL
);
CREATE TABLE IF NOT EXISTS jobs (
    seq INTEGER PRIMARY KEY AUTOINCREMENT,
    id TEXT NOT NULL UNIQUE,
    recording_id TEXT NOT NULL,
    pipeline TEXT NOT NULL,
    config TEXT NOT NULL,
    seed INTEGER NOT NULL,
    status TEXT NOT NULL,
    progress REAL NOT NULL DEFAULT 0,
    error TEXT,
    note TEXT,
    attempts INTEGER NOT NULL DEFAULT 0,
    created REAL NOT NULL,
    started REAL,
    finished REAL
);
CREATE INDEX IF NOT EXISTS jobs_status ON jobs (status, seq);
CREATE INDEX IF NOT EXISTS jobs_recording ON jobs (recording_id);
"""


def jid(i: int) -> str:
    return f"{i:032x}"


def app_for(data: Path) -> TestClient:
    """An app over ``data`` whose scheduler never starts: the rows put in its store stay as they are."""
    return TestClient(create_app(Settings(allowed_hosts=("testserver",), data_dir=data, workers=1),
                                 executor=InlineExecutor()))


def write_metrics(run_dir: Path, values: dict[str, float]) -> None:
    run_dir.mkdir(parents=True, exist_ok=True)
    doc = {"format": 1, "pipeline": "x", "metrics": {k: {"value": v, "better": "lower", "unit": "m"}
                                                      for k, v in values.items()}}
    (run_dir / "metrics.json").write_text(json.dumps(doc))


@pytest.fixture
def table(tmp_path: Path) -> tuple[TestClient, Store]:
    """Nine jobs: 0-5 succeeded (ape_rmse_m 0.0, 0.1 ... 0.5, odometry on sim.mcap for even seeds, dslam on
    hall.mcap for odd; 0-2 on COMMITS[0], 3-5 on COMMITS[1]), 6 failed, 7 running, 8 queued; job 3 has the config
    {"range_sigma_m": 0.2}; job i was created on 2024-05-(i+1)."""
    client = app_for(tmp_path)
    store: Store = client.app.state.jobs.store  # type: ignore[attr-defined]
    store.add_recording(RecordingRow(SIM, "sim.mcap", 10, [], 0, 0, 0, 0.0))
    store.add_recording(RecordingRow(HALL, "hall.mcap", 10, [], 0, 0, 0, 0.0))
    for i in range(9):
        rec, pipeline = (SIM, "odometry") if i % 2 == 0 else (HALL, "dslam")
        store.add_job(jid(i), rec, pipeline, {"range_sigma_m": 0.2} if i == 3 else {}, i)
        if i < 8:
            assert store.claim_next() is not None
        if i < 6:
            store.finish_job(jid(i), "succeeded", None, {"ape_rmse_m": i / 10, "poses_scored": 100.0 - i},
                             COMMITS[i // 3])
        elif i == 6:
            store.finish_job(jid(i), "failed", "sim.mcap: topic /camera/image is missing\nsecond line", None)
    with sqlite3.connect(store.path) as conn:
        conn.executemany("UPDATE jobs SET created = ? WHERE id = ?",
                         [(1714521600.0 + i * 86400 + 3600, jid(i)) for i in range(9)])
    return client, store


def row_ids(html: str) -> list[int]:
    """The listed jobs, in the table's order, as their numbers."""
    return [int(m, 16) for m in re.findall(r'<tr id="run-([0-9a-f]{32})"', html)]


def test_first_page_lists_every_column(table: tuple[TestClient, Store]) -> None:
    """/ and /runs list every job newest first with recording by file name, status with the error's first line,
    the metric column with its unit and direction, and a viewport meta and favicon link; /runs is the table alone."""
    client, _ = table
    for path in ("/", "/runs"):
        r = client.get(path)
        assert r.status_code == 200
        assert row_ids(r.text) == [8, 7, 6, 5, 4, 3, 2, 1, 0]
    assert 'id="upload-form"' in client.get("/").text  # the home page has the lists and forms below the table
    html = client.get("/runs").text
    assert 'id="upload-form"' not in html and 'href="/#recordings"' in html
    assert '<meta name="viewport" content="width=device-width, initial-scale=1">' in html
    assert 'rel="icon" href="/static/favicon.svg"' in html
    assert "hall.mcap" in html and SIM not in html.split('id="runs-table"')[1].split("</table>")[0]
    assert "sim.mcap: topic /camera/image is missing" in html and "second line" not in html
    assert re.search(r"ape_rmse_m</a> ↓", html)  # the unit is in the name; lower is better
    assert 'title="absolute position error RMSE' in html
    assert "config: range_sigma_m" in html  # the only key that differs between the listed runs


def test_paging(table: tuple[TestClient, Store]) -> None:
    """per=25 of 60 jobs: three pages (25, 25, 10), links to the next page; a page past the end shows the last."""
    client, store = table
    for i in range(9, 60):
        store.add_job(jid(i), SIM, "odometry", {}, i)
    first = client.get("/runs", params={"per": 25})
    assert row_ids(first.text) == list(range(59, 34, -1)) and "page 1 of 3" in first.text
    nxt = re.search(r'href="([^"]+)" rel="next"', first.text)
    assert nxt is not None
    second = client.get(nxt.group(1).replace("&amp;", "&"))
    assert row_ids(second.text) == list(range(34, 9, -1))
    assert row_ids(client.get("/runs", params={"per": 25, "page": 3}).text) == list(range(9, -1, -1))
    assert row_ids(client.get("/runs", params={"per": 25, "page": 99}).text) == list(range(9, -1, -1))


@pytest.mark.parametrize(("sort", "expected"), [
    ("-created", [8, 7, 6, 5, 4, 3, 2, 1, 0]),
    ("created", [0, 1, 2, 3, 4, 5, 6, 7, 8]),
    ("seed", [0, 1, 2, 3, 4, 5, 6, 7, 8]),
    ("-seed", [8, 7, 6, 5, 4, 3, 2, 1, 0]),
    ("pipeline", [7, 5, 3, 1, 8, 6, 4, 2, 0]),  # dslam first; ties newest first
    ("recording", [7, 5, 3, 1, 8, 6, 4, 2, 0]),  # hall.mcap before sim.mcap
    ("status", [6, 7, 5, 4, 3, 2, 1, 0, 8]),  # failed, queued... alphabetical: failed < queued < running
    ("m.ape_rmse_m", [0, 1, 2, 3, 4, 5, 8, 7, 6]),  # runs without the metric last
    ("-m.ape_rmse_m", [5, 4, 3, 2, 1, 0, 8, 7, 6]),
    ("m.poses_scored", [5, 4, 3, 2, 1, 0, 8, 7, 6]),
    ("c.range_sigma_m", [3, 8, 7, 6, 5, 4, 2, 1, 0]),
    ("-started", [7, 6, 5, 4, 3, 2, 1, 0, 8]),
    ("-finished", [6, 5, 4, 3, 2, 1, 0, 8, 7]),
])
def test_each_sort(table: tuple[TestClient, Store], sort: str, expected: list[int]) -> None:
    """Each column sorts (runs without a value last either way, then newest first)."""
    client, _ = table
    got = row_ids(client.get("/runs", params={"sort": sort}).text)
    if sort == "status":  # queued (8) and running (7) after failed: check the order of statuses only
        assert got[0] == 6 and got[1:3] == [8, 7] and set(got[3:]) == {0, 1, 2, 3, 4, 5}
    else:
        assert got == expected


def test_sort_by_name_tags_note_duration_and_variant(table: tuple[TestClient, Store]) -> None:
    """Name, tags, note, duration and variant sort too; unnamed runs come last."""
    client, store = table
    store.set_labels(jid(2), Labels("beta", ("z",), "second"))
    store.set_labels(jid(4), Labels("Alpha", ("a",), "first"))
    assert row_ids(client.get("/runs", params={"sort": "name"}).text)[:2] == [4, 2]
    assert row_ids(client.get("/runs", params={"sort": "-name"}).text)[:2] == [2, 4]
    assert row_ids(client.get("/runs", params={"sort": "note"}).text)[:2] == [4, 2]
    assert row_ids(client.get("/runs", params={"sort": "tags"}).text)[0] in (2, 4)
    assert len(row_ids(client.get("/runs", params={"sort": "-duration"}).text)) == 9
    with sqlite3.connect(store.path) as conn:
        conn.execute("INSERT INTO suite_cells VALUES ('s', 0, ?, ?, 0)", (json.dumps({"variant": "tuned"}), jid(1)))
    html = client.get("/runs", params={"sort": "variant"}).text
    assert row_ids(html)[0] == 1 and ">tuned<" in html
    assert "It serves 1 suite cell:" in client.get(f"/ui/jobs/{jid(1)}/delete").text


@pytest.mark.parametrize(("params", "expected"), [
    ({"recording": SIM}, [8, 6, 4, 2, 0]),
    ({"recording": "hall.mcap"}, [7, 5, 3, 1]),
    ({"recording": "bbbbbbbb"}, [7, 5, 3, 1]),  # an id prefix, as the page shows it
    ({"pipeline": "dslam"}, [7, 5, 3, 1]),
    ({"status": "failed"}, [6]),
    ({"q": "camera/image"}, [6]),  # the error's text
    ({"q": "range_sigma"}, [3]),  # the config
    ({"q": jid(5)[-6:]}, [5]),  # the id
    ({"where": "ape_rmse_m < 0.25"}, [2, 1, 0]),
    ({"where": "ape_rmse_m >= 0.3"}, [5, 4, 3]),
    ({"where": "ape_rmse_m != 0"}, [5, 4, 3, 2, 1]),
    ({"where": "ape_rmse_m = 0.2"}, [2]),
    ({"where": "ape_rmse_m > 0.05 and poses_scored >= 97", "pipeline": "dslam"}, [3, 1]),
    ({"where": "ape_rmse_m<=1e-1", "recording": SIM}, [0]),
])
def test_each_filter(table: tuple[TestClient, Store], params: dict[str, str], expected: list[int]) -> None:
    """Recording (id, prefix or file name), pipeline, status, free text and metric conditions filter the runs."""
    client, _ = table
    r = client.get("/runs", params=params)
    assert r.status_code == 200 and row_ids(r.text) == expected


def test_tag_and_text_filters_find_labels(table: tuple[TestClient, Store]) -> None:
    """A tag filters exactly; free text finds names, notes and tags (every word must match)."""
    client, store = table
    store.set_labels(jid(1), Labels("old baseline", ("paper", "v1"), "before the fix"))
    store.set_labels(jid(2), Labels(None, ("paper-draft",), None))
    assert row_ids(client.get("/runs", params={"tag": "paper"}).text) == [1]
    assert row_ids(client.get("/runs", params={"q": "baseline"}).text) == [1]
    assert row_ids(client.get("/runs", params={"q": "before fix"}).text) == [1]
    assert row_ids(client.get("/runs", params={"q": "paper"}).text) == [2, 1]
    assert row_ids(client.get("/runs", params={"q": "100%"}).text) == []  # % is a character, not a wildcard


@pytest.mark.parametrize(("where", "message"), [
    ("ape_rmse_m << 0.1", "cannot read the condition 'ape_rmse_m << 0.1': write a metric name, one of"),
    ("ape_rmse_m < abc", "cannot read the condition"),
    ("ape_rmse_m < 0.1; drop table jobs", "cannot read the condition"),
    ("ape_rmse < 0.1", "unknown metric 'ape_rmse': did you mean ape_rmse_m"),
    ("< 0.1", "cannot read the condition"),
])
def test_bad_condition_is_a_message(table: tuple[TestClient, Store], where: str, message: str) -> None:
    """A condition that does not parse: 422 with one line saying what is wrong, the table unfiltered by it."""
    client, _ = table
    r = client.get("/runs", params={"where": where})
    assert r.status_code == 422 and r.headers["content-type"].startswith("text/html")
    assert message in html.unescape(r.text) and "(the condition is not applied)" in r.text
    assert len(row_ids(r.text)) == 9


def test_other_bad_parameters_are_messages(table: tuple[TestClient, Store]) -> None:
    """An unknown status, sort or metric column and a page that is not a number: messages, never a 500."""
    client, _ = table
    for params, message in (({"status": "done"}, "unknown status"), ({"sort": "colour"}, "cannot sort by"),
                            ({"cols": "ape_rmse_m,nope"}, "column unknown metric"),
                            ({"page": "two"}, "page must be a whole number")):
        r = client.get("/runs", params=params)
        assert r.status_code == 422 and message in html.unescape(r.text), params


def test_parse_conditions_strictly() -> None:
    """Each operator parses; the number may be signed or in exponent form; and/or/parentheses nest as written."""
    known = {"a_m": None, "b": None}
    got = parse_conditions("a_m < 1 and b>=-2.5e-3 AND a_m != .5", known)
    assert [(c.metric, c.op, c.value) for c in got] == [("a_m", "<", 1.0), ("b", ">=", -2.5e-3), ("a_m", "!=", 0.5)]
    for op in ("<", "<=", ">", ">=", "=", "!="):
        assert parse_conditions(f"b {op} 1", known)[0].op == op
    for bad in ("b == 1", "b < nan", "b <", "1 < b", "b < 1; drop table jobs"):
        with pytest.raises(ValueError, match="cannot read the condition"):
            parse_conditions(bad, known)


def test_grammar_precedence_and_fields() -> None:
    """``and`` binds tighter than ``or``; parentheses group; config keys, seed, commit, dates and text fields
    each read their kind of value."""
    known = {"a_m": None, "b": None}
    expr = parse_where("a_m < 1 or b > 2 and a_m = 3", known)
    assert str(expr) == "a_m < 1 or (b > 2 and a_m = 3)"
    assert isinstance(expr, Clause) and expr.join == "or" and isinstance(expr.parts[1], Clause)
    expr = parse_where("(a_m < 1 OR b > 2) and (seed = 3)", known)
    assert str(expr) == "(a_m < 1 or b > 2) and seed = 3"
    cases = {"config.range_sigma_m <= 0.1": ("config.range_sigma_m", "<=", 0.1),
             "config.association = nn": ("config.association", "=", "nn"),
             "config.association != 'joint compatibility'": ("config.association", "!=", "joint compatibility"),
             "config.sparsify = true": ("config.sparsify", "=", True),
             "config.range_sigma_m = default": ("config.range_sigma_m", "=", None),
             "seed != 2": ("seed", "!=", 2), "commit = 1A2b3C4": ("commit", "=", "1a2b3c4"),
             "commit = none": ("commit", "=", None),
             "created >= 2024-05-01": ("created", ">=", 1714521600.0),
             "recording = 'hall 2.mcap'": ("recording", "=", "hall 2.mcap"), "variant = none": ("variant", "=", None),
             "pipeline=dslam": ("pipeline", "=", "dslam")}
    for text, want in cases.items():
        c = parse_where(text, known, {"range_sigma_m", "association", "sparsify"})
        assert isinstance(c, Condition) and (c.field, c.op, c.value) == want, text
        assert parse_where(str(c), known, {"range_sigma_m", "association", "sparsify"}) == c  # written back


BAD_GRAMMAR = {
    "(ape_rmse_m < 1": "a ( without its )",
    "ape_rmse_m < 1)": "a ) without its (",
    "ape_rmse_m < 1 and": "a comparison is missing after 'and'",
    "or ape_rmse_m < 1": "a comparison is missing at the start",
    "ape_rmse_m < 1 and or seed = 2": "a comparison is missing after 'and'",
    "() ": "a comparison is missing after '('",
    "config.range_sigm < 1": "unknown config key 'range_sigm': did you mean range_sigma_m",
    "config.range_sigma_m < abc": "config.range_sigma_m takes a number with <",
    "commit < abcd": "commit takes = or != only",
    "commit = xyz1": "commit takes 4 to 40 hex digits",
    "created > 2024-13-01": "created takes a day YYYY-MM-DD",
    "finished = yesterday": "finished takes a day YYYY-MM-DD",
    "seed = 1.5": "seed takes a whole number",
    "status = done": "unknown status 'done'",
    "pipeline < dslam": "pipeline takes = or != only",
    "recording = 'hall.mcap": "is not closed",
}


def test_bad_grammar_is_one_line_on_the_page_and_the_api(table: tuple[TestClient, Store]) -> None:
    """A condition that does not parse: the page says so in one line above the unfiltered table (422), and the
    JSON API (GET /jobs?where=) answers 422 with the same line."""
    client, _ = table
    for where, message in BAD_GRAMMAR.items():
        r = client.get("/runs", params={"where": where})
        assert r.status_code == 422
        errors = re.findall(r'<p class="error" id="view-error">(.*?)</p>', r.text, re.S)
        assert len(errors) == 1 and message in html.unescape(errors[0]) and "\n" not in errors[0], (where, errors)
        assert len(row_ids(r.text)) == 9
        api = client.get("/jobs", params={"where": where})
        detail = api.json()["detail"]
        assert api.status_code == 422 and message in detail and "\n" not in detail and "not applied" not in detail


def test_url_state_round_trip(table: tuple[TestClient, Store]) -> None:
    """A view written to a URL and read back is the same view; the page's sort and pager links keep the filters."""
    view = parse_view({"q": ["drift"], "pipeline": ["dslam"], "status": ["succeeded"], "tag": ["paper"],
                       "where": ["ape_rmse_m < 0.5"], "cols": ["ape_rmse_m", "poses_scored"],
                       "sort": ["-m.ape_rmse_m"], "page": ["2"], "per": ["25"], "recording": ["sim.mcap"]})
    assert view.errors == ()
    again = parse_view({k: [v] for k, v in parse_qs(urlsplit(view.url()).query).items() for v in v})
    assert again == view and again.cols == ("ape_rmse_m", "poses_scored")
    assert parse_view({}) == RunsView()
    client, _ = table
    html = client.get("/runs", params={"pipeline": "dslam", "cols": "ape_rmse_m,poses_scored"}).text
    link = re.search(r'href="([^"]*sort=seed[^"]*)"', html)
    assert link is not None
    params = parse_qs(urlsplit(link.group(1).replace("&amp;", "&")).query)
    assert params == {"pipeline": ["dslam"], "cols": ["ape_rmse_m,poses_scored"], "sort": ["seed"]}
    assert "poses_scored</a>" in html


def test_csv_export_is_the_view_on_every_page(table: tuple[TestClient, Store]) -> None:
    """Export CSV: the same filter and sort over every page, the metric columns with units."""
    client, _ = table
    html = client.get("/runs", params={"pipeline": "odometry", "sort": "-m.ape_rmse_m", "per": 25}).text
    href = re.search(r'id="export-csv" href="([^"]+)"', html)
    assert href is not None
    r = client.get(href.group(1).replace("&amp;", "&"))
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/csv")
    rows = list(csv.reader(io.StringIO(r.text)))
    assert rows[0][:3] == ["id", "name", "tags"] and rows[0][-1] == "ape_rmse_m"
    assert [int(x[0], 16) for x in rows[1:]] == [4, 2, 0, 8, 6]
    assert [x[-1] for x in rows[1:]] == ["0.4", "0.2", "0.0", "", ""]
    assert rows[1][4] == "sim.mcap" and rows[1][13] == "succeeded"
    bad = client.get("/runs.csv", params={"where": "nope <"})
    assert bad.status_code == 422 and "cannot read the condition" in bad.text


def test_csv_cells_are_never_formulas(table: tuple[TestClient, Store]) -> None:
    """A name a spreadsheet would run (=HYPERLINK...) is exported with a leading apostrophe."""
    client, store = table
    store.set_labels(jid(0), Labels("=HYPERLINK(1)"))
    rows = list(csv.reader(io.StringIO(client.get("/runs.csv").text)))
    assert [x[1] for x in rows if x[0] == jid(0)] == ["'=HYPERLINK(1)"]


def test_rename_tag_and_note(table: tuple[TestClient, Store]) -> None:
    """The edit form saves name, tags and note and goes back to the table; bad tags are a 422 message."""
    client, store = table
    form = client.get(f"/ui/jobs/{jid(1)}/edit", params={"next": "/runs?pipeline=dslam"})
    assert form.status_code == 200 and 'id="edit-form"' in form.text
    r = client.post(f"/ui/jobs/{jid(1)}/edit", data={"name": "baseline 2024", "tags": "paper, v1 paper",
                                                      "note": "the run in the paper", "next": "/runs?pipeline=dslam"},
                    follow_redirects=False)
    assert r.status_code == 303 and r.headers["location"] == "/runs?pipeline=dslam"
    job = store.get_job(jid(1))
    assert job is not None and (job.name, job.tags, job.note) == ("baseline 2024", ("paper", "v1"),
                                                                 "the run in the paper")
    html = client.get("/runs", params={"tag": "v1"}).text
    assert row_ids(html) == [1] and "baseline 2024" in html and 'class="tag"' in html
    api = client.get(f"/jobs/{jid(1)}").json()
    assert (api["name"], api["tags"], api["note"]) == ("baseline 2024", ["paper", "v1"], "the run in the paper")
    assert [j["tags"] for j in client.get("/jobs", params={"pipeline": "dslam"}).json() if j["id"] == jid(1)] == [
        ["paper", "v1"]]
    bad = client.post(f"/ui/jobs/{jid(1)}/edit", data={"name": "x", "tags": "a;b"})
    assert bad.status_code == 422 and "tag &#39;a;b&#39;" in bad.text
    away = client.post(f"/ui/jobs/{jid(1)}/edit", data={"name": "", "tags": "", "next": "https://evil.example/"},
                       follow_redirects=False)
    assert away.headers["location"] == "/runs"  # only a path on this server
    job = store.get_job(jid(1))
    assert job is not None and (job.name, job.tags) == (None, ())


def test_cancel_and_delete_ask_first(table: tuple[TestClient, Store], tmp_path: Path) -> None:
    """Cancel and delete are a confirmation page, then a form POST; each refuses the other kind of job."""
    client, store = table
    page = client.get(f"/ui/jobs/{jid(8)}/cancel")
    assert page.status_code == 200 and f'action="/ui/jobs/{jid(8)}/cancel"' in page.text
    assert store.get_job(jid(8)).status == "queued"  # type: ignore[union-attr]  # asking changes nothing
    r = client.post(f"/ui/jobs/{jid(8)}/cancel", data={"next": "/runs"}, follow_redirects=False)
    assert r.status_code == 303 and store.get_job(jid(8)).status == "cancelled"  # type: ignore[union-attr]
    assert "nothing to cancel" in client.get(f"/ui/jobs/{jid(0)}/cancel").text
    assert client.post(f"/ui/jobs/{jid(0)}/cancel").status_code == 409

    run = tmp_path / "runs" / jid(0)
    write_metrics(run, {"ape_rmse_m": 0.0})
    page = client.get(f"/ui/jobs/{jid(0)}/delete")
    assert 'id="confirm-form"' in page.text and "cannot be undone" in page.text
    assert "cancel it before deleting it" in client.get(f"/ui/jobs/{jid(7)}/delete").text
    assert client.post(f"/ui/jobs/{jid(7)}/delete").status_code == 409
    r = client.post(f"/ui/jobs/{jid(0)}/delete", data={"next": "/runs?status=succeeded"}, follow_redirects=False)
    assert r.status_code == 303 and r.headers["location"] == "/runs?status=succeeded"
    assert store.get_job(jid(0)) is None and not run.exists()
    assert 0 not in row_ids(client.get("/runs").text)
    assert client.post(f"/ui/jobs/{jid(0)}/delete").status_code == 404
    assert client.get(f"/ui/jobs/{jid(0)}/delete").status_code == 404


def test_compare_selected(table: tuple[TestClient, Store]) -> None:
    """Compare selected goes straight to the comparison: two succeeded runs of one recording, pipeline and seed to
    the paired page, any others to /ui/compare?runs=; fewer than two is a message."""
    client, store = table
    store.cancel_job(jid(8))  # so that the next claim is the new job
    store.add_job(jid(20), SIM, "odometry", {"x": 1}, 0)
    store.claim_next()
    store.finish_job(jid(20), "succeeded", None, {})
    r = client.get("/ui/runs/compare", params={"sel": [jid(0), jid(20)]}, follow_redirects=False)
    assert r.status_code == 303 and r.headers["location"] == f"/ui/compare?a={jid(0)}&b={jid(20)}"
    r = client.get("/ui/runs/compare", params={"sel": [jid(0), jid(1)]}, follow_redirects=False)
    assert r.status_code == 303 and r.headers["location"] == f"/ui/compare?runs={jid(0)},{jid(1)}"
    r = client.get("/ui/runs/compare", params={"sel": [jid(0), jid(1), jid(2)]}, follow_redirects=False)
    assert r.headers["location"] == f"/ui/compare?runs={jid(0)},{jid(1)},{jid(2)}"
    r = client.get("/ui/runs/compare", params={"sel": [jid(0)]})
    assert r.status_code == 422 and "select at least two runs" in r.text


def test_favicon(table: tuple[TestClient, Store]) -> None:
    """/favicon.ico answers with the package's SVG icon."""
    client, _ = table
    r = client.get("/favicon.ico")
    assert r.status_code == 200 and r.headers["content-type"].startswith("image/svg+xml") and b"<svg" in r.content


def test_metrics_are_backfilled_once_for_old_jobs(table: tuple[TestClient, Store], tmp_path: Path) -> None:
    """A succeeded job without stored metric values (an older server's) is read from metrics.json once, under the
    metrics' current names."""
    client, store = table
    store.cancel_job(jid(8))  # so that the next claim is the new job
    store.add_job(jid(30), SIM, "odometry", {}, 0)
    store.claim_next()
    store.finish_job(jid(30), "succeeded", None)  # no values: as an older server left it
    assert store.unscored() == [jid(30)]
    write_metrics(tmp_path / "runs" / jid(30), {"robot_ate_rmse_m": 7.5})  # a metric's name before a rename
    assert row_ids(client.get("/runs", params={"where": "ape_rmse_m > 7"}).text) == [30]
    assert store.unscored() == [] and store.get_job(jid(30)).metrics == {"ape_rmse_m": 7.5}  # type: ignore[union-attr]


def test_old_database_is_migrated_in_place(tmp_path: Path) -> None:
    """A jobs.sqlite made with the first schema opens: new columns and tables added, old rows kept and listed,
    their metrics read from their runs."""
    db = tmp_path / "runs" / "jobs.sqlite"
    db.parent.mkdir()
    with sqlite3.connect(db) as conn:
        conn.executescript(OLD_SCHEMA)
        conn.execute("INSERT INTO recordings VALUES (?, 'old.mcap', 1, '[]', 0, 0, 0, 0)", (SIM,))
        conn.execute("INSERT INTO jobs (id, recording_id, pipeline, config, seed, status, note, created, started, "
                     "finished) VALUES (?, ?, 'odometry', '{}', 3, 'succeeded', 're-queued once', 1.0, 2.0, 5.0)",
                     (jid(1), SIM))
    write_metrics(tmp_path / "runs" / jid(1), {"ape_rmse_m": 0.25})
    store = Store(db)
    job = store.get_job(jid(1))
    assert job is not None and (job.name, job.tags, job.metrics, job.note) == (None, (), None, "re-queued once")
    assert job.rev is None  # a job of an older server ran the service's own code
    Store(db)  # opening it again changes nothing
    with sqlite3.connect(db) as conn:
        columns = {r[1] for r in conn.execute("PRAGMA table_info(jobs)")}
        tables = {r[0] for r in conn.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
    assert {"name", "metrics", "rev"} <= columns and "job_tags" in tables
    client = app_for(tmp_path)
    html = client.get("/runs", params={"cols": "ape_rmse_m"}).text
    assert row_ids(html) == [1] and "old.mcap" in html and "0.25" in html and "3.0 s" in html
    assert store.set_labels(jid(1), Labels("kept", ("old",), None)) is not None


def test_finished_job_stores_its_metrics(tmp_path: Path) -> None:
    """A job run by the scheduler has its metric values in the store when it ends (no file read by the table)."""
    from conftest import write_tiny_recording
    from service_helpers import wait_for

    rec = write_tiny_recording(tmp_path / "tiny.mcap")
    with app_for(tmp_path / "data") as client:
        rid = client.post("/recordings", content=rec.read_bytes(), params={"filename": "tiny.mcap"}).json()["id"]
        job_id = client.post("/jobs", json={"recording_id": rid, "pipeline": "odometry"}).json()["id"]
        assert wait_for(client, job_id)["status"] == "succeeded"
        job = client.app.state.jobs.store.get_job(job_id)  # type: ignore[attr-defined]
        on_disk = json.loads((tmp_path / "data" / "runs" / job_id / "metrics.json").read_text())["metrics"]
        assert job.metrics == {k: v["value"] for k, v in on_disk.items()} and job.metrics
        html = client.get("/runs").text
        assert "tiny.mcap" in html and row_ids(html) == [int(job_id, 16)]


@pytest.mark.parametrize(("params", "expected"), [
    ({"where": "ape_rmse_m < 0.15 or ape_rmse_m > 0.45"}, [5, 1, 0]),
    ({"where": "(pipeline = dslam or seed = 0) and ape_rmse_m < 0.35"}, [3, 1, 0]),
    ({"where": "pipeline = dslam or seed = 0 and ape_rmse_m < 0.35"}, [7, 5, 3, 1, 0]),  # and binds tighter
    ({"where": "config.range_sigma_m = 0.2"}, [3]),
    ({"where": "config.range_sigma_m < 0.3"}, [3]),
    ({"where": "config.range_sigma_m = default and pipeline = dslam"}, [7, 5, 1]),
    ({"where": "seed >= 7 or seed = 1"}, [8, 7, 1]),
    ({"where": "commit = abcd"}, [2, 1, 0]),
    ({"where": f"commit = {COMMITS[1]}"}, [5, 4, 3]),
    ({"where": "commit != ABCD1"}, [5, 4, 3]),
    ({"where": "commit = none"}, [8, 7, 6]),
    ({"where": "status = failed or status = queued"}, [8, 6]),
    ({"where": "recording = hall.mcap and not_a_word = 1"}, list(range(8, -1, -1))),  # 422: unknown, not applied
    ({"where": "recording = hall.mcap and seed < 4"}, [3, 1]),
    ({"where": "created >= 2024-05-04"}, [8, 7, 6, 5, 4, 3]),
    ({"where": "created = 2024-05-02"}, [1]),
    ({"where": "created < 2024-05-03 or created > 2024-05-08"}, [8, 1, 0]),
    ({"since": "2024-05-03", "until": "2024-05-04"}, [3, 2]),
    ({"since": "2024-05-08"}, [8, 7]),
    ({"until": "2024-05-01"}, [0]),
])
def test_grammar_and_dates_filter(table: tuple[TestClient, Store], params: dict[str, str],
                                  expected: list[int]) -> None:
    """or, parentheses, config keys, seed, commit prefixes, text fields and days filter the runs as written."""
    client, _ = table
    assert row_ids(client.get("/runs", params=params).text) == expected


def test_bad_dates_are_messages(table: tuple[TestClient, Store]) -> None:
    """A date filter that is not a day is a one-line message, and not applied."""
    client, _ = table
    r = client.get("/runs", params={"since": "2024-02-30"})
    assert r.status_code == 422 and "since must be a day YYYY-MM-DD" in html.unescape(r.text)
    assert len(row_ids(r.text)) == 9


def test_first_click_on_a_metric_sorts_best_first(table: tuple[TestClient, Store]) -> None:
    """A lower-is-better metric's heading sorts ascending first, a higher-is-better one descending, a target one by
    its distance from the target; the second click flips."""
    view = parse_view({"cols": ["ape_rmse_m,landmarks_mapped,landmark_nees_mean"]})
    assert "sort=m.ape_rmse_m" in view.sort_url("m.ape_rmse_m")
    assert "sort=-m.landmarks_mapped" in view.sort_url("m.landmarks_mapped")
    assert "sort=m.landmark_nees_mean" in view.sort_url("m.landmark_nees_mean")
    sorted_view = parse_view({"sort": ["m.ape_rmse_m"]})
    assert "sort=-m.ape_rmse_m" in sorted_view.sort_url("m.ape_rmse_m")
    assert sorted_view.sort_title("m.ape_rmse_m") == "sorted best first: click for worst first"
    client, store = table
    html_text = client.get("/runs").text
    link = re.search(r'<a href="([^"]+)" title="sort best first">ape_rmse_m</a>', html_text)
    assert link is not None and "sort=m.ape_rmse_m" in link.group(1)
    assert row_ids(client.get(link.group(1).replace("&amp;", "&")).text)[:6] == [0, 1, 2, 3, 4, 5]
    with sqlite3.connect(store.path) as conn:  # NEES target 2: 2.1 is best, then 1.5 (ratio 1.33), then 3.5
        for i, nees in ((0, 3.5), (1, 1.5), (2, 2.1)):
            conn.execute("UPDATE jobs SET metrics = json_set(metrics, '$.landmark_nees_mean', ?) WHERE id = ?",
                         (nees, jid(i)))
    assert row_ids(client.get("/runs", params={"sort": "m.landmark_nees_mean"}).text)[:3] == [2, 1, 0]
    assert row_ids(client.get("/runs", params={"sort": "-m.landmark_nees_mean"}).text)[:3] == [0, 1, 2]


def headings(page: str) -> list[str]:
    """The column headings of the runs table, in order, as text."""
    head = page.split('id="runs-table"')[1].split("</thead>")[0]
    return [re.sub(r"<[^>]+>|[▲▼↓↑]|≈\S+", "", h).strip() for h in re.findall(r"<th[^>]*>(.*?)</th>", head, re.S)]


def test_columns_results_first_and_chosen_in_the_url(table: tuple[TestClient, Store]) -> None:
    """The run's name first (pinned), the metric columns next, then the others; ``cols`` and ``show`` choose and
    order them; the metric menu lists the metrics of the listed runs only."""
    client, _ = table
    first = headings(client.get("/runs").text)
    assert first[:3] == ["run", "ape_rmse_m", "status"] and "commit" in first and "made by" in first
    assert "started" not in first  # hidden by default, in the menu
    page = client.get("/runs", params={"cols": "poses_scored,ape_rmse_m", "show": "seed,commit"}).text
    assert headings(page) == ["run", "poses_scored", "ape_rmse_m", "seed", "commit"]
    assert '<th class="name pin">' in page and '<td class="name pin">' in page
    menu = page.split('id="metric-menu"')[1].split("</ol>")[0]
    assert re.findall(r'name="cols" value="(\w+)"', menu) == ["poses_scored", "ape_rmse_m"]  # chosen first
    assert "landmark_rmse_m" not in menu  # no listed run reports it
    others = page.split('id="other-menu"')[1].split("</ol>")[0]
    assert re.findall(r'name="show" value="(\w+)"', others)[:2] == ["seed", "commit"]
    again = parse_view({"cols": ["", "poses_scored", "ape_rmse_m"], "show": ["", "seed", "commit"]})  # the form
    assert again.url() == "/runs?cols=poses_scored%2Cape_rmse_m&show=seed%2Ccommit"
    r = client.get("/runs", params={"show": "colour"})
    assert r.status_code == 422 and "unknown column 'colour'" in html.unescape(r.text)


def test_commit_made_by_and_long_names(table: tuple[TestClient, Store]) -> None:
    """The commit column shows a short sha linked to its runs; made by names the person, and for a pushed run
    where it came from; a long name is cut by the page's style, whole in its tooltip; the CSV has both."""
    client, store = table
    long_name = "a sweep of the range noise " * 4
    store.set_labels(jid(2), Labels(long_name.strip()))
    with sqlite3.connect(store.path) as conn:
        conn.execute("UPDATE jobs SET made_by = 'ana' WHERE id = ?", (jid(1),))
        conn.execute("UPDATE jobs SET made_by = 'ci', source = ? WHERE id = ?",
                     (json.dumps({"pushed_by": "ci", "origin": "lab-pc-3", "address": "10.0.0.7"}), jid(0)))
    page = client.get("/runs").text
    row0 = page.split(f'id="run-{jid(0)}"')[1].split("</tr>")[0]
    assert ">abcd1111</a>" in row0 and "ci, pushed from lab-pc-3" in row0
    link = re.search(r'<a class="sha" href="([^"]+)"', row0)
    assert link is not None and row_ids(client.get(html.unescape(link.group(1))).text) == [2, 1, 0]
    row1 = page.split(f'id="run-{jid(1)}"')[1].split("</tr>")[0]
    assert ">ana</td>" in row1
    assert f'class="run-name" href="/ui/jobs/{jid(2)}" title="{long_name.strip()}"' in page
    rows = list(csv.reader(io.StringIO(client.get("/runs.csv").text)))
    assert rows[0][16:18] == ["commit", "made_by"]
    assert [(x[16], x[17]) for x in rows if x[0] == jid(0)] == [(COMMITS[0], "ci, pushed from lab-pc-3")]
    job_page = client.get(f"/ui/jobs/{jid(2)}").text
    assert long_name.strip() in job_page  # the whole name on the job's page


def group_rows(page: str) -> list[tuple[str, str, list[str]]]:
    """The groups table: (group name, runs, metric cells as text), in order."""
    body = page.split('id="groups-table"')[1].split("</tbody>")[0]
    out = []
    for row in re.findall(r'<tr class="group".*?</tr>', body, re.S):
        name = re.search(r'<span class="group-name"[^>]*>(.*?)</span>', row, re.S)
        cells = re.findall(r"<td[^>]*>(.*?)</td>", row, re.S)
        assert name is not None
        text = [re.sub(r"<[^>]+>", "", c).strip() for c in cells]
        out.append((html.unescape(name.group(1)), text[1], text[2:]))
    return out


def test_groups_have_known_mean_spread_and_count(table: tuple[TestClient, Store]) -> None:
    """group=pipeline: odometry (runs 0, 2, 4, 6, 8; ape 0, 0.2, 0.4) and dslam (1, 3, 5, 7; 0.1, 0.3, 0.5) with
    n, mean ± sample standard deviation, min and max on hover; sorted best first; each links to its runs."""
    client, _ = table
    page = client.get("/runs", params={"group": "pipeline", "cols": "ape_rmse_m,poses_scored",
                                       "sort": "m.ape_rmse_m"}).text
    assert group_rows(page) == [("odometry", "5", ["0.2 ± 0.2", "98 ± 2"]), ("dslam", "4", ["0.3 ± 0.2", "97 ± 2"])]
    assert 'title="3 of 5 runs: mean 0.2, std 0.2, min 0, max 0.4"' in page
    assert "2 groups of 9 runs" in page
    assert row_ids(page) == []  # groups, not runs
    worst = client.get("/runs", params={"group": "pipeline", "sort": "-m.ape_rmse_m"}).text
    assert [g[0] for g in group_rows(worst)] == ["dslam", "odometry"]
    links = re.findall(r'<a class="all-runs" href="([^"]+)"', page)
    assert [sorted(row_ids(client.get(html.unescape(u)).text)) for u in links] == [[0, 2, 4, 6, 8], [1, 3, 5, 7]]
    assert row_ids(client.get(html.unescape(links[0])).text)[:3] == [0, 2, 4]  # in the view's sort
    by_n = client.get("/runs", params={"group": "pipeline", "sort": "-n"}).text
    assert [g[1] for g in group_rows(by_n)] == ["5", "4"]


def test_groups_by_config_commit_and_two_keys(table: tuple[TestClient, Store]) -> None:
    """A config key's groups (its default one included), commits' groups, two keys at once, and filters applying
    before grouping."""
    client, _ = table
    page = client.get("/runs", params={"group": "config.range_sigma_m", "sort": "group"}).text
    assert [(g[0], g[1], g[2]) for g in group_rows(page)] == [("range_sigma_m=0.2", "1", ["0.3"]),
                                                             ("range_sigma_m=default", "8", ["0.24 ± 0.21"])]
    commits = client.get("/runs", params={"group": "commit", "sort": "m.ape_rmse_m"}).text
    assert [(g[0], g[2]) for g in group_rows(commits)] == [("abcd1111", ["0.1 ± 0.1"]), ("ef012222", ["0.4 ± 0.1"]),
                                                           ("commit unknown", [""])]
    two = client.get("/runs", params={"group": "pipeline,commit", "sort": "m.ape_rmse_m",
                                      "where": "status = succeeded"}).text
    assert [(g[0], g[1], g[2]) for g in group_rows(two)] == [
        ("dslam, abcd1111", "1", ["0.1"]), ("odometry, abcd1111", "2", ["0.1 ± 0.14"]),  # ties by name
        ("dslam, ef012222", "2", ["0.4 ± 0.14"]), ("odometry, ef012222", "1", ["0.4"])]
    bad = client.get("/runs", params={"group": "colour"})
    assert bad.status_code == 422 and "cannot group by 'colour'" in html.unescape(bad.text)


def test_groups_export_as_csv(table: tuple[TestClient, Store]) -> None:
    """A grouped view's CSV: one line per group, the keys, n, and mean, std, min, max and n of each metric."""
    client, _ = table
    page = client.get("/runs", params={"group": "pipeline,recording", "sort": "m.ape_rmse_m"}).text
    href = re.search(r'id="export-csv" href="([^"]+)"', page)
    assert href is not None
    rows = list(csv.reader(io.StringIO(client.get(html.unescape(href.group(1))).text)))
    assert rows[0] == ["pipeline", "recording", "runs", "ape_rmse_m mean", "ape_rmse_m std", "ape_rmse_m min",
                       "ape_rmse_m max", "ape_rmse_m n"]
    assert rows[1][:3] == ["odometry", "sim.mcap", "5"] and rows[2][:3] == ["dslam", "hall.mcap", "4"]
    assert [float(x) for x in rows[1][3:7]] == pytest.approx([0.2, 0.2, 0.0, 0.4]) and rows[1][7] == "3"


def add_sweep(store: Store, first: int) -> None:
    """Succeeded ekfslam runs jid(first)... of a sweep: range_sigma_m 0.05, 0.1, 0.2, 0.4, 0.8 x seeds 1, 2, 3, each
    with landmark_rmse_m = sigma / 4 + seed / 100."""
    store.cancel_job(jid(8))  # so that each claim is the new job
    k = first
    for sigma in (0.05, 0.1, 0.2, 0.4, 0.8):
        for seed in (1, 2, 3):
            store.add_job(jid(k), HALL, "ekfslam", {"range_sigma_m": sigma}, seed)
            assert store.claim_next() is not None
            store.finish_job(jid(k), "succeeded", None, {"landmark_rmse_m": sigma / 4 + seed / 100}, COMMITS[0])
            k += 1


def test_scatter_of_a_sweep_shows_a_column_per_value(table: tuple[TestClient, Store]) -> None:
    """A sweep of range_sigma_m over 5 values x 3 seeds: the scatter of landmark_rmse_m against it draws 15 dots
    at 5 x positions, each linked to its run; commit and seed scatters too."""
    client, store = table
    add_sweep(store, 100)
    page = client.get("/runs", params={"pipeline": "ekfslam", "chart": "landmark_rmse_m",
                                       "x": "config.range_sigma_m"}).text
    svg = page.split('id="runs-chart"')[1].split("</svg>")[0]
    dots = re.findall(r'<a href="/ui/jobs/([0-9a-f]{32})" class="mark">.*?<circle cx="([\d.]+)"', svg, re.S)
    assert len(dots) == 15 and {int(i, 16) for i, _ in dots} == set(range(100, 115))
    assert len({x for _, x in dots}) == 5
    assert "range_sigma_m 0.8, landmark_rmse_m 0.23" in html.unescape(svg)
    by_commit = client.get("/runs", params={"chart": "ape_rmse_m", "x": "commit"}).text
    assert by_commit.split('id="runs-chart"')[1].count("<circle") == 6  # the six runs with the metric
    by_day = client.get("/runs", params={"chart": "ape_rmse_m", "x": "created"}).text
    assert ">05-02</text>" in by_day or ">05-03</text>" in by_day  # days on the axis
    for params, message in (({"chart": "nope"}, "chart: unknown metric 'nope'"),
                            ({"chart": "ape_rmse_m", "x": "colour"}, "cannot chart against 'colour'")):
        r = client.get("/runs", params=params)
        assert r.status_code == 422 and message in html.unescape(r.text)


def test_parallel_coordinates_of_a_sweep(table: tuple[TestClient, Store]) -> None:
    """chart=METRIC&x=parallel: an axis per config key that differs among the listed runs, then the metric; a line
    per run linked to it, through the sweep's value and its metric, the best (lowest) run drawn darkest."""
    client, store = table
    add_sweep(store, 200)
    page = client.get("/runs", params={"pipeline": "ekfslam", "where": "landmark_rmse_m > 0", "cols": "",
                                       "chart": "landmark_rmse_m", "x": "parallel"}).text
    svg = html.unescape(page.split('id="runs-chart"')[1].split("</svg>")[0])
    assert "parallel coordinates of " in svg and "over config.range_sigma_m, landmark_rmse_m" in svg, svg[:400]
    lines = re.findall(r'<a href="/ui/jobs/([0-9a-f]{32})" class="mark"><title>([^<]*)</title><polyline points="'
                       r'([^"]+)"[^>]*stroke-opacity="([\d.]+)"', svg)
    sweep = {int(i, 16): (title, pts, float(o)) for i, title, pts, o in lines if 200 <= int(i, 16) < 215}
    assert len(sweep) == 15
    assert "range_sigma_m 0.8, landmark_rmse_m 0.21" in sweep[212][0]  # sigma 0.8, seed 1: 0.8 / 4 + 0.01
    best = min(sweep.values(), key=lambda v: float(v[0].rsplit(" ", 1)[1]))
    assert best[2] == max(v[2] for v in sweep.values()) and "range_sigma_m 0.05" in best[0]
    assert all(len(v[1].split()) == 2 for v in sweep.values())  # two axes: the key that differs, the metric


def test_group_chart_has_a_row_per_group(table: tuple[TestClient, Store]) -> None:
    """chart=METRIC on a grouped view: a row per group in the table's order (mean, spread, min-max), each linked
    to the group's runs; without groups or x, a line saying what to choose."""
    client, _ = table
    page = client.get("/runs", params={"group": "pipeline", "chart": "ape_rmse_m", "sort": "m.ape_rmse_m"}).text
    svg = page.split('id="runs-chart"')[1].split("</svg>")[0]
    rows = re.findall(r'<a href="([^"]+)" class="mark"><title>([^<]+)</title>', svg)
    assert [html.unescape(t).split(":")[0] for _, t in rows] == ["odometry", "dslam"]
    assert "mean 0.2 ± 0.2 over 3 runs; min 0, max 0.4" in html.unescape(rows[0][1])  # 3 of 5 report it
    assert sorted(row_ids(client.get(html.unescape(rows[1][0])).text)) == [1, 3, 5, 7]
    alone = client.get("/runs", params={"chart": "ape_rmse_m"}).text
    assert 'id="runs-chart-empty"' in alone and "Group the runs" in alone
