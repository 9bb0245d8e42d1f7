"""kill -9 of `slamreplay suite run` and of `slamreplay serve`, and the service on a full disk.

Trial functions for ``benchmarks/crash_consistency.py`` (``--commands suite,serve``) and, with
fewer trials, ``tests/api/test_crash.py``. Each returns a dict with ``problems`` (empty: the
trial kept every rule):

- suite: `suite run` (a recording on disk and a simulated one, odometry and dslam, 2 seeds,
  ``--jobs 2``) killed after a random delay. A killed results directory is never read as
  finished (``compare`` exits 2 "unfinished suite run"); every row of its results.jsonl that
  says succeeded has its manifest and metrics; no cell directory without a row holds
  ``metrics.json`` or ``run.rrd`` beside an unfinished manifest; the simulated-recording cache
  holds no partial recording under a final name; the same command again resumes (cells that
  had finished are reused, not run again) and ends with results equal to an unkilled run's
  (``compare`` exits 0: replay is deterministic).
- serve: the server killed after a random delay while jobs run and a slow upload streams in;
  its worker processes end with it; restarted, the service lists only whole recordings (each
  downloads with the sha256 it is listed under) and no temporary upload; ``GET /diff`` answers
  409 for every job that has not succeeded; then every job ends succeeded, failed with a
  reason or interrupted with a reason (none stays queued or running), each succeeded job with
  its manifest (status succeeded, run id = job id), metrics and run.rrd.
- serve, disk full (a small tmpfs; needs the right to mount one): an upload that does not fit
  is 507 and nothing is listed or left; a job whose run does not fit fails naming the full
  disk; ``/healthz`` and listings answer throughout; once space is freed, the same upload and
  job succeed.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import httpx

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))  # patience: deadlines scaled by load
from patience import deadline as give_up_at

REPO = Path(__file__).resolve().parents[1]
SLAMREPLAY = [sys.executable, "-m", "slamreplay.api.cli"]
SUITE = """seeds = [0, 1]
[recordings.long]
path = "{recording}"
[recordings.sim]
sim = "sim-landmarks"
args = {{ duration-s = {sim_s} }}
seeds = [7]
{pipelines}
"""


def suite_text(recording: Path, light: bool) -> str:
    """The suite of the trials: odometry and dslam over the recording and a 60 s simulation (light: odometry only,
    a 10 s simulation)."""
    pipelines = "[pipelines.odometry]" + ("" if light else "\n[pipelines.dslam]")
    return SUITE.format(recording=recording, sim_s=10 if light else 60, pipelines=pipelines)


def _env(cache: Path | None = None) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("SLAMREPLAY_")}
    env["PYTHONUNBUFFERED"] = "1"
    if cache is not None:
        env["SLAMREPLAY_CACHE"] = str(cache)
    return env


def cli(*args: str | Path, cache: Path | None = None, timeout: float = 600) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*SLAMREPLAY, *map(str, args)], capture_output=True, text=True, timeout=timeout, cwd=REPO,
                          env=_env(cache))


def children(pid: int) -> list[int]:
    """Pids of the processes whose parent is ``pid``."""
    out = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            out.append(int(stat.parent.name))
    return out


def alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


# ---------------------------------------------------------------------------------------
# suite run


def suite_setup(work: Path, duration_s: float = 240.0, light: bool = False) -> tuple[Path, Path]:
    """A recording for the suite and an unkilled results directory to compare against: (recording, baseline)."""
    recording = work / "suite-rec.mcap"
    cli("record", "sim-landmarks", "--duration-s", str(duration_s), "--seed", "1", "--out", recording, "-q")
    suite = work / "suite-base.toml"
    suite.write_text(suite_text(recording, light))
    baseline = work / "suite-baseline"
    p = cli("suite", "run", suite, "--out", baseline, "--jobs", "2", "-q", cache=work / "cache-base")
    if p.returncode != 0:
        raise SystemExit(f"the baseline suite run failed: {p.stderr}")
    return recording, baseline


def _rows(out: Path) -> list[dict[str, Any]]:
    try:
        return [json.loads(line) for line in (out / "results.jsonl").read_text().splitlines()]
    except FileNotFoundError:
        return []


def _wait_for_rows(proc: subprocess.Popen[bytes], out: Path, rows: int, timeout_s: float = 120.0) -> None:
    """Return once ``out/results.jsonl`` holds ``rows`` rows (or the process ended, or ``timeout_s`` passed)."""
    deadline = give_up_at(timeout_s)
    while proc.poll() is None and len(_rows(out)) < rows and time.monotonic() < deadline:
        time.sleep(0.01)


def suite_trial(work: Path, recording: Path, baseline: Path, k: int, delay_s: float, light: bool = False,
                after_rows: int = 0) -> dict[str, Any]:
    """Kill `suite run` ``delay_s`` after it has written ``after_rows`` result rows, check what it left, run it
    again into the same --out."""
    suite = work / f"suite-{k}.toml"
    suite.write_text(suite_text(recording, light))  # the same cells as the baseline
    out, cache = work / f"suite-{k}", work / f"cache-{k}"
    shutil.copytree(work / "cache-base", cache)  # the simulated recording, as a user's cache would hold it ...
    for f in (cache / "recordings").glob("*.mcap"):
        f.unlink()  # ... or not: simulated afresh, so a kill can also land in the simulation
    args = ["suite", "run", suite, "--out", out, "--jobs", "2", "-q"]
    proc = subprocess.Popen([*SLAMREPLAY, *map(str, args)], cwd=REPO, env=_env(cache), stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    t: dict[str, Any] = {"command": "suite run", "trial": k, "kill_after_s": round(delay_s, 2), "problems": []}
    if after_rows:
        t["kill_after_rows"] = after_rows
        _wait_for_rows(proc, out, after_rows)
    try:
        t["finished"] = proc.wait(delay_s) == 0
        workers: list[int] = []
    except subprocess.TimeoutExpired:
        workers = children(proc.pid)
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        t["finished"] = False
    deadline = give_up_at(5)
    while any(alive(w) for w in workers) and time.monotonic() < deadline:
        time.sleep(0.1)
    if any(alive(w) for w in workers):
        t["problems"].append("worker processes outlived the killed suite run by 5 s")
    rows = _rows(out)
    t["rows_before_rerun"] = len(rows)
    for r in rows:
        run_dir = Path(r["run_dir"])
        if r["status"] == "succeeded":
            manifest = json.loads((run_dir / "manifest.json").read_text())
            if manifest.get("status") != "succeeded" or not (run_dir / "metrics.json").is_file():
                t["problems"].append(f"row {run_dir.name} says succeeded, its run does not")
    listed = {Path(r["run_dir"]).name for r in rows}
    for run_dir in (out / "runs").iterdir() if (out / "runs").is_dir() else []:
        if run_dir.name in listed:
            continue
        try:
            status = json.loads((run_dir / "manifest.json").read_text()).get("status")
        except (OSError, ValueError):
            status = None
        if status is not None and status != "succeeded" and (run_dir / "metrics.json").exists():
            t["problems"].append(f"unlisted cell {run_dir.name}: a {status} run beside a metrics.json")
        elif status is None and ((run_dir / "metrics.json").exists() or (run_dir / "run.rrd").exists()):
            # killed between its last file and its manifest (the commit point): every reader must say unfinished
            d = cli("diff", run_dir, run_dir)
            if d.returncode != 2 or "not a finished run" not in d.stderr:
                t["problems"].append(f"unlisted cell {run_dir.name} has no manifest, yet diff reads it: "
                                     f"exit {d.returncode}, {d.stderr.strip()[:200]!r}")
    for f in (cache / "recordings").glob("*.mcap") if (cache / "recordings").is_dir() else []:
        if (ins := cli("inspect", f)).returncode != 0:
            t["problems"].append(f"the cache holds {f.name} under its final name, unhealthy: {ins.stdout[-200:]!r}")
    try:
        t["said_finished"] = json.loads((out / "suite.json").read_text()).get("finished") is True
    except (OSError, ValueError):
        t["said_finished"] = False
    if not t["finished"] and t["said_finished"]:  # killed on its way out, after its last write: complete
        if (c := cli("compare", baseline, out)).returncode != 0:
            t["problems"].append(f"compare of results killed after they said finished: exit {c.returncode}, "
                                 f"{c.stdout[-300:]!r}")
    elif not t["finished"]:
        c = cli("compare", baseline, out)
        want = "unfinished suite run" if (out / "suite.json").is_file() else str(out)
        if c.returncode != 2 or want not in c.stderr:
            t["problems"].append(f"compare of the killed results: exit {c.returncode}, {c.stderr.strip()[:300]!r}")
    done_before = {r["key"] for r in rows if r["status"] == "succeeded"}
    again = cli(*args, cache=cache)
    if again.returncode != 0:
        t["problems"].append(f"the same suite run again: exit {again.returncode}, {again.stderr.strip()[:300]!r}")
        return t
    rows = _rows(out)
    reused = {r["key"] for r in rows if r.get("cached")}
    t["reused"], t["rerun"] = len(reused), len(rows) - len(reused)
    if not done_before <= reused:
        t["problems"].append(f"{len(done_before - reused)} finished cell(s) were run again instead of reused")
    if json.loads((out / "suite.json").read_text()).get("finished") is not True:
        t["problems"].append("suite.json does not say finished after the re-run")
    c = cli("compare", baseline, out)
    if c.returncode != 0:
        t["problems"].append(f"compare with an unkilled run: exit {c.returncode}, {c.stdout[-300:]!r}")
    shutil.rmtree(cache, ignore_errors=True)
    return t


# ---------------------------------------------------------------------------------------
# serve


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


@contextmanager
def server(data: Path, log: Path, workers: int = 2, env: dict[str, str] | None = None
           ) -> Iterator[tuple[subprocess.Popen[bytes], httpx.Client]]:
    """`slamreplay serve` on a free loopback port over ``data``; stopped with SIGTERM unless killed meanwhile."""
    port = free_port()
    cmd = [*SLAMREPLAY, "serve", "--port", str(port), "--data-dir", str(data), "--workers", str(workers),
           "--log-level", "warning"]
    with open(log, "ab") as f:
        proc = subprocess.Popen(cmd, cwd=REPO, env=_env() | (env or {}), stdout=f, stderr=subprocess.STDOUT)
    base = f"http://127.0.0.1:{port}"
    try:
        deadline = give_up_at(60)
        while True:
            if proc.poll() is not None:
                raise RuntimeError(f"server exited with {proc.returncode}: {log.read_text()[-2000:]}")
            try:
                if httpx.get(f"{base}/healthz", timeout=1).status_code == 200:
                    break
            except httpx.TransportError:
                pass
            if time.monotonic() > deadline:
                raise RuntimeError("server did not come up in 60 s")
            time.sleep(0.1)
        with httpx.Client(base_url=base, timeout=60) as client:
            yield proc, client
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


def slow_upload(url: str, body: bytes, chunk: int, pause_s: float, result: dict[str, Any]) -> None:
    """POST ``body`` to /recordings in chunks with pauses; ``result['status']``: the answer, or the error."""

    def chunks() -> Iterator[bytes]:
        for i in range(0, len(body), chunk):
            yield body[i:i + chunk]
            time.sleep(pause_s)

    try:
        r = httpx.post(f"{url}/recordings", content=chunks(), headers={"Content-Length": str(len(body))}, timeout=60)
        result["status"] = r.status_code
    except httpx.HTTPError as err:
        result["status"] = type(err).__name__


def check_store(data: Path, client: httpx.Client) -> list[str]:
    """What is wrong with the recordings a (restarted) server lists: partial ones, leftovers."""
    problems = []
    for rec in client.get("/recordings").json():
        got = hashlib.sha256(client.get(f"/recordings/{rec['id']}/download").content).hexdigest()
        if got != rec["id"]:
            problems.append(f"recording {rec['id'][:12]} is listed but its file is not whole")
    left = [p.name for p in (data / "recordings").iterdir() if p.name.startswith(".")]
    if left:
        problems.append(f"temporary files stay after the restart: {left}")
    return problems


def check_job(data: Path, job: dict[str, Any]) -> list[str]:
    """What is wrong with an ended job: no reason for a failure, a succeeded job without its files."""
    run_dir = data / "runs" / job["id"]
    if job["status"] in ("queued", "running"):
        return [f"job {job['id'][:8]} is still {job['status']}"]
    if job["status"] != "succeeded":
        if not job["error"]:
            return [f"job {job['id'][:8]} ended {job['status']} without a reason"]
        if (run_dir / "metrics.json").exists() or (run_dir / "run.rrd").exists():
            return [f"job {job['id'][:8]} ended {job['status']} yet its run directory holds metrics or run.rrd"]
        return []
    try:
        manifest = json.loads((run_dir / "manifest.json").read_text())
    except (OSError, ValueError) as err:
        return [f"succeeded job {job['id'][:8]} has no readable manifest: {err}"]
    if manifest.get("status") != "succeeded" or manifest.get("run_id") != job["id"]:
        return [f"succeeded job {job['id'][:8]}: manifest status {manifest.get('status')}, run id "
                f"{manifest.get('run_id')}"]
    if not (run_dir / "metrics.json").is_file() or not (run_dir / "run.rrd").is_file():
        return [f"succeeded job {job['id'][:8]} lacks metrics.json or run.rrd"]
    return []


def wait_jobs(client: httpx.Client, ids: list[str], timeout_s: float = 300) -> dict[str, dict[str, Any]]:
    deadline, done = give_up_at(timeout_s), {}
    while len(done) < len(ids) and time.monotonic() < deadline:
        for job_id in set(ids) - set(done):
            job = client.get(f"/jobs/{job_id}").json()
            if job["status"] not in ("queued", "running"):
                done[job_id] = job
        time.sleep(0.2)
    return done


def serve_setup(work: Path, recording: Path) -> tuple[Path, str, str]:
    """A data directory with ``recording`` and one succeeded job: (data dir, recording id, baseline job id)."""
    data = work / "serve-data"
    data.mkdir()
    with server(data, work / "serve.log") as (_, client):
        rid = client.post("/recordings", content=recording.read_bytes()).json()["id"]
        base = client.post("/jobs", json={"recording_id": rid, "pipeline": "odometry"}).json()["id"]
        wait_jobs(client, [base])
    return data, rid, base


def serve_trial(work: Path, data: Path, rid: str, base: str, upload: bytes, k: int, delay_s: float,
                jobs: int = 4) -> dict[str, Any]:
    """Kill the server ``delay_s`` after jobs were submitted (a slow upload streaming meanwhile); restart; check."""
    t: dict[str, Any] = {"command": "serve", "trial": k, "kill_after_s": round(delay_s, 2), "problems": []}
    log = work / "serve.log"
    up: dict[str, Any] = {}
    with server(data, log) as (proc, client):
        ids = [client.post("/jobs", json={"recording_id": rid, "pipeline": "odometry", "seed": 100 * k + s}).json()
               ["id"] for s in range(jobs)]
        uploader = threading.Thread(target=slow_upload, args=(str(client.base_url), upload, 32 << 10, 0.05, up))
        uploader.start()
        time.sleep(delay_s)
        before = {j["id"]: j["status"] for j in client.get("/jobs", params={"limit": 1000}).json() if j["id"] in ids}
        workers = children(proc.pid)
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        uploader.join(60)
    t["at_kill"] = {s: list(before.values()).count(s) for s in sorted(set(before.values()))}
    t["upload"] = up.get("status")
    t["partial_uploads_left"] = len(list((data / "recordings").glob(".upload-*.partial")))
    deadline = give_up_at(5)
    while any(alive(w) for w in workers) and time.monotonic() < deadline:
        time.sleep(0.1)
    if any(alive(w) for w in workers):
        t["problems"].append("worker processes outlived the killed server by 5 s")
    with server(data, log) as (_, client):
        t["problems"] += check_store(data, client)
        listed = {r["id"] for r in client.get("/recordings").json()}
        uploaded = hashlib.sha256(upload).hexdigest()
        if (uploaded in listed) != (t["upload"] in (200, 201)):
            t["problems"].append(f"the slow upload answered {t['upload']} but is listed: {uploaded in listed}")
        for job_id in ids:
            job = client.get(f"/jobs/{job_id}").json()
            if job["status"] != "succeeded":
                d = client.get("/diff", params={"a": base, "b": job_id})
                if d.status_code != 409:
                    t["problems"].append(f"GET /diff of unfinished job {job_id[:8]}: {d.status_code}")
        ended = wait_jobs(client, ids)
        for job_id in ids:
            t["problems"] += check_job(data, ended.get(job_id) or client.get(f"/jobs/{job_id}").json())
        statuses = [j["status"] for j in ended.values()]
        t["ended"] = {s: statuses.count(s) for s in sorted(set(statuses))}
        t["requeued"] = sum(1 for j in ended.values() if j["note"] and "re-queued" in j["note"])
        if uploaded in listed:
            client.delete(f"/recordings/{uploaded}")
    return t


def serve_disk_full(work: Path, recording: Path, upload: bytes) -> dict[str, Any]:
    """The service over a small tmpfs filled up by uploads, then by a job's run."""
    t: dict[str, Any] = {"command": "serve (disk full)", "trial": 0, "problems": []}
    mnt = work / "serve-small"
    mnt.mkdir()
    size = recording.stat().st_size + (4 << 20)
    m = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(mnt)], capture_output=True,
                       text=True)
    if m.returncode != 0:
        t["skipped"] = f"cannot mount a small tmpfs ({m.stderr.strip()[:120]})"
        return t
    try:
        with server(mnt, work / "serve-small.log") as (_, client):
            r = client.post("/recordings", content=recording.read_bytes())
            rid = r.json()["id"]
            filler = mnt / "filler"
            with open(filler, "wb") as f:  # fill the disk but for about 64 KiB
                try:
                    while True:
                        f.write(b"\0" * (64 << 10))
                        f.flush()
                except OSError:
                    pass
            os.truncate(filler, max(filler.stat().st_size - (64 << 10), 0))
            answer = client.post("/recordings", content=upload)
            t["upload"] = answer.status_code
            if answer.status_code != 507 or "no space left on the device" not in answer.json().get("detail", ""):
                t["problems"].append(f"upload onto the full disk: {answer.status_code} {answer.text[:200]}")
            if client.get("/healthz").status_code != 200 or len(client.get("/recordings").json()) != 1:
                t["problems"].append("the service stopped serving, or listed a partial upload")
            job = client.post("/jobs", json={"recording_id": rid, "pipeline": "odometry"})
            if job.status_code == 202:
                ended = wait_jobs(client, [job.json()["id"]], 120)
                end = ended.get(job.json()["id"], {"status": "still running"})
                t["job"] = f"{end['status']}: {str(end.get('error'))[:160]}"
                if end["status"] != "failed" or "no space left" not in (end.get("error") or ""):
                    t["problems"].append(f"a job on the full disk ended {t['job']}")
                t["problems"] += check_job(mnt, end) if "id" in end else []
            elif job.status_code != 507:
                t["problems"].append(f"POST /jobs on the full disk: {job.status_code} {job.text[:200]}")
            t["problems"] += check_store(mnt, client)
            filler.unlink()
            if (again := client.post("/recordings", content=upload)).status_code != 201:
                t["problems"].append(f"upload once space was freed: {again.status_code}")
            job = client.post("/jobs", json={"recording_id": rid, "pipeline": "odometry", "seed": 1}).json()
            if (end := wait_jobs(client, [job["id"]], 120).get(job["id"], {})).get("status") != "succeeded":
                t["problems"].append(f"a job once space was freed: {end.get('status')} {end.get('error')}")
        if "Traceback" in (work / "serve-small.log").read_text():
            t["problems"].append("the server log holds a traceback")
    finally:
        subprocess.run(["umount", "-l", str(mnt)], check=False)  # lazy: connections may still be open
    return t
