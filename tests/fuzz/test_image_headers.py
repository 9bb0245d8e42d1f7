"""The image header readers (recorder/codec/bounds.py) on every prefix and on seeded damage of a real header of
each format: a size, None, or a one-line CodecError, never another exception (their first crashers came from
harness_datasets.py: a BMP wider than OpenCV takes, a TIFF of 5 bytes)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from slamreplay.recorder.codec.bounds import MAX_IMAGE_SIDE, check_image_size, image_format, image_size
from slamreplay.recorder.errors import CodecError

FORMATS = (".png", ".jpg", ".tif", ".bmp", ".pgm", ".ppm")


def _image(suffix: str) -> bytes:
    pixels = (np.arange(48 * 3, dtype=np.uint8).reshape(6, 8, 3) if suffix == ".ppm"
              else np.arange(48, dtype=np.uint8).reshape(6, 8))
    ok, buf = cv2.imencode(suffix, pixels)
    assert ok
    return buf.tobytes()


def _checked(data: bytes) -> None:
    try:
        check_image_size(data, "frame")
    except CodecError as err:
        assert "\n" not in str(err)


@pytest.mark.parametrize("suffix", FORMATS)
def test_each_format_is_sized(suffix: str) -> None:
    """The encoder's own image: its format recognised and its 8 x 6 read from the header."""
    data = _image(suffix)
    assert image_format(data) is not None and image_size(data) == (8, 6)
    check_image_size(data, suffix)


@pytest.mark.parametrize("suffix", FORMATS)
def test_prefixes_and_damage(suffix: str) -> None:
    """Every prefix of the image, and 2,000 seeded overwrites of 1 to 3 of its bytes."""
    data = _image(suffix)
    for n in range(len(data) + 1):
        _checked(data[:n])
    rng = np.random.default_rng(26)
    for _ in range(2000):
        damaged = bytearray(data)
        for at in rng.integers(0, len(data), size=rng.integers(1, 4)):
            damaged[at] = int(rng.integers(0, 256))
        _checked(bytes(damaged))


def test_a_side_longer_than_the_bound_is_refused() -> None:
    """A 100,000 x 2 PNG header (200,000 pixels) is refused for its side, before OpenCV."""
    data = bytearray(_image(".png"))
    data[16:24] = (100_000).to_bytes(4, "big") + (2).to_bytes(4, "big")
    with pytest.raises(CodecError, match=f"at most {MAX_IMAGE_SIDE:,} pixels along a side"):
        check_image_size(bytes(data), "png")
