"""A Python client of the slamreplay service: upload, submit, wait, list, label, compare and push, in a few lines.

    from slamreplay.api.client import Client

    server = Client("http://slam.lan:8000")            # the token from $SLAMREPLAY_TOKEN, or token="..."
    rec = server.upload("sim.mcap")                       # skipped when the server holds the same file
    job = server.submit(rec["id"], "dslam", seed=0, tags=["ci"])
    done = server.wait(job["id"])                          # ClientError if it fails, with its error
    for j in server.jobs(pipeline="dslam", where="ape_rmse_m < 0.1"):   # every page, newest first
        print(j["id"], j["metrics"]["ape_rmse_m"])
    server.label(job["id"], note="baseline for PR 12")
    print(server.compare(done["id"], other_id)["worse"])
    server.push("runs/laptop-run", origin="my laptop")    # a run made elsewhere, beside the server's own

Only the standard library (urllib): nothing to install beyond slamreplay. Each failure is a `ClientError` whose
message is the server's one line (or why the server could not be reached) and whose ``status`` is the HTTP code
(0: no answer). ``slamreplay push`` is this client on the command line.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import tarfile
import tempfile
import time
import urllib.error
import urllib.parse
import urllib.request
from collections.abc import Callable, Iterable, Iterator, Mapping
from pathlib import Path
from typing import IO, Any

TOKEN_ENV = "SLAMREPLAY_TOKEN"
ENDED = ("succeeded", "failed", "cancelled", "interrupted")


class ClientError(Exception):
    """What the server said was wrong (``status``: its HTTP code), or why it could not be asked (``status`` 0)."""

    def __init__(self, message: str, status: int = 0) -> None:
        super().__init__(message)
        self.status = status


def _detail(body: bytes) -> str:
    try:
        detail = json.loads(body).get("detail")
    except (ValueError, AttributeError):
        return body[:300].decode("utf-8", "replace").strip() or "no details"
    if isinstance(detail, list):  # FastAPI's validation errors: the first field at fault
        first = detail[0] if detail and isinstance(detail[0], dict) else {}
        where = ".".join(str(p) for p in first.get("loc", [])[1:])
        return f"{where}: {first.get('msg', detail)}" if where else str(first.get("msg", detail))
    return str(detail)


class Client:
    """The service at ``url`` (``http://HOST:PORT``), with a person's token or the shared one (else
    ``$SLAMREPLAY_TOKEN``; none on an open server)."""

    def __init__(self, url: str, token: str | None = None, timeout_s: float = 120.0) -> None:
        parts = urllib.parse.urlsplit(url.strip())
        if parts.scheme not in ("http", "https") or not parts.netloc:
            raise ClientError(f"server {url!r}: give its address as http://HOST:PORT (or https://)")
        self.url = url.strip().rstrip("/")
        self.token = token if token is not None else (os.environ.get(TOKEN_ENV) or None)
        self.timeout_s = timeout_s

    # -- HTTP -------------------------------------------------------------------------------------

    def request(self, method: str, path: str, *, params: Mapping[str, Any] | None = None, body: Any = None,
                data: bytes | IO[bytes] | None = None, content_type: str | None = None,
                length: int | None = None) -> tuple[int, dict[str, str], Any]:
        """(status, headers, the decoded JSON body) of one call; ClientError for a 4xx or 5xx or no answer."""
        query = urllib.parse.urlencode([(k, x) for k, v in (params or {}).items() if v is not None
                                        for x in (v if isinstance(v, list | tuple) else [v])])
        url = self.url + urllib.parse.quote(path, safe="/%?=&:;,+@") + ("?" + query if query else "")
        headers = {"Accept": "application/json"}
        if self.token:
            headers["Authorization"] = f"Bearer {self.token}"
        if body is not None:
            data, content_type = json.dumps(body).encode(), "application/json"
        if content_type:
            headers["Content-Type"] = content_type
        if length is not None:
            headers["Content-Length"] = str(length)
        req = urllib.request.Request(url, data=data, method=method, headers=headers)
        try:
            with urllib.request.urlopen(req, timeout=self.timeout_s) as r:
                raw = r.read()
                return r.status, dict(r.headers.items()), json.loads(raw) if raw else None
        except urllib.error.HTTPError as err:
            raise ClientError(_detail(err.read()), err.code) from None
        except (urllib.error.URLError, OSError) as err:
            reason = getattr(err, "reason", err)
            raise ClientError(f"cannot reach {self.url}: {reason}") from None

    def get(self, path: str, **params: Any) -> Any:
        return self.request("GET", path, params=params)[2]

    # -- recordings ---------------------------------------------------------------------------------

    def recording(self, sha256: str) -> dict[str, Any] | None:
        """The stored recording with this sha256, or None."""
        try:
            return dict(self.get(f"/recordings/{sha256}"))
        except ClientError as err:
            if err.status == 404:
                return None
            raise

    def upload(self, path: str | Path, filename: str | None = None) -> dict[str, Any]:
        """Upload a recording (streamed), unless the server already holds the same file (by sha256)."""
        path = Path(path)
        sha = file_sha256(path)
        known = self.recording(sha)
        if known is not None:
            return known
        with open(path, "rb") as f:
            return dict(self.request("POST", "/recordings", params={"filename": filename or path.name}, data=f,
                                     content_type="application/octet-stream", length=path.stat().st_size)[2])

    # -- jobs ------------------------------------------------------------------------------------------

    def submit(self, recording: str, pipeline: str, *, config: Mapping[str, Any] | None = None, seed: int = 0,
               topic_map: Mapping[str, str] | None = None, name: str | None = None, tags: Iterable[str] = (),
               note: str | None = None) -> dict[str, Any]:
        """Queue a job (``recording``: its id or an unambiguous prefix), with its name, tags and note."""
        spec = {"recording_id": recording, "pipeline": pipeline, "config": dict(config or {}), "seed": seed,
                "topic_map": dict(topic_map or {}), "name": name, "tags": list(tags), "note": note}
        return dict(self.request("POST", "/jobs", body=spec)[2])

    def job(self, job_id: str) -> dict[str, Any]:
        return dict(self.get(f"/jobs/{job_id}"))

    def wait(self, job_id: str, timeout_s: float | None = None, poll_s: float = 1.0,
             on_progress: Callable[[dict[str, Any]], None] | None = None) -> dict[str, Any]:
        """The job once it has ended; ClientError when it did not succeed (its error) or ``timeout_s`` passed."""
        start = time.monotonic()
        while True:
            job = self.job(job_id)
            if on_progress is not None:
                on_progress(job)
            if job["status"] in ENDED:
                if job["status"] != "succeeded":
                    raise ClientError(f"job {job_id} {job['status']}: {job.get('error') or 'no error given'}")
                return job
            if timeout_s is not None and time.monotonic() - start > timeout_s:
                raise ClientError(f"job {job_id} is still {job['status']} after {timeout_s:g} s")
            time.sleep(poll_s)

    def jobs(self, *, recording: str | None = None, pipeline: str | None = None, status: str | None = None,
             tag: str | None = None, q: str | None = None, where: str | None = None,
             page_size: int = 200) -> Iterator[dict[str, Any]]:
        """Every job matching the filters (as the runs table's), newest first, fetched a page at a time."""
        params: dict[str, Any] = {"recording": recording, "pipeline": pipeline, "status": status, "tag": tag,
                                  "q": q, "where": where, "limit": page_size}
        path: str | None = "/jobs"
        while path is not None:
            _, headers, page = self.request("GET", path, params=params)
            yield from page
            link = {k.lower(): v for k, v in headers.items()}.get("link", "")
            m = re.fullmatch(r'<([^>]+)>; rel="next"', link.strip())
            path, params = (m.group(1), {}) if m else (None, {})

    def count(self, **filters: Any) -> int:
        """How many jobs match the filters (``jobs``'s), without fetching them."""
        params = {k: v for k, v in filters.items() if v is not None} | {"limit": 1}
        headers = self.request("GET", "/jobs", params=params)[1]
        return int({k.lower(): v for k, v in headers.items()}["x-total-count"])

    def label(self, job_id: str, **fields: Any) -> dict[str, Any]:
        """Change a job's ``name``, ``tags`` (all of them) or ``note``; the others are kept (None clears one)."""
        unknown = set(fields) - {"name", "tags", "note"}
        if unknown:
            raise ClientError(f"label: {', '.join(sorted(unknown))} is not a label (name, tags, note)")
        if isinstance(fields.get("tags"), str):
            fields["tags"] = [fields["tags"]]
        return dict(self.request("PATCH", f"/jobs/{job_id}", body=fields)[2])

    def cancel(self, job_id: str) -> dict[str, Any]:
        return dict(self.request("DELETE", f"/jobs/{job_id}")[2])

    def compare(self, a: str, b: str, tolerance: Iterable[str] = ()) -> dict[str, Any]:
        """Job B against job A (``slamreplay diff``'s verdicts): changes, metric deltas, ``worse``, ``lost``."""
        return dict(self.get("/diff", a=a, b=b, tolerance=list(tolerance) or None))

    def submit_suite(self, text: str, *, json_format: bool = False, tags: Iterable[str] = (),
                     note: str | None = None) -> dict[str, Any]:
        """Run a suite file's text (TOML, or JSON) on the server; its new jobs carry ``tags`` and ``note``."""
        return dict(self.request("POST", "/suites", params={"tags": list(tags) or None, "note": note},
                                 data=text.encode(), content_type="application/json" if json_format
                                 else "application/toml")[2])

    # -- runs made elsewhere -------------------------------------------------------------------------

    def push(self, run_dir: str | Path, *, recording: str | Path | None = None, origin: str | None = None,
             name: str | None = None, tags: Iterable[str] = (), note: str | None = None) -> tuple[dict[str, Any], bool]:
        """Put a run directory made elsewhere on the server: (its job, whether it is new there). The recording it
        replayed is uploaded first when the server lacks it: ``recording``, else the path its manifest records
        (when that file is still there and the same); ClientError when neither is."""
        run_dir = Path(run_dir)
        manifest = read_manifest(run_dir)
        sha = str((manifest.get("recording") or {}).get("sha256") or "")
        if re.fullmatch(r"[0-9a-f]{64}", sha) and self.recording(sha) is None:
            self.upload(find_recording(manifest, sha, recording))
        with tempfile.TemporaryFile() as archive:
            pack(run_dir, archive)
            size = archive.tell()
            archive.seek(0)
            status, _, job = self.request(
                "POST", "/runs", params={"origin": origin if origin is not None else default_origin(), "name": name,
                                         "tags": list(tags) or None, "note": note},
                data=archive, content_type="application/gzip", length=size)
        return dict(job), status == 201


    def push_suite(self, folder: str | Path, *, recording: str | Path | None = None, origin: str | None = None,
                   name: str | None = None, tags: Iterable[str] = (), note: str | None = None,
                   on_run: Callable[[Path, dict[str, Any] | None, bool, ClientError | None], None] | None = None,
                   ) -> dict[str, Any] | None:
        """Push every cell's run of a ``suite run`` output folder, then the suite itself (its name, its file and
        which job each cell became), so that the server's page, comparisons and history of that suite's name count
        it. ``on_run(run_dir, job, new, error)`` hears of each run. The suite as the server keeps it; None when a
        run was refused (the suite is not recorded without all its runs)."""
        folder = Path(folder)
        about = read_json(folder / "suite.json", "a `suite run` output folder (no suite.json)")
        cells: list[dict[str, Any]] = []
        refused = False
        for run in suite_runs(folder):
            try:
                job, new = self.push(run, recording=recording, origin=origin, name=name, tags=tags, note=note)
            except ClientError as err:
                if err.status == 0 and "cannot reach" in str(err):
                    raise
                refused = True
                if on_run is not None:
                    on_run(run, None, False, err)
                continue
            if on_run is not None:
                on_run(run, job, new, None)
            cell = read_json(run / "cell.json", "a suite's run (no cell.json)").get("cell") or {}
            keys = ("recording", "recording_seed", "pipeline", "variant", "seed", "config")
            cells.append({k: cell.get(k) for k in keys if k in cell} | {"job_id": job["id"]})
        if refused or not cells:
            return None
        suite_file = Path(str(about.get("suite") or ""))
        text = suite_file.read_text() if suite_file.name and suite_file.is_file() else ""
        return dict(self.request("POST", "/runs/suites", body={
            "name": str(about.get("suite_name") or folder.name), "text": text, "cells": cells})[2])


def read_json(path: Path, what: str) -> dict[str, Any]:
    try:
        doc = json.loads(path.read_text())
    except FileNotFoundError:
        raise ClientError(f"{path.parent} is not {what}") from None
    except (OSError, ValueError) as err:
        raise ClientError(f"{path} is unreadable: {err}") from None
    if not isinstance(doc, dict):
        raise ClientError(f"{path} is not a JSON object")
    return doc


def suite_runs(folder: Path) -> list[Path]:
    """The run directories of a ``suite run`` output folder's cells, in its results' order."""
    results = folder / "results.jsonl"
    try:
        rows = [json.loads(line) for line in results.read_text().splitlines() if line.strip()]
    except (OSError, ValueError) as err:
        raise ClientError(f"{results} is unreadable: {err}") from None
    out = []
    for row in rows:
        run = Path(str(row.get("run_dir") or ""))
        run = run if run.is_absolute() else folder / run
        if (run / "manifest.json").is_file():
            out.append(run)
    return list(dict.fromkeys(out))


def file_sha256(path: Path) -> str:
    h = hashlib.sha256()
    try:
        with open(path, "rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
    except OSError as err:
        raise ClientError(f"cannot read {path}: {err.strerror or err}") from None
    return h.hexdigest()


def read_manifest(run_dir: Path) -> dict[str, Any]:
    """A run directory's manifest; ClientError when ``run_dir`` is not a run directory."""
    path = run_dir / "manifest.json"
    if not path.is_file():
        raise ClientError(f"{run_dir} is not a run directory (no manifest.json): give a folder `slamreplay run`, "
                          "`suite run` or `evaluate` wrote")
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError) as err:
        raise ClientError(f"{path} is unreadable: {err}") from None
    if not isinstance(doc, dict):
        raise ClientError(f"{path} is not a run's manifest (not a JSON object)")
    return doc


def find_recording(manifest: Mapping[str, Any], sha: str, given: str | Path | None) -> Path:
    """The local file of the recording a run replayed: ``given`` (checked), else the manifest's path if the file
    there is still the same."""
    if given is not None:
        path = Path(given)
        if file_sha256(path) != sha:
            raise ClientError(f"{path} is not the recording the run replayed (its sha256 differs from "
                              f"{sha[:12]}...)")
        return path
    recorded = Path(str((manifest.get("recording") or {}).get("path") or ""))
    if recorded.name and recorded.is_file() and file_sha256(recorded) == sha:
        return recorded
    raise ClientError(f"the server does not hold the recording the run replayed ({sha[:12]}..., "
                      f"{recorded.name or 'no path recorded'}) and it is not at its recorded path: give it with "
                      "--recording FILE")


def pack(run_dir: Path, into: IO[bytes]) -> None:
    """A run directory as the gzipped tar ``POST /runs`` takes (its files, not links; hidden files left out)."""
    with tarfile.open(fileobj=into, mode="w:gz") as tar:
        for path in sorted(run_dir.rglob("*")):
            rel = path.relative_to(run_dir)
            if path.is_symlink() or any(p.startswith(".") for p in rel.parts) or not path.is_file():
                continue
            tar.add(path, arcname=rel.as_posix(), recursive=False)


def default_origin() -> str:
    """Where a run is pushed from: the CI job's page when on GitHub Actions or GitLab CI, else this host's name."""
    env = os.environ
    if env.get("GITHUB_ACTIONS") and env.get("GITHUB_RUN_ID"):
        return (f"{env.get('GITHUB_SERVER_URL', 'https://github.com')}/{env.get('GITHUB_REPOSITORY', '')}/actions/"
                f"runs/{env['GITHUB_RUN_ID']}")
    if env.get("GITLAB_CI") and env.get("CI_JOB_URL"):
        return env["CI_JOB_URL"]
    import socket

    return socket.gethostname()
