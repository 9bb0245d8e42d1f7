"""The per-file bound: a file of many valid-CRC bomb chunks is refused at once by inspect, run and recover, while
the densest legitimate recordings (black frames, empty messages at 1 ms) read as before."""

from __future__ import annotations

import io
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from mcap.records import Chunk
from mcap.writer import CompressionType, Writer

from slamreplay.recorder.codec.mcap_io import MAX_RECORDS_PER_BYTE, McapFile, decompress
from slamreplay.recorder.messages import CameraImage
from slamreplay.recorder.writer import Recorder
from tests.fuzz.bombs import bomb_file

SECONDS = 30  # each command, on a loaded 2-core machine (about 2 s idle)


def _cli(*args: str) -> tuple[int, str, str, float]:
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "slamreplay.api.cli", *args], capture_output=True, text=True,
                          timeout=10 * SECONDS, check=False)
    return proc.returncode, proc.stdout, proc.stderr, time.perf_counter() - t0


@pytest.fixture(scope="module")
def bomb(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """300 chunks of 1,000,000 identical /odom messages each (83 MB uncompressed, 7 KB compressed): 2 MB that
    unpack to 25 GB and 300 million messages, every CRC right, every chunk within MAX_CHUNK_BYTES and
    MAX_CHUNK_RECORDS."""
    path = tmp_path_factory.mktemp("bomb") / "bomb.mcap"
    size = bomb_file(path, chunks=300, records=1_000_000)
    assert size < 3_000_000
    return path


LIMIT = r"holds more than [\d,]+ records in [\d,]+ compressed bytes, above slamreplay's limit of 2 per byte of chunk"


def test_inspect_reports_the_bomb(bomb: Path) -> None:
    """inspect: health corrupt, the bomb named in its problem line (its convention: exit 1), in seconds."""
    code, out, err, seconds = _cli("inspect", str(bomb))
    assert code == 1 and "health: corrupt" in out and seconds < SECONDS, (out, err, seconds)
    assert any(line.startswith("  problem:") and "decompression bomb" in line for line in out.splitlines()), out


def test_run_refuses_the_bomb(bomb: Path, tmp_path: Path) -> None:
    """run: exit 2, one line naming the first bomb chunk, in seconds."""
    code, _, err, seconds = _cli("run", str(bomb), "--pipeline", "odometry", "--out", str(tmp_path / "run"), "-q")
    assert code == 2 and err.count("\n") == 1 and seconds < SECONDS, (err, seconds)
    assert err.startswith("slamreplay: error: ") and "decompression bomb" in err, err


def test_recover_refuses_the_bomb(bomb: Path, tmp_path: Path) -> None:
    """recover: exit 2, one line, nothing written; the chunks after its damage budget are not decompressed."""
    out_file = tmp_path / "fixed.mcap"
    code, _, err, seconds = _cli("recover", str(bomb), "--out", str(out_file))
    assert code == 2 and err.count("\n") == 1 and seconds < SECONDS, (err, seconds)
    assert "holds no readable message" in err and "decompression bomb" in err and not out_file.exists(), err


def _chunks_read(path: Path) -> int:
    """Every chunk of ``path`` decompressed and checked; how many."""
    n = 0
    with McapFile(path) as f:
        for offset, _, record in f.records():
            if isinstance(record, Chunk):
                decompress(record, offset)
                n += 1
    return n


def test_black_frames_read(tmp_path: Path) -> None:
    """slamreplay's own recording of black 1080p frames (thousands to one per chunk) reads whole."""
    path = tmp_path / "black.mcap"
    with Recorder(path, source={}) as rec:
        for k in range(20):
            rec.write("/camera/image", CameraImage(1000 + k, np.zeros((1080, 1920), np.uint8), "camera", "raw"))
    assert _chunks_read(path) == 20


@pytest.mark.parametrize("same_time", [False, True])
def test_the_densest_recordings_read(tmp_path: Path, same_time: bool) -> None:
    """Empty messages every 1 ms (0.26 records per chunk byte), or all at one time with sequence numbers (0.98):
    under MAX_RECORDS_PER_BYTE, every chunk reads."""
    buf = io.BytesIO()
    w = Writer(buf, compression=CompressionType.ZSTD, chunk_size=1 << 20)
    w.start()
    channel = w.register_channel("/tick", "json", w.register_schema("tick", "jsonschema", b"{}"))
    for k in range(200_000):
        t = 5 if same_time else k * 1_000_000
        w.add_message(channel, log_time=t, publish_time=t, data=b"", sequence=k)
    w.finish()
    (tmp_path / "dense.mcap").write_bytes(buf.getvalue())
    assert MAX_RECORDS_PER_BYTE >= 2 and _chunks_read(tmp_path / "dense.mcap") > 1
