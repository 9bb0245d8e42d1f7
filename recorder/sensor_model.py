"""The sensor model a recording carries: its sensors' noise and limits, in named fields.

A recording says how noisy its sensors are, so that replaying it needs no hidden settings:
simulators write the model they simulated, importers the dataset's (measured or documented),
and a user's `Recorder` takes one. Pipelines read it as a configuration layer: a value the user
gives wins, then the recording's model, then the pipeline's default (`slamreplay.replay.engine.pipeline`).

Fields are optional (``None``: the recording does not say). Units are in the names; the
odometry noise follows ``algorithms/common/motion.py`` (sigma growing with the square root
of the distance and of the turned angle).
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from slamreplay.recorder.codec.bounds import MAX_JSON_DEPTH, json_depth
from slamreplay.recorder.errors import RecorderError

METADATA_KEY = "sensor_model"  # key of the JSON object inside the ``slamreplay.recording`` metadata record


def sensor_model_key(namespace: str = "") -> str:
    """Metadata key of the model of the robot whose topics are under ``namespace`` ("": the recording's one robot)."""
    if namespace and not (namespace.startswith("/") and not namespace.endswith("/")):
        raise RecorderError(f"a topic namespace starts with / and does not end with one, got {namespace!r}")
    return METADATA_KEY + namespace


@dataclass(frozen=True, slots=True)
class SensorModel:
    """Noise and limits of a recording's sensors; ``None`` where the recording does not say.

    ``source`` says where the figures come from (simulated, measured against ground truth,
    the dataset's documentation, the user's): `slamreplay inspect` prints it.
    """

    # odometry (algorithms/common/motion.py: OdometryNoise)
    translation_sigma_per_sqrt_m: float | None = field(default=None, metadata={
        "help": "odometry translation noise, m per sqrt(m) travelled"})
    heading_sigma_per_sqrt_m: float | None = field(default=None, metadata={
        "help": "odometry heading noise, rad per sqrt(m) travelled"})
    heading_sigma_per_sqrt_rad: float | None = field(default=None, metadata={
        "help": "odometry heading noise, rad per sqrt(rad) turned"})
    # range-bearing sensor
    range_sigma_m: float | None = field(default=None, metadata={"help": "range noise (1 sigma), m"})
    bearing_sigma_rad: float | None = field(default=None, metadata={"help": "bearing noise (1 sigma), rad"})
    outlier_rate: float | None = field(default=None, metadata={
        "help": "fraction of observations that are outliers (not explained by the sigmas)"})
    fov_rad: float | None = field(default=None, metadata={"help": "field of view (full angle), rad"})
    min_range_m: float | None = field(default=None, metadata={"help": "shortest observed range, m"})
    max_range_m: float | None = field(default=None, metadata={"help": "longest observed range, m"})
    # camera (pinhole)
    fx_px: float | None = field(default=None, metadata={"help": "camera focal length x, px"})
    fy_px: float | None = field(default=None, metadata={"help": "camera focal length y, px"})
    cx_px: float | None = field(default=None, metadata={"help": "camera principal point x, px"})
    cy_px: float | None = field(default=None, metadata={"help": "camera principal point y, px"})
    width_px: int | None = field(default=None, metadata={"help": "image width, px"})
    height_px: int | None = field(default=None, metadata={"help": "image height, px"})
    source: str = field(default="", metadata={"help": "where the figures come from"})

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if f.name == "source":
                if not isinstance(value, str):
                    raise RecorderError(f"sensor model: source must be a string, got {value!r}")
                continue
            if value is None:
                continue
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise RecorderError(f"sensor model: {f.name} must be a finite number, got {value!r}")
            if value < 0:
                raise RecorderError(f"sensor model: {f.name} must be >= 0, got {value!r}")
        if self.outlier_rate is not None and self.outlier_rate >= 1:
            raise RecorderError(f"sensor model: outlier_rate must be < 1, got {self.outlier_rate!r}")
        if self.fov_rad is not None and self.fov_rad > 2 * math.pi + 1e-9:
            raise RecorderError(f"sensor model: fov_rad must be at most 2 pi, got {self.fov_rad!r}")

    def values(self) -> dict[str, float | int]:
        """The stated figures (``None`` fields and ``source`` left out)."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)
                if f.name != "source" and getattr(self, f.name) is not None}

    def to_json(self) -> str:
        return json.dumps({**self.values(), **({"source": self.source} if self.source else {})}, sort_keys=True)

    @classmethod
    def from_mapping(cls, data: Mapping[str, Any]) -> SensorModel:
        """From a JSON object; RecorderError naming an unknown key or a bad value."""
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise RecorderError(f"sensor model: unknown key {unknown[0]!r}; known keys: {', '.join(sorted(known))}")
        return cls(**dict(data))

    @classmethod
    def from_record(cls, record: Mapping[str, str], namespace: str = "") -> SensorModel | None:
        """The model in a recording's ``slamreplay.recording`` metadata record (`slamreplay.recorder.writer`) of the
        robot under ``namespace`` ("": the only one), None when it carries none (older recordings, other
        tools' files); RecorderError when it is damaged.
        """
        text = record.get(sensor_model_key(namespace))
        if not text:
            return None
        if json_depth(text) > MAX_JSON_DEPTH:  # json.loads would recurse once per level
            raise RecorderError(f"the recording's sensor model nests {json_depth(text):,} deep (at most "
                                f"{MAX_JSON_DEPTH}): it is damaged; re-record it or pass every noise setting "
                                f"with --set")
        try:
            data = json.loads(text)
        except ValueError as err:
            raise RecorderError(f"the recording's sensor model is not valid JSON ({err}); "
                                f"re-record it or pass every noise setting with --set") from err
        if not isinstance(data, dict):
            raise RecorderError("the recording's sensor model is not a JSON object; re-record it")
        return cls.from_mapping(data)

    def describe(self) -> list[str]:
        """One line per stated figure, with its meaning (for `slamreplay inspect`)."""
        helps = {f.name: f.metadata.get("help", "") for f in dataclasses.fields(self)}
        return [f"{k} = {v:g}  ({helps[k]})" for k, v in self.values().items()]
