"""The message model: what a recording holds, independent of how it is stored.

Every message is a frozen dataclass. Times are integer nanoseconds; units, frames and
array orders are in the field names. Construction validates shapes, dtypes and finiteness,
so a message that exists is a message the algorithms can use: a NaN never gets past here.

Arrays are stored as read-only copies; compare messages with :func:`assert_msg_equal`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from typing import ClassVar, Final, Literal

import numpy as np
from numpy.typing import NDArray

# Logical topics of a slamreplay recording (docs/design.md, "Recording format").
TOPIC_ODOM: Final = "/odom"
TOPIC_GROUND_TRUTH_POSE: Final = "/ground_truth/pose"
TOPIC_RANGE_BEARING: Final = "/landmarks/range_bearing"
TOPIC_GROUND_TRUTH_LANDMARKS: Final = "/ground_truth/landmarks"
TOPIC_CAMERA_IMAGE: Final = "/camera/image"
TOPIC_CAMERA_CALIBRATION: Final = "/camera/calibration"
TOPIC_CMD_VEL: Final = "/cmd_vel"
TOPIC_NAV_LOCALIZATION: Final = "/nav/localization"
TOPIC_IMU_YAW_RATE: Final = "/imu/yaw_rate"

ImageEncoding = Literal["mono8", "rgb8"]
ImageCompression = Literal["raw", "png", "jpeg"]


def _finite_float_array(name: str, value: object, ndim: int, width: int | None = None) -> NDArray[np.float64]:
    arr = np.array(value, dtype=np.float64, copy=True)
    if arr.ndim != ndim or (width is not None and arr.shape[-1] != width):
        want = "(n,)" if ndim == 1 else f"(n, {width})"
        raise ValueError(f"{name} must have shape {want}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or infinite values")
    arr.flags.writeable = False
    return arr


def _check_stamp(stamp_ns: object) -> None:
    if not isinstance(stamp_ns, (int, np.integer)) or isinstance(stamp_ns, bool):
        raise ValueError(f"stamp_ns must be an integer number of nanoseconds, got {stamp_ns!r}")
    if stamp_ns < 0:
        raise ValueError(f"stamp_ns must be >= 0, got {stamp_ns}")


def _check_finite(**values: float) -> None:
    for name, value in values.items():
        # math.isfinite: a tenth of np.isfinite's cost on a scalar (this runs for every decoded pose)
        if not math.isfinite(value):
            raise ValueError(f"{name} is {value}: every value in a message must be finite")


@dataclass(frozen=True, slots=True)
class PlanarPose:
    """A planar pose: position in metres and heading (yaw, counter-clockwise from +x)."""

    stamp_ns: int
    x_m: float
    y_m: float
    yaw_rad: float

    def __post_init__(self) -> None:
        # One pose per decoded message: the common case (an int stamp, finite Python floats) is checked
        # without a call per field; anything else goes through the general checks and conversions.
        stamp, x, y, yaw = self.stamp_ns, self.x_m, self.y_m, self.yaw_rad
        if type(stamp) is not int or stamp < 0:
            _check_stamp(stamp)
            object.__setattr__(self, "stamp_ns", int(stamp))
        if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(yaw)):
            _check_finite(x_m=x, y_m=y, yaw_rad=yaw)
        if type(x) is not float or type(y) is not float or type(yaw) is not float:
            object.__setattr__(self, "x_m", float(x))
            object.__setattr__(self, "y_m", float(y))
            object.__setattr__(self, "yaw_rad", float(yaw))

    @property
    def xy_yaw(self) -> NDArray[np.float64]:
        """The pose as a (3,) array ``[x_m, y_m, yaw_rad]``."""
        return np.array([self.x_m, self.y_m, self.yaw_rad])


@dataclass(frozen=True, slots=True)
class OdometryPose(PlanarPose):
    """Cumulative wheel-odometry pose of the robot body in the ``odom`` frame."""

    FRAME_ID: ClassVar[str] = "odom"


@dataclass(frozen=True, slots=True)
class GroundTruthPose(PlanarPose):
    """True pose of the robot body in the ``world`` frame."""

    FRAME_ID: ClassVar[str] = "world"


@dataclass(frozen=True, slots=True, eq=False)  # arrays: compare with assert_msg_equal
class RangeBearingScan:
    """Landmarks seen in one sensor sweep, in the robot frame (x forward, y left).

    ``landmark_ids`` holds the true landmark id where the source knows it and -1 where it
    does not. ``range_sigma_m`` and ``bearing_sigma_rad`` are the sensor's 1-sigma noise;
    0 means "not stated by the source".
    """

    stamp_ns: int
    ranges_m: NDArray[np.float64]  # (n,)
    bearings_rad: NDArray[np.float64]  # (n,), counter-clockwise from +x
    landmark_ids: NDArray[np.int64]  # (n,), -1 where unknown
    range_sigma_m: float = 0.0
    bearing_sigma_rad: float = 0.0

    def __post_init__(self) -> None:
        _check_stamp(self.stamp_ns)
        ranges = _finite_float_array("ranges_m", self.ranges_m, 1)
        bearings = _finite_float_array("bearings_rad", self.bearings_rad, 1)
        ids = np.array(self.landmark_ids, dtype=np.int64, copy=True)
        if ids.ndim != 1 or not (len(ranges) == len(bearings) == len(ids)):
            raise ValueError(
                f"ranges_m, bearings_rad and landmark_ids must have the same length (n,), "
                f"got {ranges.shape}, {bearings.shape}, {ids.shape}"
            )
        if np.any(ranges < 0):
            raise ValueError("ranges_m must be >= 0")
        if np.any(ids < -1):
            raise ValueError("landmark_ids must be >= 0, or -1 for unknown")
        _check_finite(range_sigma_m=self.range_sigma_m, bearing_sigma_rad=self.bearing_sigma_rad)
        if self.range_sigma_m < 0 or self.bearing_sigma_rad < 0:
            raise ValueError("range_sigma_m and bearing_sigma_rad must be >= 0")
        ids.flags.writeable = False
        object.__setattr__(self, "stamp_ns", int(self.stamp_ns))
        object.__setattr__(self, "ranges_m", ranges)
        object.__setattr__(self, "bearings_rad", bearings)
        object.__setattr__(self, "landmark_ids", ids)
        object.__setattr__(self, "range_sigma_m", float(self.range_sigma_m))
        object.__setattr__(self, "bearing_sigma_rad", float(self.bearing_sigma_rad))

    def __len__(self) -> int:
        return len(self.ranges_m)


@dataclass(frozen=True, slots=True, eq=False)
class LandmarkMap:
    """Point landmarks in the ``world`` frame: ids and positions in metres."""

    stamp_ns: int
    landmark_ids: NDArray[np.int64]  # (n,), unique, >= 0
    positions_m: NDArray[np.float64]  # (n, 2), x and y

    def __post_init__(self) -> None:
        _check_stamp(self.stamp_ns)
        positions = _finite_float_array("positions_m", np.reshape(self.positions_m, (-1, 2)), 2, 2)
        ids = np.array(self.landmark_ids, dtype=np.int64, copy=True)
        if ids.shape != (len(positions),):
            raise ValueError(f"landmark_ids must have shape ({len(positions)},), got {ids.shape}")
        if np.any(ids < 0) or len(np.unique(ids)) != len(ids):
            raise ValueError("landmark_ids must be unique and >= 0")
        ids.flags.writeable = False
        object.__setattr__(self, "stamp_ns", int(self.stamp_ns))
        object.__setattr__(self, "landmark_ids", ids)
        object.__setattr__(self, "positions_m", positions)

    def __len__(self) -> int:
        return len(self.landmark_ids)


@dataclass(frozen=True, slots=True, eq=False)
class CameraImage:
    """One camera frame.

    ``pixels`` is (H, W) uint8 for ``mono8`` and (H, W, 3) uint8 in RGB order for ``rgb8``.
    ``compression`` says how the codec stores it: ``raw`` (foxglove.RawImage), ``png``
    (lossless) or ``jpeg`` (lossy) as foxglove.CompressedImage.
    """

    stamp_ns: int
    pixels: NDArray[np.uint8]
    frame_id: str = "camera"
    compression: ImageCompression = "png"

    def __post_init__(self) -> None:
        _check_stamp(self.stamp_ns)
        pixels = np.array(self.pixels, copy=True)
        if pixels.dtype != np.uint8:
            raise ValueError(f"pixels must be uint8, got {pixels.dtype}")
        if not (pixels.ndim == 2 or (pixels.ndim == 3 and pixels.shape[2] == 3)):
            raise ValueError(f"pixels must be (H, W) mono8 or (H, W, 3) rgb8, got shape {pixels.shape}")
        if pixels.shape[0] == 0 or pixels.shape[1] == 0:
            raise ValueError(f"pixels must not be empty, got shape {pixels.shape}")
        if self.compression not in ("raw", "png", "jpeg"):
            raise ValueError(f"compression must be 'raw', 'png' or 'jpeg', got {self.compression!r}")
        pixels.flags.writeable = False
        object.__setattr__(self, "stamp_ns", int(self.stamp_ns))
        object.__setattr__(self, "pixels", pixels)

    @property
    def encoding(self) -> ImageEncoding:
        """``mono8`` or ``rgb8``, from the pixel array's shape."""
        return "mono8" if self.pixels.ndim == 2 else "rgb8"

    @property
    def width_px(self) -> int:
        return int(self.pixels.shape[1])

    @property
    def height_px(self) -> int:
        return int(self.pixels.shape[0])


@dataclass(frozen=True, slots=True, eq=False)
class CameraCalibration:
    """Pinhole intrinsics of a camera (foxglove.CameraCalibration)."""

    stamp_ns: int
    width_px: int
    height_px: int
    K: NDArray[np.float64]  # (3, 3) intrinsic matrix, pixels
    D: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))  # (k,) distortion
    distortion_model: str = "plumb_bob"
    frame_id: str = "camera"

    def __post_init__(self) -> None:
        _check_stamp(self.stamp_ns)
        if self.width_px <= 0 or self.height_px <= 0:
            raise ValueError(f"width_px and height_px must be > 0, got {self.width_px}x{self.height_px}")
        K = np.array(self.K, dtype=np.float64, copy=True)
        if K.shape != (3, 3) or not np.all(np.isfinite(K)):
            raise ValueError(f"K must be a finite (3, 3) matrix, got shape {K.shape}")
        D = _finite_float_array("D", np.ravel(self.D), 1)
        K.flags.writeable = False
        object.__setattr__(self, "stamp_ns", int(self.stamp_ns))
        object.__setattr__(self, "width_px", int(self.width_px))
        object.__setattr__(self, "height_px", int(self.height_px))
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "D", D)


@dataclass(frozen=True, slots=True)
class VelocityCommand:
    """A planar velocity command to the robot base: forward speed and yaw rate (counter-clockwise)."""

    stamp_ns: int
    linear_mps: float
    angular_radps: float

    def __post_init__(self) -> None:
        _check_stamp(self.stamp_ns)
        _check_finite(linear_mps=self.linear_mps, angular_radps=self.angular_radps)
        object.__setattr__(self, "stamp_ns", int(self.stamp_ns))
        object.__setattr__(self, "linear_mps", float(self.linear_mps))
        object.__setattr__(self, "angular_radps", float(self.angular_radps))


@dataclass(frozen=True, slots=True)
class NavLocalization:
    """A navigation-mode localization after one image (topo-metric map, ``map`` frame).

    The estimated pose after the image; the matched map node (-1: no loop closure), the
    image x-translation in pixels and the heading deviation it gave; ``corrected`` when the
    match moved the estimate (visual correction on).
    """

    stamp_ns: int
    x_m: float
    y_m: float
    yaw_rad: float
    node: int
    x_translation_px: float
    heading_deviation_rad: float
    corrected: bool

    FRAME_ID: ClassVar[str] = "map"

    def __post_init__(self) -> None:
        _check_stamp(self.stamp_ns)
        _check_finite(x_m=self.x_m, y_m=self.y_m, yaw_rad=self.yaw_rad, x_translation_px=self.x_translation_px,
                      heading_deviation_rad=self.heading_deviation_rad)
        if not isinstance(self.node, (int, np.integer)) or isinstance(self.node, bool) or self.node < -1:
            raise ValueError(f"node must be a node index >= 0, or -1 for none, got {self.node!r}")
        object.__setattr__(self, "stamp_ns", int(self.stamp_ns))
        object.__setattr__(self, "node", int(self.node))
        object.__setattr__(self, "corrected", bool(self.corrected))
        for name in ("x_m", "y_m", "yaw_rad", "x_translation_px", "heading_deviation_rad"):
            object.__setattr__(self, name, float(getattr(self, name)))


@dataclass(frozen=True, slots=True)
class ImuYawRate:
    """A gyroscope's rate about the body's +z axis (counter-clockwise), and its 1-sigma (0: not stated)."""

    stamp_ns: int
    yaw_rate_radps: float
    yaw_rate_sigma_radps: float = 0.0

    FRAME_ID: ClassVar[str] = "base_link"

    def __post_init__(self) -> None:
        _check_stamp(self.stamp_ns)
        _check_finite(yaw_rate_radps=self.yaw_rate_radps, yaw_rate_sigma_radps=self.yaw_rate_sigma_radps)
        if self.yaw_rate_sigma_radps < 0:
            raise ValueError(f"yaw_rate_sigma_radps must be >= 0, got {self.yaw_rate_sigma_radps}")
        object.__setattr__(self, "stamp_ns", int(self.stamp_ns))
        object.__setattr__(self, "yaw_rate_radps", float(self.yaw_rate_radps))
        object.__setattr__(self, "yaw_rate_sigma_radps", float(self.yaw_rate_sigma_radps))


Message = (OdometryPose | GroundTruthPose | RangeBearingScan | LandmarkMap | CameraImage | CameraCalibration
           | VelocityCommand | NavLocalization | ImuYawRate)


def assert_msg_equal(a: Message, b: Message, *, atol: float = 0.0) -> None:
    """Raise AssertionError unless ``a`` and ``b`` are the same type with equal fields.

    Arrays compare element-wise within ``atol``; other fields compare exactly.
    """
    if type(a) is not type(b):
        raise AssertionError(f"type {type(a).__name__} != {type(b).__name__}")
    for f in fields(a):
        va, vb = getattr(a, f.name), getattr(b, f.name)
        if isinstance(va, np.ndarray):
            if va.shape != vb.shape or not np.allclose(va, vb, atol=atol, rtol=0.0):
                raise AssertionError(f"{f.name}: {va!r} != {vb!r}")
        elif isinstance(va, float) and atol > 0:
            if abs(va - vb) > atol:
                raise AssertionError(f"{f.name}: {va!r} != {vb!r}")
        elif va != vb:
            raise AssertionError(f"{f.name}: {va!r} != {vb!r}")


# The message type each logical topic carries.
TOPIC_TYPES: Final[dict[str, type]] = {
    TOPIC_ODOM: OdometryPose,
    TOPIC_GROUND_TRUTH_POSE: GroundTruthPose,
    TOPIC_RANGE_BEARING: RangeBearingScan,
    TOPIC_GROUND_TRUTH_LANDMARKS: LandmarkMap,
    TOPIC_CAMERA_IMAGE: CameraImage,
    TOPIC_CAMERA_CALIBRATION: CameraCalibration,
    TOPIC_CMD_VEL: VelocityCommand,
    TOPIC_NAV_LOCALIZATION: NavLocalization,
    TOPIC_IMU_YAW_RATE: ImuYawRate,
}
