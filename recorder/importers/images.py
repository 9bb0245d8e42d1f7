"""Importer for an image sequence without navigation: a folder of frames -> ``/camera/image``.

Frames are ordered by their frame counter: the last run of digits in the file name
(``ESC.970622_023824.0546.png`` -> 546), then by name; a name without digits sorts after
those with, by name. Stamps are ``k / rate_hz`` seconds after :data:`EPOCH_NS` for the k-th
frame (the files carry no time we can trust). Colour frames are converted to mono8, and
every frame must have the first frame's size. Frames are stored lossless (PNG).
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Final, cast

import cv2
import numpy as np
from numpy.typing import NDArray

from slamreplay.recorder.codec.bounds import check_image_size
from slamreplay.recorder.errors import CodecError, RecorderError
from slamreplay.recorder.messages import TOPIC_CAMERA_IMAGE, CameraImage
from slamreplay.recorder.writer import Recorder

# Bytes read to find an image's width and height: a PNG's IHDR is at byte 16; a JPEG's frame header follows
# its APP segments (EXIF, at most 64 KiB each).
HEADER_BYTES = 256 << 10

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
            with open(path, "rb") as f:
                head = f.read(HEADER_BYTES)
            try:
                check_image_size(head, path.suffix.lstrip(".").lower())  # before OpenCV allocates what it claims
            except CodecError as err:
                raise RecorderError(f"{path.name}: {err}") from err
            img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
            if img is None:
                raise RecorderError(f"{path} is not an image OpenCV can read")
            if size is None:
                size = img.shape
            elif img.shape != size:
                raise RecorderError(f"{path.name} is {img.shape[1]}x{img.shape[0]} but the first frame is "
                                    f"{size[1]}x{size[0]}: every frame must have one size")
            pixels = cast(NDArray[np.uint8], img)  # IMREAD_GRAYSCALE always yields 8-bit pixels
            rec.write(TOPIC_CAMERA_IMAGE, CameraImage(EPOCH_NS + k * period, pixels, frame_id="camera",
                                                      compression="png"))
            if progress is not None:
                progress(k + 1, len(frames))
    assert size is not None
    return ImagesSummary(Path(out), len(frames), size[1], size[0], frames[0].name, frames[-1].name, EPOCH_NS,
                         EPOCH_NS + (len(frames) - 1) * period)
