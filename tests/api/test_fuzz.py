"""A bounded schemathesis pass over the OpenAPI schema: no generated request gets a 5xx, answers match the schema."""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any

import pytest
from conftest import write_tiny_recording
from hypothesis import HealthCheck, given, settings
from hypothesis.errors import Unsatisfiable

with warnings.catch_warnings():
    warnings.simplefilter("ignore", UserWarning)  # StarletteDeprecationWarning: it asks for httpx2; httpx works
    from fastapi.testclient import TestClient

from slamreplay.api.app import create_app
from slamreplay.api.service.executor import Outcome, Task
from slamreplay.api.service.settings import Settings

schemathesis = pytest.importorskip("schemathesis")  # the `dev` extra has it; skip in a bare install
TOKEN = "fuzz-token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
EXAMPLES_PER_OPERATION_AND_MODE = 8


class ParkedExecutor:
    """No slots: the scheduler starts no thread, so jobs stay queued and no process is spawned."""

    slots = 0

    def start(self) -> None:
        """Nothing to start."""

    def run(self, task: Task) -> Outcome:
        raise AssertionError("a parked executor never runs a task")

    def cancel(self, job_id: str) -> None:
        """Nothing runs, so nothing to stop."""

    def close(self) -> None:
        """Nothing to stop."""


@pytest.mark.slow
def test_no_server_errors(tmp_path: Path) -> None:
    """Positive and negative requests generated for every operation get no 5xx and answers that match the schema."""
    app = create_app(Settings(allowed_hosts=("testserver",),
                              data_dir=tmp_path, max_upload_bytes=1 << 20, token=TOKEN), executor=ParkedExecutor())
    client = TestClient(app, headers=AUTH)
    rec = write_tiny_recording(tmp_path / "tiny.mcap", n=20)
    rid = client.post("/recordings", content=rec.read_bytes()).json()["id"]
    client.post("/jobs", json={"recording_id": rid, "pipeline": "odometry"})
    schema = schemathesis.openapi.from_asgi("/openapi.json", app, headers=AUTH)
    # Not about server errors or the schema: Starlette's 405 answers list only the methods of the first route
    # matching a path; and a schema-valid upload may still be refused for its content (415/422).
    excluded = [schemathesis.checks.allow_header_conformance, schemathesis.checks.positive_data_acceptance]
    operations = [result.ok() for result in schema.get_all_operations()]
    assert len(operations) >= 17
    for operation in operations:
        for mode in schemathesis.GenerationMode:

            @given(case=operation.as_strategy(generation_mode=mode))
            @settings(max_examples=EXAMPLES_PER_OPERATION_AND_MODE, deadline=None, derandomize=True, database=None,
                      suppress_health_check=list(HealthCheck))
            def check(case: Any) -> None:
                # a simulation route takes 5-13 s with its defaults on a loaded 2-core machine (schemathesis waits
                # 10 s by default): how fast it answers is service_load's question, not this test's
                case.call_and_validate(headers=AUTH, excluded_checks=excluded, timeout=120)

            try:
                check()
            except Unsatisfiable:
                assert mode == schemathesis.GenerationMode.NEGATIVE, operation.label  # nothing to break: no inputs
