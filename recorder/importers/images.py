"""Importer for an image sequence without navigation: a folder of frames -> ``/camera/image``.

Frames are ordered by their frame counter: the last run of digits in the file name
(``ESC.970622_023824.0546.png`` -> 546), then by name; a name without digits sorts after
those with, by name. Stamps are ``k / rate_hz`` seconds after :data:`EPOCH_NS` for the k-th
frame (the files carry no time we can trust). Colour frames are converted to mono8, and
every frame must have the first frame's size. Frames are stored lossless (PNG).
"""

from __future__ import annotations

import os
import re
import sys
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Final, cast

import cv2
import numpy as np
from numpy.typing import NDArray

from slamreplay.recorder.codec.bounds import MAX_IMAGE_PIXELS, check_image_size, image_format, shown
from slamreplay.recorder.codec.protobuf import check_png
from slamreplay.recorder.errors import CodecError, RecorderError
from slamreplay.recorder.messages import TOPIC_CAMERA_IMAGE, CameraImage
from slamreplay.recorder.writer import Recorder

# The largest frame file read: a frame of MAX_IMAGE_PIXELS rgb8 pixels stored uncompressed (BMP, PPM, TIFF) with
# room for its headers. A frame is read whole: a TIFF's size is in a directory that may sit at its end.
MAX_FRAME_BYTES = 3 * MAX_IMAGE_PIXELS + (1 << 20)

IMPORTER: Final = "images"
EPOCH_NS: Final = 1_000_000_000
SUFFIXES: Final = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".pgm")

Progress = Callable[[int, int], None]


@dataclass(frozen=True, slots=True)
class ImagesSummary:
    """What :func:`import_images` wrote."""

    path: Path
    images: int
    width_px: int
    height_px: int
    first: str
    last: str
    start_ns: int
    end_ns: int


def frame_key(path: Path) -> tuple[int, int, str]:
    """Sort key: (0, frame counter, name) when the stem holds digits, else (1, 0, name)."""
    runs = re.findall(r"\d+", path.stem)
    return (0, int(runs[-1]), path.name) if runs else (1, 0, path.name)


def list_frames(folder: Path) -> list[Path]:
    """The image files of ``folder`` in frame order; RecorderError when there are none."""
    if not folder.is_dir():
        raise RecorderError(f"{folder} is not a directory: give the folder that holds the frames")
    frames = sorted((p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in SUFFIXES), key=frame_key)
    if not frames:
        raise RecorderError(f"{folder} holds no images ({', '.join(SUFFIXES)})")
    return frames


def read_frame(path: Path) -> NDArray[np.uint8]:
    """The pixels of one frame file, mono8 (H, W); RecorderError naming the file when it is not a whole image of
    a format whose size its header states (checked before OpenCV allocates what it claims), or too large."""
    try:
        with open(path, "rb") as f:
            data = f.read(MAX_FRAME_BYTES + 1)
    except OSError as err:
        raise RecorderError(f"{path} cannot be read: {err.strerror or err}") from err
    if len(data) > MAX_FRAME_BYTES:
        raise RecorderError(f"{path.name} is larger than {MAX_FRAME_BYTES:,} bytes, more than a frame of "
                            f"{MAX_IMAGE_PIXELS:,} pixels takes: it is not a frame")
    if not data:
        raise RecorderError(f"{path.name} is empty: it is not an image")
    try:
        if image_format(data) == "PNG":
            check_png(data)  # libpng prints damage on stderr before it fails
        check_image_size(data, path.suffix.lstrip(".").lower())
    except CodecError as err:
        raise RecorderError(f"{path.name}: {err}") from err
    img, printed = _decode(data)
    if printed:  # libjpeg and libpng report damage only there: a frame that decodes with gray blocks is damaged
        raise RecorderError(f"{path.name} is damaged: {shown(printed.splitlines()[0])}")
    if img is None:
        raise RecorderError(f"{path} is not an image OpenCV can read")
    return img


def _decode(data: bytes) -> tuple[NDArray[np.uint8] | None, str]:
    """(mono8 pixels or None, what the C decoders printed while decoding): OpenCV's log is silenced and file
    descriptor 2 is caught for the call, so that a user sees the damage once, in slamreplay's one-line error.

    Both are the process's: this importer reads the machine's folders, so it runs in the command line's own
    process (the service does not offer it), one frame at a time."""
    level = cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with tempfile.TemporaryFile() as caught:
            os.dup2(caught.fileno(), 2)
            try:
                pixels = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE)
                img = cast("NDArray[np.uint8] | None", pixels)  # IMREAD_GRAYSCALE always yields 8-bit pixels
            finally:
                os.dup2(saved, 2)
            caught.seek(0)
            printed = caught.read(4096).decode("utf-8", "replace").strip()
    finally:
        os.close(saved)
        cv2.utils.logging.setLogLevel(level)
    return img, printed


def import_images(folder: Path, out: Path, rate_hz: float = 1.0, progress: Progress | None = None) -> ImagesSummary:
    """Record the frames of ``folder`` as ``/camera/image`` messages in ``out``.

    Raises
    ------
    RecorderError : no frames, an unreadable frame, a frame of another size, a bad rate, or
        ``out`` exists / its directory does not.
    """
    if not (rate_hz > 0 and np.isfinite(rate_hz)):
        raise RecorderError(f"--rate-hz must be a positive number, got {rate_hz}")
    frames = list_frames(Path(folder))
    period = max(1, round(1e9 / rate_hz))
    size: tuple[int, int] | None = None
    with Recorder(out, source={"importer": IMPORTER, "folder": Path(folder).name}, parameters={"rate_hz": rate_hz},
                  robot={"camera": "image sequence, no navigation"}) as rec:
        for k, path in enumerate(frames):
            img = read_frame(path)
            if size is None:
                size = img.shape
            elif img.shape != size:
                raise RecorderError(f"{path.name} is {img.shape[1]}x{img.shape[0]} but the first frame is "
                                    f"{size[1]}x{size[0]}: every frame must have one size")
            rec.write(TOPIC_CAMERA_IMAGE, CameraImage(EPOCH_NS + k * period, img, frame_id="camera",
                                                      compression="png"))
            if progress is not None:
                progress(k + 1, len(frames))
    assert size is not None
    return ImagesSummary(Path(out), len(frames), size[1], size[0], frames[0].name, frames[-1].name, EPOCH_NS,
                         EPOCH_NS + (len(frames) - 1) * period)
