"""Simulator ``sim-seabed``: a downward camera over a planar seabed flying a lawn-mower survey.

The vehicle flies parallel legs joined by U-turns, adjacent legs overlapping so that every
leg revisits the previous one (loop closures for a photo map, as in iFMI mapping [1]_). The
heading wobbles along a leg, the altitude (hence the image scale) drifts slowly, and each image
gets vignetting (a radial fall-off with an off-centre hot spot, like a lamp on an ROV) and
Gaussian sensor noise.

Seabed texture: a procedural one made from the seed (fractal sediment, rocks with shadows,
grain; needs nothing outside the repository), or ``texture`` = an image file, or a folder of
frames (for instance the Skerki Bank images) tiled side by side after flattening their
illumination.

Recorded topics (times are integer ns from :data:`EPOCH_NS`, never the wall clock):

- ``/ground_truth/pose``: true camera pose in ``world`` (metres; x east, y north, yaw
  counter-clockwise); the image's up direction is the body's +x axis, its left the body's +y;
- ``/odom``: dead reckoning from noisy relative motions, starting at (0, 0, 0);
- ``/camera/image``: the mono8 image (PNG), same stamp, written last.

One image pixel is ``metres_per_pixel / scale`` metres on the seabed, where ``scale`` is the
altitude factor (1 at the nominal altitude, > 1 closer). The recording's ``parameters``
metadata holds the config, so a consumer can convert pixels to metres.

References
----------
.. [1] M. Pfingsthorn, A. Birk, S. Schwertfeger, H. Bülow, K. Pathak, "Maximum Likelihood
   Mapping with Spectral Image Registration", ICRA 2010.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Final, cast

import cv2
import numpy as np
from numpy.typing import NDArray

from slamreplay.recorder.errors import RecorderError
from slamreplay.recorder.importers.images import SUFFIXES as IMAGE_SUFFIXES
from slamreplay.recorder.messages import (
    TOPIC_CAMERA_IMAGE,
    TOPIC_GROUND_TRUTH_POSE,
    TOPIC_ODOM,
    CameraImage,
    GroundTruthPose,
    OdometryPose,
)
from slamreplay.recorder.sensor_model import SensorModel
from slamreplay.recorder.sim.seabed_config import SeabedSimConfig as SeabedSimConfig  # re-exported
from slamreplay.recorder.sim.unicycle import between, compose, wrap_angle
from slamreplay.recorder.writer import Recorder

SIMULATOR: Final = "sim-seabed"
EPOCH_NS: Final = 1_000_000_000
TEXTURE_MARGIN_PX: Final = 64

Progress = Callable[[int, int], None]
F64 = NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class SeabedSummary:
    """What :func:`simulate_seabed` wrote."""

    path: Path
    messages: int
    images: int
    texture_px: tuple[int, int]  # (width, height)
    path_length_m: float
    start_ns: int
    end_ns: int


def procedural_texture(width: int, height: int, rng: np.random.Generator) -> NDArray[np.uint8]:
    """A seabed-like uint8 texture (height, width): fractal sediment, shaded rocks, fine grain."""
    fy = np.fft.fftfreq(height)[:, None]
    fx = np.fft.rfftfreq(width)[None, :]
    f = np.hypot(fx, fy)
    f[0, 0] = 1.0
    amp = f**-1.6 * np.exp(-((f / 0.35) ** 2))
    amp[0, 0] = 0.0
    phase = rng.uniform(0.0, 2.0 * np.pi, amp.shape)
    sediment = np.fft.irfft2(amp * np.exp(1j * phase), s=(height, width))
    sediment /= sediment.std()
    rocks = np.zeros((height, width), np.float32)
    n_rocks = max(1, int(width * height / 10_000))
    for cx, cy, r, ang, ecc in zip(rng.uniform(0, width, n_rocks), rng.uniform(0, height, n_rocks),
                                   rng.uniform(6, 40, n_rocks), rng.uniform(0, 180, n_rocks),
                                   rng.uniform(0.4, 1.0, n_rocks), strict=True):
        axes = (int(r), max(2, int(r * ecc)))
        cv2.ellipse(rocks, (int(cx + 0.3 * r), int(cy + 0.3 * r)), axes, ang, 0, 360, -0.8, -1)  # shadow
        cv2.ellipse(rocks, (int(cx), int(cy)), axes, ang, 0, 360, 1.2, -1)
    rocks = cast(NDArray[np.float32], cv2.GaussianBlur(rocks, (0, 0), 2.0))
    grain = rng.standard_normal((height, width)) * 0.25
    tex = sediment + 1.5 * rocks + grain
    tex = (tex - tex.mean()) / (tex.std() + 1e-12)
    return cast(NDArray[np.uint8], np.clip(128.0 + 38.0 * tex, 0, 255).astype(np.uint8))


def tiled_texture(folder: Path) -> NDArray[np.uint8]:
    """The frames of ``folder`` (sorted by name), illumination flattened, tiled in a near-square grid."""
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    decoded = [cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) for p in files]
    frames = [f for f in decoded if f is not None]
    if not frames:
        raise RecorderError(f"texture folder {folder} holds no readable images ({', '.join(IMAGE_SUFFIXES)})")
    h, w = frames[0].shape
    frames = [cv2.resize(f, (w, h)) if f.shape != (h, w) else f for f in frames]
    stack = np.stack(frames).astype(np.float32)
    light = cv2.GaussianBlur(stack.mean(axis=0), (0, 0), 0.05 * min(h, w)) + 1.0
    cols = math.ceil(math.sqrt(len(frames)))
    rows = math.ceil(len(frames) / cols)
    out = np.full((rows * h, cols * w), 128.0, np.float32)
    for k, f in enumerate(stack):
        flat = f / light
        flat = 128.0 + 40.0 * (flat - flat.mean()) / (flat.std() + 1e-6)
        r, c = divmod(k, cols)
        out[r * h:(r + 1) * h, c * w:(c + 1) * w] = flat
    return np.clip(out, 0, 255).astype(np.uint8)


def load_texture(spec: str, width: int, height: int, rng: np.random.Generator) -> NDArray[np.uint8]:
    """The texture named by ``spec`` (module docstring); RecorderError when it cannot be read."""
    if not spec:
        return procedural_texture(width, height, rng)
    path = Path(spec)
    if path.is_dir():
        return tiled_texture(path)
    if not path.is_file():
        raise RecorderError(f"texture {spec} does not exist: give an image file or a folder of images")
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise RecorderError(f"texture {spec} is not an image OpenCV can read")
    return np.asarray(img, dtype=np.uint8)


def survey_path(config: SeabedSimConfig, rng: np.random.Generator) -> tuple[F64, F64]:
    """True poses ``(n, 3)`` [x_m, y_m, yaw_rad] of the images and their altitude scales ``(n,)``.

    Legs run along +x and -x, ``leg_spacing`` footprints apart in y; two images on each U-turn
    (half way round) join them. Heading wobble and scale are smooth random walks.
    """
    step = config.image_spacing * config.footprint_m
    gap = config.leg_spacing * config.footprint_m
    per_leg = max(2, math.floor(config.leg_length_m / step + 1e-9) + 1)
    poses: list[tuple[float, float, float]] = []
    for leg in range(config.legs):
        forward = leg % 2 == 0
        xs = np.arange(per_leg) * step
        if not forward:
            xs = xs[::-1]
        yaw = 0.0 if forward else math.pi
        poses += [(float(x), leg * gap, yaw) for x in xs]
        if leg + 1 < config.legs:  # the U-turn: quarter and three quarters round a half circle
            x_end, r = float(xs[-1]), 0.5 * gap
            side = 1.0 if forward else -1.0
            for a in (0.25 * math.pi, 0.75 * math.pi):
                poses.append((x_end + side * r * math.sin(a), leg * gap + r * (1 - math.cos(a)),
                              yaw + a if forward else yaw - a))
    p = np.array(poses)
    n = len(p)
    wobble = np.cumsum(rng.standard_normal(n)) * 0.3
    wobble = np.radians(config.heading_wobble_deg) * np.tanh(wobble - wobble.mean())
    p[:, 2] = wrap_angle(p[:, 2] + wobble)
    phase = rng.uniform(0, 2 * np.pi)
    scales = 1.0 + config.scale_amplitude * np.sin(np.linspace(0.0, 3.0 * np.pi, n) + phase)
    return p, scales


def image_to_texture(pose: F64, scale: float, config: SeabedSimConfig, origin_px: tuple[float, float]) -> F64:
    """The 2x3 affine taking image pixels (u, v) to texture pixels (col, row).

    Body point of a pixel: ``b = (mpp / scale) J (p - c)`` with ``J = [[0, -1], [-1, 0]]`` (image up is
    body +x, image left body +y); world ``w = t + R(yaw) b``; texture ``(x / mpp + ox, oy - y / mpp)``.
    """
    mpp, n = config.metres_per_pixel, config.image_px
    c = np.array([(n - 1) / 2.0, (n - 1) / 2.0])
    cy, sy = math.cos(pose[2]), math.sin(pose[2])
    rot = np.array([[cy, -sy], [sy, cy]])
    flip = np.array([[1.0 / mpp, 0.0], [0.0, -1.0 / mpp]])
    lin = flip @ rot @ (mpp / scale * np.array([[0.0, -1.0], [-1.0, 0.0]]))
    off = flip @ pose[:2] + np.asarray(origin_px) - lin @ c
    return np.hstack([lin, off[:, None]])


def render(texture: NDArray[np.uint8], affine: F64, config: SeabedSimConfig, vignette: NDArray[np.float32],
           rng: np.random.Generator) -> NDArray[np.uint8]:
    """One camera image: the seabed under ``affine``, vignetted, with sensor noise."""
    n = config.image_px
    img = cv2.warpAffine(texture, affine, (n, n), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                         borderMode=cv2.BORDER_REFLECT).astype(np.float32)
    img = img * vignette + rng.standard_normal((n, n)).astype(np.float32) * np.float32(config.noise_sigma)
    return cast(NDArray[np.uint8], np.clip(img + 0.5, 0, 255).astype(np.uint8))


def vignette_map(config: SeabedSimConfig) -> NDArray[np.float32]:
    """Multiplicative illumination: an off-centre lamp hot spot fading to dark corners."""
    n = config.image_px
    y, x = np.mgrid[0:n, 0:n] / (n - 1.0) - 0.5
    r2 = (x - 0.08) ** 2 + (y + 0.1) ** 2
    return cast(NDArray[np.float32],
                (1.0 - config.vignetting * np.clip(r2 / 0.5, 0, 1) + 0.25 * config.vignetting * np.exp(-r2 / 0.02)
                 ).astype(np.float32))


def simulate_seabed(out: Path, config: SeabedSimConfig, seed: int, progress: Progress | None = None
                    ) -> SeabedSummary:
    """Simulate the survey of ``config`` and record it to ``out`` (an MCAP file).

    Parameters
    ----------
    out : the recording to create; must not exist (the Recorder never overwrites).
    config : the scenario.
    seed : seeds the texture, the path, the odometry and the sensor noise (independent
        streams). Same seed and config give identical messages.
    progress : called as ``progress(done, total)`` in images.

    Raises
    ------
    RecorderError : ``out`` exists, its directory does not, or the texture cannot be read.
    """
    rng_tex, rng_path, rng_odom, rng_noise = np.random.default_rng(seed).spawn(4)
    truth, scales = survey_path(config, rng_path)
    mpp = config.metres_per_pixel
    lo = truth[:, :2].min(axis=0) - config.footprint_m
    hi = truth[:, :2].max(axis=0) + config.footprint_m
    width = math.ceil((hi[0] - lo[0]) / mpp) + 2 * TEXTURE_MARGIN_PX
    height = math.ceil((hi[1] - lo[1]) / mpp) + 2 * TEXTURE_MARGIN_PX
    texture = load_texture(config.texture, width, height, rng_tex)
    th, tw = texture.shape
    # Centre the survey on the texture: world (0, 0) at this texture pixel.
    origin = (0.5 * tw - 0.5 * (lo[0] + hi[0]) / mpp, 0.5 * th + 0.5 * (lo[1] + hi[1]) / mpp)
    rel = np.array([between(truth[k], truth[k + 1]) for k in range(len(truth) - 1)]).reshape(-1, 3)
    rel[:, 2] = wrap_angle(rel[:, 2])  # the survey's poses are wrapped
    noise = rng_odom.standard_normal(rel.shape)
    dist = np.hypot(rel[:, 0], rel[:, 1])
    rel_odom = rel + noise * config.odom_sigma * np.column_stack([dist, dist, np.abs(rel[:, 2]) + 0.02])
    odom = [np.zeros(3)]
    for r in rel_odom:
        odom.append(compose(odom[-1], r))
    vignette = vignette_map(config)
    period = max(1, round(1e9 / config.frame_rate_hz))
    total = len(truth)
    with Recorder(out, source={"simulator": SIMULATOR}, seed=seed, parameters=dataclasses.asdict(config),
                  robot={"camera": "downward, image up = body +x", "texture_px": [tw, th]},
                  sensor_model=SensorModel(width_px=config.image_px, height_px=config.image_px,
                                           source=f"{SIMULATOR}: its camera's image size")) as rec:
        for k in range(total):
            stamp = EPOCH_NS + k * period
            image = render(texture, image_to_texture(truth[k], float(scales[k]), config, origin), config, vignette,
                           rng_noise)
            rec.write(TOPIC_GROUND_TRUTH_POSE, GroundTruthPose(stamp, *truth[k]))
            rec.write(TOPIC_ODOM, OdometryPose(stamp, float(odom[k][0]), float(odom[k][1]),
                                               float(wrap_angle(odom[k][2]))))
            rec.write(TOPIC_CAMERA_IMAGE, CameraImage(stamp, image, frame_id="camera", compression="png"))
            if progress is not None:
                progress(k + 1, total)
        messages = rec.message_count
    return SeabedSummary(Path(out), messages, total, (tw, th), float(dist.sum()), EPOCH_NS,
                         EPOCH_NS + (total - 1) * period)
