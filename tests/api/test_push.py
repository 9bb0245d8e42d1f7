"""Runs from anywhere (issue 40, item 5): ``slamreplay push`` and `slamreplay.api.client.client` against a served team
server: three runs of a `suite run` made in another folder pushed (their recording uploaded on the way), listed
and compared beside the server's own run of the same recording; the same run pushed again is the same job; a run
that lies about its files, an archive with a link or a path out of its folder, a run of a recording the server
lacks, a viewer, and a server that is not there are each refused in one line."""

from __future__ import annotations

import io
import json
import shutil
import tarfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from conftest import write_tiny_recording
from patience import deadline as give_up_at
from test_cli import run_cli

from slamreplay.api.client.client import Client, ClientError
from slamreplay.replay.runs import suite_run


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, dict[str, str], Path]]:
    """A team server on a loopback port (a runner and a viewer): its URL, their tokens and its data folder."""
    import uvicorn
    from service_helpers import InlineExecutor

    from slamreplay.api.app import create_app
    from slamreplay.api.cli.listen import listen
    from slamreplay.api.service.settings import Settings

    data = tmp_path_factory.mktemp("server")
    app = create_app(Settings(data_dir=data, workers=1), executor=InlineExecutor())
    tokens = {role: app.state.jobs.store.add_user(f"{role}1", role) for role in ("runner", "viewer")}
    sock = listen("127.0.0.1", 0)
    srv = uvicorn.Server(uvicorn.Config(app, log_level="warning"))
    thread = threading.Thread(target=srv.run, kwargs={"sockets": [sock]}, daemon=True)
    thread.start()
    deadline = give_up_at(60)
    while not srv.started:
        assert thread.is_alive() and time.monotonic() < deadline, "the server did not start"
        time.sleep(0.05)
    try:
        yield f"http://127.0.0.1:{sock.getsockname()[1]}", tokens, data
    finally:
        srv.should_exit = True
        thread.join(30)
        sock.close()


@pytest.fixture(scope="module")
def made_elsewhere(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A `suite run` output folder on "a laptop": odometry on one recording, seeds 0, 1 and 2."""
    folder = tmp_path_factory.mktemp("laptop")
    write_tiny_recording(folder / "tiny.mcap", n=60)
    (folder / "suite.toml").write_text('name = "laptop odometry"\nseeds = [0, 1, 2]\n[recordings.tiny]\n'
                                       'path = "tiny.mcap"\n[pipelines.odometry]\n')
    from slamreplay.api.cli.command import main

    assert main(["suite", "run", str(folder / "suite.toml"), "--out", str(folder / "results"), "-q"]) == 0
    return folder / "results"


def test_three_suite_runs_pushed_and_compared_with_the_servers_own(
        server: tuple[str, dict[str, str], Path], made_elsewhere: Path, capsys: pytest.CaptureFixture[str]) -> None:
    url, tokens, _ = server
    code, out, err = run_cli(["push", str(made_elsewhere), "--server", url, "--token", tokens["runner"],
                              "--origin", "laptop of rui", "--tag", "laptop"], capsys)
    assert code == 0, err
    lines = out.strip().splitlines()
    assert len(lines) == 5 and lines[-1] == f"3 of 3 runs on {url}", out
    assert all(": pushed as job " in line and "odometry seed" in line for line in lines[:3]), out
    assert "suite 'laptop odometry' (3 cells) recorded as" in lines[3], out

    runner = Client(url, tokens["runner"])
    pushed = list(runner.jobs(tag="laptop"))
    assert sorted(j["seed"] for j in pushed) == [0, 1, 2] and runner.count(tag="laptop") == 3
    rows = {r["seed"]: r for r in suite_run.read_results(made_elsewhere)}
    for job in pushed:
        assert job["status"] == "succeeded" and job["made_by"] == "runner1"
        assert job["source"]["origin"] == "laptop of rui" and job["source"]["pushed_by"] == "runner1"
        assert job["source"]["run_id"] == json.loads((Path(rows[job["seed"]]["run_dir"]) / "manifest.json")
                                                     .read_text())["run_id"]
        for name, value in rows[job["seed"]]["metrics"].items():
            assert job["metrics"][name] == pytest.approx(value, rel=1e-12), name

    # the server's own run of the same recording (uploaded by the push) and seed: the same numbers
    rid = pushed[0]["recording_id"]
    own = runner.wait(runner.submit(rid[:8], "odometry", seed=0)["id"], timeout_s=120)
    assert own["source"] is None and own["made_by"] == "runner1"
    twin = next(j for j in pushed if j["seed"] == 0)
    verdict = runner.compare(own["id"], twin["id"])
    assert verdict["worse"] == [] and len(verdict["metrics"]) >= 5
    assert all(m["delta"] == 0 for m in verdict["metrics"] if m["delta"] is not None), verdict["metrics"]

    viewer = Client(url, tokens["viewer"])
    ids = ",".join(j["id"] for j in [own, *pushed])
    page = viewer.request("GET", "/compare", params={"runs": ids})[2]
    assert {r["id"] for r in page["runs"]} == {own["id"], *(j["id"] for j in pushed)}, page.keys()

    # the suite is the server's too: its page and the history of its name count it
    suite = next(x for x in runner.get("/suites") if x["name"] == "laptop odometry")
    assert suite["progress"]["status"] == "succeeded" and {c["job_id"] for c in suite["cells"]} == {
        j["id"] for j in pushed}
    history = runner.get("/history/suites/laptop odometry")
    assert [v["code_version"] for v in history["versions"]] == [pushed[0]["git_commit"]], history["versions"]
    assert history["versions"][0]["status"] == "succeeded" and history["series"], history

    again = run_cli(["push", str(made_elsewhere), "--server", url, "--token", tokens["runner"]], capsys)
    assert again[0] == 0 and again[1].count("already on the server as job") == 3, again
    assert runner.count(tag="laptop") == 3 and runner.count(pipeline="odometry") == 4
    assert f"recorded as {suite['id'][:8]}" in again[1]  # the same suite, not a second one
    assert [x["id"] for x in runner.get("/suites") if x["name"] == "laptop odometry"] == [suite["id"]]


def _tar(files: dict[str, bytes], link: str | None = None) -> bytes:
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz") as tar:
        for name, data in files.items():
            info = tarfile.TarInfo(name)
            info.size = len(data)
            tar.addfile(info, io.BytesIO(data))
        if link is not None:
            info = tarfile.TarInfo(link)
            info.type, info.linkname = tarfile.SYMTYPE, "/etc/passwd"
            tar.addfile(info)
    return buf.getvalue()


def _run_files(run_dir: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in run_dir.iterdir() if p.is_file()}


def _post(client: Client, body: bytes) -> ClientError:
    with pytest.raises(ClientError) as caught:
        client.request("POST", "/runs", data=body, content_type="application/gzip", length=len(body))
    return caught.value


def test_bad_pushes_are_refused_in_one_line_and_keep_nothing(
        server: tuple[str, dict[str, str], Path], made_elsewhere: Path, tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    url, tokens, data = server
    runner = Client(url, tokens["runner"])
    before = runner.count()
    run_dir = Path(suite_run.read_results(made_elsewhere)[0]["run_dir"])
    files = _run_files(run_dir)

    lied = dict(files, **{"trajectory.tum": files["trajectory.tum"].replace(b"0", b"1", 1)})
    err = _post(runner, _tar(lied))
    assert err.status == 422 and "trajectory.tum" in str(err) and "sha256" in str(err), err
    assert "is not a file or a folder" in str(_post(runner, _tar(files, link="evil")))
    out_of_folder = _post(runner, _tar({"../../escape.txt": b"x", **files}))
    assert out_of_folder.status == 422 and "relative names" in str(out_of_folder)
    assert "not a tar archive" in str(_post(runner, b"PK\x03\x04 a zip file"))
    running = json.loads(files["manifest.json"]) | {"status": "running"}
    assert "only ended runs" in str(_post(runner, _tar(dict(files, **{"manifest.json": json.dumps(running)
                                                                       .encode()}))))
    assert "no manifest.json" in str(_post(runner, _tar({"metrics.json": files["metrics.json"]})))
    bad_metric = {"format": 1, "metrics": {"ape_rmse_m": {"value": "small"}}}
    assert "not a number" in str(_post(runner, _tar(dict(files, **{"metrics.json": json.dumps(bad_metric)
                                                                  .encode()}))))
    unknown = json.loads(files["manifest.json"])
    unknown["recording"] = {**unknown["recording"], "sha256": "ab" * 32}
    missing = _post(runner, _tar(dict(files, **{"manifest.json": json.dumps(unknown).encode()})))
    assert missing.status == 404 and "upload it first" in str(missing)
    viewer = _post(Client(url, tokens["viewer"]), _tar(files))
    assert viewer.status == 403 and "push runs made elsewhere" in str(viewer)
    assert runner.count() == before
    assert [p.name for p in data.rglob(".push-*")] == []  # no half-kept run

    # the command line: a run whose recording moved, and a server that is not there
    moved = tmp_path / "moved"
    shutil.copytree(run_dir, moved)
    doc = json.loads((moved / "manifest.json").read_text())
    doc["recording"] = {**doc["recording"], "sha256": "cd" * 32, "path": str(tmp_path / "gone.mcap")}
    (moved / "manifest.json").write_text(json.dumps(doc))
    code, _, err_text = run_cli(["push", str(moved), "--server", url, "--token", tokens["runner"]], capsys)
    assert code == 2 and "give it with --recording FILE" in err_text, err_text
    code, _, err_text = run_cli(["push", str(run_dir), "--server", "http://127.0.0.1:9"], capsys)
    assert code == 2 and err_text.count("\n") == 1 and "cannot reach http://127.0.0.1:9" in err_text, err_text
    code, _, err_text = run_cli(["push", str(tmp_path), "--server", url], capsys)
    assert code == 2 and err_text.count("\n") == 1 and "is not a run directory" in err_text, err_text


def test_client_errors_say_what_to_do() -> None:
    with pytest.raises(ClientError, match="http://HOST:PORT"):
        Client("slam.lan:8000")

