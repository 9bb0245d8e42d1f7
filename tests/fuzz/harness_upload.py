"""Coverage-guided fuzzing (atheris, libFuzzer) of the multipart/form-data upload parser (api/service/multipart.py).

Contract: for any body and Content-Type, ``form_file`` gives (file name, chunks of the ``file`` part),
or an ``ApiError`` with a 4xx status (``FormError`` 422, ``TooLargeError`` 413) whose message is one
line, both when it finds the part and while the chunks are read. Any other exception, a timeout or a
memory blow-up is a finding. The parser is driven directly (no HTTP), so an execution takes microseconds.

Input layout: the first line is the Content-Type (``multipart/form-data; boundary=...``), the first byte
after it sets the size of the chunks the body arrives in (1..256 bytes: a boundary split across
chunks), and the rest is the body; the upload limit is 4 KiB so that TooLargeError is reached too.

    nice -n 10 .venv/bin/python tests/fuzz/harness_upload.py -max_total_time=600 -timeout=10 \\
        -rss_limit_mb=2048 -max_len=8192 -artifact_prefix=/tmp/fuzz-upload/ \\
        /tmp/fuzz-upload/corpus tests/fuzz/corpus/upload
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import sys
from collections.abc import AsyncIterator

try:
    import atheris
except ImportError:  # replaying stored cases (tests/fuzz/test_harness_cases.py) needs no fuzzer
    atheris = None

with atheris.instrument_imports(include=["slamreplay", "python_multipart"]) if atheris else contextlib.nullcontext():
    from slamreplay.api.service.errors import ApiError
    from slamreplay.api.service.multipart import form_file

LIMIT = 4096
# python-multipart logs every malformed byte as a warning: millions of lines in a run, and slow
logging.disable(logging.CRITICAL)
_LOOP = asyncio.new_event_loop()  # one loop for all executions: a new one each time would dominate the cost


def _one_line_4xx(err: ApiError) -> None:
    """A finding when a refusal is not a 4xx answer with a one-line message."""
    text = str(err)
    if not 400 <= err.status < 500:
        raise AssertionError(f"{type(err).__name__} answers {err.status}, not 4xx: {text[:300]!r}")
    if not text or "\n" in text:
        raise AssertionError(f"{type(err).__name__} message is not one line: {text[:300]!r}")


def split(data: bytes) -> tuple[str, int, bytes]:
    """(Content-Type, chunk size, body) of a fuzz input (see the module docstring)."""
    head, sep, rest = data.partition(b"\n")
    if not sep:
        return "multipart/form-data; boundary=b", 64, data
    size = 1 + (rest[0] if rest else 63)
    return head.decode("latin-1"), size, rest[1:]


async def _stream(body: bytes, size: int) -> AsyncIterator[bytes]:
    for i in range(0, len(body), size):
        yield body[i:i + size]


async def _upload(content_type: str, size: int, body: bytes) -> int:
    name, chunks = await form_file(_stream(body, size), content_type, LIMIT)
    assert name is None or isinstance(name, str)
    return sum([len(c) async for c in chunks])


def test_one_input(data: bytes) -> None:
    """Parse ``data`` as a form upload and read its file part to the end; only a 4xx ApiError may come out."""
    content_type, size, body = split(data)
    try:
        n = _LOOP.run_until_complete(_upload(content_type, size, body))
        assert 0 <= n <= len(body)
    except ApiError as err:
        _one_line_4xx(err)


def main() -> None:
    """libFuzzer's command line: corpus directories and -flags (see the module docstring)."""
    atheris.Setup(sys.argv, test_one_input)
    atheris.Fuzz()


if __name__ == "__main__":
    main()
