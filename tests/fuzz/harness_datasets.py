"""Coverage-guided fuzzing (atheris, libFuzzer) of the public-dataset importers: MRCLAM, Victoria Park, image folders.

Contract: for any dataset folder built from the fuzz input, the importer, called as ``slamreplay record NAME DIR
--out FILE`` calls it (``get_importer(NAME).record(options, ...)``), writes the recording ``FILE`` or raises
slamreplay's own error (``RecorderError``, ``ReplayError``: exit 2) whose message is one line, and writes
nothing on file descriptor 2 (where numpy's warnings and C libraries such as libpng and libtiff print). Any
other exception, a timeout or a memory blow-up is a finding.

Input layout: byte 0 picks the importer, byte 1 its options, and the rest is cut at ``SEPARATOR`` into the
files of the folder:

- 0, ``record mrclam DIR --robot R``: ``Barcodes.dat``, ``Landmark_Groundtruth.dat``, ``RobotN_Odometry.dat``,
  ``RobotN_Groundtruth.dat``, ``RobotN_Measurement.dat`` in that order (a missing part: no such file); the
  robot files are written for N = 1..5; option bit 0 picks R = all (else 1);
- 1, ``record victoria-park DIR``: the whole rest is ``victoria_park.txt``; option bit 0 adds
  ``--no-reference``, bit 1 ``--merge-window-m 5``;
- 2, ``record images DIR``: each part is one frame, its first byte picking the suffix (``SUFFIXES``) and
  the rest its bytes, named ``frame000K.<suffix>``.

    .venv/bin/python tests/fuzz/harness_datasets.py --seeds tests/fuzz/corpus/datasets   # rewrite the seeds
    nice -n 10 .venv/bin/python tests/fuzz/harness_datasets.py -max_total_time=1800 -timeout=20 \\
        -rss_limit_mb=3072 -max_len=16384 -dict=tests/fuzz/datasets.dict -artifact_prefix=/tmp/fuzz-datasets/ \\
        /tmp/fuzz-datasets/corpus tests/fuzz/corpus/datasets
"""

from __future__ import annotations

import contextlib
import os
import shutil
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

try:
    import atheris
except ImportError:  # replaying stored cases (tests/fuzz/test_harness_cases.py) needs no fuzzer
    atheris = None

SEPARATOR = b"\n%%\n"
IMPORTERS = ("mrclam", "victoria-park", "images")

# our code only (numpy, scipy and OpenCV would swamp the map). The importers and what `record` imports lazily (the
# importer modules, Victoria Park's reference solver) are loaded here, inside the instrumentation.
with atheris.instrument_imports(include=["slamreplay.recorder", "slamreplay.replay", "slamreplay.algorithms.common"]) \
        if atheris else contextlib.nullcontext():
    import slamreplay.recorder.importers.images
    import slamreplay.recorder.importers.mrclam
    import slamreplay.recorder.importers.victoria_park
    import slamreplay.replay.evaluation.landmark_reference  # noqa: F401
    from slamreplay.recorder.errors import RecorderError
    from slamreplay.recorder.importers.images import SUFFIXES
    from slamreplay.recorder.sources import get_importer
    from slamreplay.recorder.writer import partial_path
    from slamreplay.replay.errors import ReplayError

    for _name in IMPORTERS:
        get_importer(_name)  # loads each plugin's module

MRCLAM_FILES = ("Barcodes.dat", "Landmark_Groundtruth.dat", "Robot{}_Odometry.dat", "Robot{}_Groundtruth.dat",
                "Robot{}_Measurement.dat")
# tmpfs when there is one: every execution writes a folder and a recording
_DIR = Path(tempfile.mkdtemp(prefix="fuzz-datasets-", dir="/dev/shm" if os.path.isdir("/dev/shm") else None))
_DATA, _OUT = _DIR / "data", _DIR / "out.mcap"
_STDERR = _DIR / "stderr"


def build(data: bytes) -> tuple[str, dict[str, Any]]:
    """The dataset folder ``_DATA`` made from a fuzz input, and (importer, its options) as `record` parses them."""
    shutil.rmtree(_DATA, ignore_errors=True)
    _DATA.mkdir()
    name = IMPORTERS[data[0] % len(IMPORTERS)] if data else IMPORTERS[0]
    flags = data[1] if len(data) > 1 else 0
    parts = data[2:].split(SEPARATOR)
    options: dict[str, Any] = {"dir": str(_DATA), "out": str(_OUT)}
    if name == "mrclam":
        for pattern, body in zip(MRCLAM_FILES, parts, strict=False):
            for robot in range(1, 6) if "{}" in pattern else [0]:
                (_DATA / pattern.format(robot)).write_bytes(body)
        options["robot"] = "all" if flags & 1 else 1
    elif name == "victoria-park":
        (_DATA / "victoria_park.txt").write_bytes(data[2:])
        options.update(no_reference=bool(flags & 1), merge_window_m=5.0 if flags & 2 else 0.0)
    else:
        for k, part in enumerate(parts):
            suffix = SUFFIXES[part[0] % len(SUFFIXES)] if part else ".png"
            (_DATA / f"frame{k:04d}{suffix}").write_bytes(part[1:])
        options["rate_hz"] = 1.0
    return name, options


@contextlib.contextmanager
def _fd2_to_file() -> Iterator[None]:
    """File descriptor 2 (Python's stderr, and C libraries') into ``_STDERR`` for the block."""
    sys.stderr.flush()
    saved = os.dup(2)
    with open(_STDERR, "wb") as f:
        os.dup2(f.fileno(), 2)
    try:
        yield
    finally:
        sys.stderr.flush()
        os.dup2(saved, 2)
        os.close(saved)


def record(data: bytes) -> str:
    """Import the folder built from ``data`` as `slamreplay record` does: the summary line, or the error raised."""
    name, options = build(data)
    for path in (_OUT, partial_path(_OUT)):
        path.unlink(missing_ok=True)
    return str(get_importer(name).record(options, lambda done, total: None, lambda text: None))


def _one_line(err: Exception) -> None:
    """A finding when one of our errors is not the promised single line."""
    text = str(err)
    if not text or "\n" in text:
        raise AssertionError(f"{type(err).__name__} message is not one line: {text[:300]!r}")


def test_one_input(data: bytes) -> None:
    """Import the folder built from ``data``; only a recording or a one-line RecorderError/ReplayError, silently."""
    try:
        with _fd2_to_file():
            record(data)
    except (RecorderError, ReplayError) as err:
        _one_line(err)
    else:
        if not _OUT.is_file() or partial_path(_OUT).exists():
            raise AssertionError(f"the importer returned without writing {_OUT}")
    printed = _STDERR.read_bytes()
    if printed:
        raise AssertionError(f"the importer wrote to stderr: {printed[:300]!r}")


# Seeds: tiny valid folders of each importer, written by hand (not copies of the real datasets).
_T0 = 1248444187.0


def _mrclam_seed() -> bytes:
    """A robot driving a slow arc among three landmarks for 3 s: 30 odometry, ground-truth and measurement rows."""
    import math

    barcodes = "# Subject #    Barcode #\n1 5\n2 14\n6 63\n7 81\n8 90\n"
    marks = "# Subject # x y sx sy\n6 2.0 0.5 0.0001 0.0002\n7 1.5 -1.0 0.0001 0.0002\n8 -1.0 2.0 0.0001 0.0002\n"
    odo, gt, meas = ["# Time [s] v w"], ["# Time [s] x y yaw"], ["# Time [s] barcode range bearing"]
    for k in range(30):
        t = _T0 + 0.1 * k
        yaw = 0.1 * 0.1 * k
        x, y = 0.2 * 0.1 * k * math.cos(yaw), 0.2 * 0.1 * k * math.sin(yaw)
        odo.append(f"{t:.3f} 0.2 0.1")
        gt.append(f"{t + 0.005:.3f} {x:.6f} {y:.6f} {yaw:.5f}")
        lx, ly = ((2.0, 0.5), (1.5, -1.0), (-1.0, 2.0))[k % 3]
        code = (63, 81, 90)[k % 3]
        meas.append(f"{t + 0.01:.3f} {code} {math.hypot(lx - x, ly - y):.3f} {math.atan2(ly - y, lx - x) - yaw:.3f}")
    meas.append(f"{_T0 + 3.0:.3f} 5 1.0 0.1")  # another robot
    meas.append(f"{_T0 + 3.0:.3f} 99 1.0 0.1")  # an unknown barcode
    return SEPARATOR.join(text.encode() + b"\n" for text in (barcodes, marks, "\n".join(odo), "\n".join(gt),
                                                              "\n".join(meas)))


def _victoria_seed() -> bytes:
    """Six poses on a straight line seeing two trees, in the file's own form."""
    cov = "0.0001 0 0 4e-06 0 4e-06"
    lines = [f"ODOMETRY {i} {i + 1} 0.5 0.001 0.002 {cov}" for i in range(5)]
    lines.insert(2, "LANDMARK 2 100 4.0 1.0 0.4 0 0.4")
    lines.insert(4, "LANDMARK 3 100 3.5 1.0 0.4 0 0.4")
    lines.insert(5, "LANDMARK 3 101 2.0 -2.0 0.4 0 0.4")
    lines.append("LANDMARK 5 101 0.5 -2.0 0.4 0 0.4")
    return ("\n".join(lines) + "\n").encode()


def _images_seed(suffix: str) -> bytes:
    """Two 8x6 frames in one format (``suffix`` as in SUFFIXES)."""
    import cv2
    import numpy as np

    frames = []
    for k in range(2):
        img = (np.arange(48, dtype=np.uint8).reshape(6, 8) * 5 + 40 * k).astype(np.uint8)
        ok, buf = cv2.imencode(suffix, img)
        assert ok, suffix
        frames.append(bytes([SUFFIXES.index(suffix)]) + buf.tobytes())
    return SEPARATOR.join(frames)


def write_seeds(out: Path) -> None:
    """The seed corpus: each importer on a tiny valid folder, each option, each image format."""
    out.mkdir(parents=True, exist_ok=True)
    mrclam, victoria = _mrclam_seed(), _victoria_seed()
    (out / "mrclam-robot1.in").write_bytes(b"\x00\x00" + mrclam)
    (out / "mrclam-all.in").write_bytes(b"\x00\x01" + mrclam)
    for flags, name in ((0, "reference"), (1, "no-reference"), (3, "no-reference-merge")):
        (out / f"victoria-{name}.in").write_bytes(b"\x01" + bytes([flags]) + victoria)
    for suffix in (".png", ".jpg", ".tif", ".bmp", ".pgm"):
        (out / f"images{suffix.replace('.', '-')}.in").write_bytes(b"\x02\x00" + _images_seed(suffix))


def main() -> None:
    """libFuzzer's command line (see the module docstring), or ``--seeds DIR`` to write the seed corpus."""
    if sys.argv[1:2] == ["--seeds"]:
        write_seeds(Path(sys.argv[2]))
        return
    atheris.Setup(sys.argv, test_one_input)
    atheris.Fuzz()


if __name__ == "__main__":
    main()
