"""Uploads as a form (curl -F file=@run.mcap) work like raw bodies; a wrong field or a mangled file says what to do."""

from __future__ import annotations

import warnings
from pathlib import Path

import pytest
from conftest import write_tiny_recording
from service_helpers import InlineExecutor

with warnings.catch_warnings():
    warnings.simplefilter("ignore", UserWarning)  # StarletteDeprecationWarning: it asks for httpx2; httpx works
    from fastapi.testclient import TestClient

from slamreplay.api.app import create_app
from slamreplay.api.service.settings import Settings


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_tiny_recording(tmp_path_factory.mktemp("rec") / "tiny.mcap")


@pytest.fixture
def client(tmp_path: Path) -> TestClient:
    return TestClient(create_app(Settings(allowed_hosts=("testserver",),
                                          data_dir=tmp_path, workers=1, max_upload_bytes=200_000),
                                 executor=InlineExecutor()))


def test_form_upload_is_stored_like_a_raw_one(client: TestClient, recording: Path) -> None:
    """-F file=@tiny.mcap: 201 with the part's file name; the same bytes raw: 200, same id (content-addressed)."""
    data = recording.read_bytes()
    r = client.post("/recordings", files={"file": ("tiny.mcap", data, "application/octet-stream")})
    assert r.status_code == 201, r.text
    body = r.json()
    assert body["filename"] == "tiny.mcap" and body["size_bytes"] == len(data)
    assert {t["topic"] for t in body["topics"]} >= {"/odom", "/ground_truth/pose"}
    again = client.post("/recordings", content=data)
    assert again.status_code == 200 and again.json()["id"] == body["id"]
    assert client.get(f"/recordings/{body['id']}/download").content == data


def test_form_with_other_fields_and_a_filename_query(client: TestClient, recording: Path) -> None:
    """Fields before the file are skipped; ?filename= wins over the part's file name."""
    r = client.post("/recordings", params={"filename": "label.mcap"}, data={"note": "first drive"},
                    files={"file": ("x.mcap", recording.read_bytes())})
    assert r.status_code == 201 and r.json()["filename"] == "label.mcap"


def test_wrong_field_names_the_right_one(client: TestClient, recording: Path) -> None:
    """-F upload=@tiny.mcap: 422 naming the field 'file' and the command; a form with no file: 422 too."""
    r = client.post("/recordings", files={"upload": ("tiny.mcap", recording.read_bytes())})
    assert r.status_code == 422
    detail = r.json()["detail"]
    assert "in the field 'upload'" in detail and "field 'file'" in detail and "curl -F file=@run.mcap" in detail
    assert r.json()["field"] == "file"
    r = client.post("/recordings", data={"recording": "tiny.mcap"}, files={"x": ("", b"")})
    assert r.status_code == 422 and "field 'file'" in r.json()["detail"]
    r = client.post("/recordings", content=b"--b--\r\n", headers={"content-type": "multipart/form-data; boundary=b"})
    assert r.status_code == 422 and "no field 'file'" in r.json()["detail"]


def test_malformed_forms(client: TestClient, recording: Path) -> None:
    """No boundary, a broken body, a body cut inside the file part: 422 saying so, nothing stored."""
    r = client.post("/recordings", content=b"abc", headers={"content-type": "multipart/form-data"})
    assert r.status_code == 422 and "without a boundary" in r.json()["detail"]
    r = client.post("/recordings", content=b"no boundary here at all",
                    headers={"content-type": "multipart/form-data; boundary=xyz"})
    assert r.status_code == 422 and "malformed multipart" in r.json()["detail"]
    head = (b"--xyz\r\nContent-Disposition: form-data; name=\"file\"; filename=\"t.mcap\"\r\n\r\n"
            + recording.read_bytes()[:500])
    r = client.post("/recordings", content=head, headers={"content-type": "multipart/form-data; boundary=xyz"})
    assert r.status_code == 422 and "ended inside the 'file' part" in r.json()["detail"]
    assert client.get("/recordings").json() == []


def test_form_errors_about_the_file(client: TestClient) -> None:
    """Over the size limit: 413; not an MCAP: 415 naming the part's file name."""
    r = client.post("/recordings", files={"file": ("big.mcap", b"\0" * 300_000)})
    assert r.status_code == 413 and "SLAMREPLAY_MAX_UPLOAD_BYTES" in r.json()["detail"]
    r = client.post("/recordings", data={"pad": "x" * 300_000}, files={"file": ("late.mcap", b"x")})
    assert r.status_code == 413
    r = client.post("/recordings", files={"file": ("notes.txt", b"just text\n")})
    assert r.status_code == 415 and "notes.txt is not an MCAP file" in r.json()["detail"]


def test_not_mcap_says_how_to_send_it(client: TestClient, recording: Path) -> None:
    """415 hints: line breaks stripped (curl -d) -> --data-binary or -F; a form without its header; anything else."""
    stripped = recording.read_bytes().replace(b"\r", b"").replace(b"\n", b"")
    detail = client.post("/recordings", content=stripped).json()["detail"]
    assert "line breaks were removed" in detail and "--data-binary @run.mcap" in detail
    form_body = b"--abc\r\nContent-Disposition: form-data; name=\"file\"\r\n\r\nxx\r\n--abc--\r\n"
    r = client.post("/recordings", content=form_body, headers={"content-type": "application/octet-stream"})
    assert r.status_code == 415 and "curl -F file=@run.mcap" in r.json()["detail"]
    r = client.post("/recordings", content=b"hello world")
    assert r.status_code == 415 and "--data-binary" in r.json()["detail"] and "-F file=@" in r.json()["detail"]


def test_openapi_documents_both_bodies(client: TestClient) -> None:
    """The upload's request body lists the raw file and the form with its field `file`."""
    body = client.get("/openapi.json").json()["paths"]["/recordings"]["post"]["requestBody"]["content"]
    assert set(body) == {"application/octet-stream", "multipart/form-data"}
    assert body["multipart/form-data"]["schema"]["required"] == ["file"]
