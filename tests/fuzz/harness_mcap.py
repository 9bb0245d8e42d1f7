"""Coverage-guided fuzzing (atheris, libFuzzer) of the MCAP reader and ``recover``.

Contract: for any bytes, ``inspect_recording`` (what ``slamreplay inspect`` prints), ``RecordingReader``
(open, then decode every message of every mapped topic) and ``recover`` give a result or slamreplay's own
error (``RecorderError``, ``ReplayError`` and their subclasses), whose message is one line. Any other
exception, a timeout (``-timeout``) or a memory blow-up (``-rss_limit_mb``) is a finding: libFuzzer writes
the input to ``crash-*``/``timeout-*``/``oom-*``.

    .venv/bin/python -m pip install -e ".[fuzz]"
    nice -n 10 .venv/bin/python tests/fuzz/harness_mcap.py -max_total_time=1800 -timeout=20 \\
        -rss_limit_mb=4096 -max_len=65536 -artifact_prefix=/tmp/fuzz-mcap/ /tmp/fuzz-mcap/corpus tests/fuzz/corpus/mcap

The first directory is the working corpus libFuzzer grows (never the committed one: libFuzzer writes new
inputs into it), the second the seed corpus committed here (tiny valid recordings of each kind slamreplay
reads: landmarks, PNG and raw images, lz4 and uncompressed chunks, ROS 2 CDR). A finding is kept under
tests/fuzz/cases/ once fixed.
"""

from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path

import atheris

# only our code and the MCAP libraries carry coverage: numpy, OpenCV and protobuf would swamp it
with atheris.instrument_imports(include=["slamreplay", "mcap", "mcap_protobuf", "mcap_ros2"]):
    from slamreplay.recorder.errors import RecorderError
    from slamreplay.recorder.recover import recover
    from slamreplay.replay.engine.reader import RecordingReader
    from slamreplay.replay.errors import ReplayError
    from slamreplay.replay.tools.inspect import inspect_recording

# tmpfs when there is one: recover fsyncs what it writes, and every execution writes a file
_DIR = Path(tempfile.mkdtemp(prefix="fuzz-mcap-", dir="/dev/shm" if os.path.isdir("/dev/shm") else None))
_IN, _OUT = _DIR / "in.mcap", _DIR / "out.mcap"


def _one_line(err: Exception) -> None:
    """A finding when one of our errors is not the promised single line."""
    text = str(err)
    if not text or "\n" in text:
        raise AssertionError(f"{type(err).__name__} message is not one line: {text[:300]!r}")


def test_one_input(data: bytes) -> None:
    """Inspect ``data`` as a recording, decode all its messages, then recover it; only slamreplay's own errors
    may come out, each on one line."""
    _IN.write_bytes(data)
    try:
        for problem in inspect_recording(_IN)["problems"]:
            if "\n" in problem:
                raise AssertionError(f"inspect reports a problem over several lines: {problem[:300]!r}")
    except (RecorderError, ReplayError) as err:
        _one_line(err)
    try:
        reader = RecordingReader(_IN)
        for _ in reader.messages():
            pass
    except (RecorderError, ReplayError) as err:
        _one_line(err)
    _OUT.unlink(missing_ok=True)
    _OUT.with_name(_OUT.name + ".partial").unlink(missing_ok=True)
    try:
        recover(_IN, _OUT)
    except RecorderError as err:
        _one_line(err)


def main() -> None:
    """libFuzzer's command line: corpus directories and -flags (see the module docstring)."""
    atheris.Setup(sys.argv, test_one_input)
    atheris.Fuzz()


if __name__ == "__main__":
    main()
