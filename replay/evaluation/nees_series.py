"""A run's NEES over time as a small file of its own, ``nees.json``, for pages and tools that cannot read run.rrd.

A pipeline that scores its pose estimate's consistency (the landmark SLAM pipelines: ``dslam``, ``ekfslam``,
``slsjf``) writes the per-scan robot pose NEES that its ``robot_nees_mean`` metric averages, with the band a
consistent filter's NEES lies in, into the run directory as an artifact (listed in the manifest with its
sha256, written atomically). The same inputs give the same bytes: times are the recording's, numbers are
rounded to a fixed number of digits and the JSON is written with sorted keys, no wall clock anywhere.

The band is said once, here (:func:`chi2_band`): the .rrd's ``metrics/nees_band/*`` series and this file
hold the same numbers.

File format (``format`` 1)::

    {"format": 1,
     "series": {"robot": {"description": ..., "dof": 3, "level": 0.95, "band": [low, high],
                          "metric": "robot_nees_mean", "mean": m, "steps": n, "stride": s,
                          "t0_ns": first time (int ns), "t_s": [...], "nees": [...]}}}

``t_s`` are seconds after ``t0_ns`` (rounded to the microsecond) and ``nees`` the values (6 significant
digits). ``mean`` is the mean of all ``steps`` values at full precision: the metric's value. A run of more
than ``MAX_POINTS`` steps keeps every ``stride``-th step, the first included (``stride = ceil(steps /
MAX_POINTS)``), so that a long run's file stays under about 20 kB. Decimated, not averaged: each point is
one step's NEES, which the band is the band of (a mean of k steps would lie in a far narrower band, and
steps of one run are correlated in time, so no band of a mean would be right); ``mean`` stays exact.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

NEES_ARTIFACT = "nees.json"
NEES_FORMAT = 1
BAND_LEVEL = 0.95  # the central probability of every NEES band slamreplay draws
MAX_POINTS = 1000


def chi2_band(dof: int, level: float = BAND_LEVEL) -> tuple[float, float]:
    """The central ``level`` interval of a chi-square with ``dof`` degrees of freedom: where the NEES of a
    consistent ``dof``-dimensional estimate lies with probability ``level``.

    Parameters
    ----------
    dof : int, >= 1, the estimated state's dimension (3 for a planar pose)
    level : float in (0, 1)
    """
    from scipy.stats import chi2

    if dof < 1:
        raise ValueError(f"dof must be >= 1, got {dof}")
    if not 0.0 < level < 1.0:
        raise ValueError(f"level must be in (0, 1), got {level}")
    return float(chi2.ppf((1 - level) / 2, dof)), float(chi2.ppf((1 + level) / 2, dof))


@dataclass(frozen=True, slots=True)
class NeesSeries:
    """One quantity's NEES at each step, as a pipeline computed it.

    Attributes
    ----------
    t_ns : (n,) int64, the steps' recording times (ns), increasing
    nees : (n,) float64, the NEES at each step
    band : (low, high) of a consistent filter's NEES (``low`` is 0 when the truth is itself an estimate)
    """

    description: str
    dof: int
    band: tuple[float, float]
    t_ns: NDArray[np.int64]
    nees: NDArray[np.float64]
    metric: str | None = None  # the metric that is this series' mean
    level: float = BAND_LEVEL


@dataclass(frozen=True, slots=True)
class NeesCurve:
    """One series as read back from ``nees.json``: ``t_s`` (k,) seconds after ``t0_ns``, ``nees`` (k,) the NEES
    of every ``stride``-th of its ``steps`` (NaN where it was not finite); ``mean`` over all of them."""

    description: str
    dof: int
    level: float
    band: tuple[float, float]
    metric: str | None
    mean: float
    steps: int
    stride: int
    t0_ns: int
    t_s: NDArray[np.float64]
    nees: NDArray[np.float64]


def _num(v: float, digits: int = 6) -> float | None:
    """``v`` rounded to ``digits`` significant digits (the file's size and bytes stay put); None if not finite."""
    return float(f"{v:.{digits}g}") if math.isfinite(v) else None


def downsample(t_ns: NDArray[np.int64], values: NDArray[np.float64],
               most: int = MAX_POINTS) -> tuple[NDArray[np.int64], NDArray[np.float64], int]:
    """(times, values, stride) of every ``stride``-th step, the first included, ``stride = ceil(n / most)``: at
    most ``most`` steps; the input itself (stride 1) when it has no more."""
    stride = max(1, math.ceil(len(values) / most))
    return t_ns[::stride], values[::stride], stride


def nees_artifact(series: Mapping[str, NeesSeries], most: int = MAX_POINTS) -> bytes:
    """``nees.json`` bytes of ``series`` (by name, e.g. ``robot``); empty series are left out.

    ValueError when a series' times and values differ in length or its times decrease.
    """
    doc: dict[str, Any] = {}
    for name, s in series.items():
        t_ns, nees = np.asarray(s.t_ns, np.int64), np.asarray(s.nees, np.float64)
        if t_ns.shape != nees.shape or t_ns.ndim != 1:
            raise ValueError(f"series {name!r}: t_ns {t_ns.shape} and nees {nees.shape} must be equal (n,) arrays")
        if np.any(np.diff(t_ns) < 0):
            raise ValueError(f"series {name!r}: t_ns must not decrease")
        if not len(t_ns):
            continue
        t_pts, v_pts, stride = downsample(t_ns, nees, most)
        t0 = int(t_ns[0])
        doc[name] = {
            "description": s.description, "dof": int(s.dof), "level": float(s.level),
            "band": [float(s.band[0]), float(s.band[1])], "metric": s.metric,
            "mean": _num(float(np.mean(nees)), 17), "steps": len(nees), "stride": stride, "t0_ns": t0,
            "t_s": [round((int(t) - t0) * 1e-9, 6) for t in t_pts.tolist()],
            "nees": [_num(v) for v in v_pts.tolist()],
        }
    return (json.dumps({"format": NEES_FORMAT, "series": doc}, sort_keys=True, separators=(",", ":"),
                       allow_nan=False) + "\n").encode()


def read_nees(text: str | bytes) -> dict[str, NeesCurve]:
    """The series of a ``nees.json`` by name; ValueError when it is not one (another format, missing fields)."""
    try:
        doc = json.loads(text)
        if doc.get("format") != NEES_FORMAT:
            raise ValueError(f"not a {NEES_ARTIFACT} file: format {doc.get('format')!r}, expected {NEES_FORMAT}")
        out = {}
        for name, s in doc["series"].items():
            steps, stride = int(s["steps"]), int(s["stride"])
            k = len(s["nees"])
            out[str(name)] = NeesCurve(
                str(s["description"]), int(s["dof"]), float(s["level"]), (float(s["band"][0]), float(s["band"][1])),
                s.get("metric"), math.nan if s["mean"] is None else float(s["mean"]), steps, stride, int(s["t0_ns"]),
                np.asarray(s["t_s"], np.float64), np.array([math.nan if v is None else v for v in s["nees"]],
                                                            np.float64))
            if len(out[str(name)].t_s) != k or k != -(-steps // max(stride, 1)):
                raise ValueError(f"series {name!r}: {len(s['t_s'])} times, {k} values for {steps} steps")
        return out
    except (KeyError, TypeError, AttributeError, json.JSONDecodeError) as err:
        raise ValueError(f"not a {NEES_ARTIFACT} file: {type(err).__name__}: {err}") from err

