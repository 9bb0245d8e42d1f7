"""Point landmarks from a planar laser scan: poles and tree trunks, found as small circles.

The method is the one used on Victoria Park's trees [1]_: the scan is cut into segments where
consecutive ranges jump, a segment that stands in front of both its neighbours and is as wide as
a pole is kept, and a circle is fitted to its points. The landmark is the circle's centre, as a
range and bearing in the sensor frame.

- Segmentation: a new segment starts where ``|r_i - r_{i-1}| > jump_m`` or a reading is invalid
  (outside ``[range_min, range_max]`` of the scan and ``max_range_m``, or not finite).
- Isolation: both neighbouring readings (or missing ones) lie at least ``jump_m`` behind the
  segment, so a pole is not confused with the edge of a wall.
- Diameter from the angular width, as in [1]_ (eq. of section V.A): ``d = r_mean * width``;
  the centre then lies ``d / 2`` behind the nearest point along the mean bearing.
- Circle fit: a geometric least-squares fit of centre and radius (Gauss-Newton on the point to
  circle distances, started from the width estimate). It is kept when it converges to a radius in
  ``[min_diameter_m, max_diameter_m] / 2``, with points within ``max_fit_rms_m`` of the circle, and
  a centre better determined than the width estimate (whose position is uncertain by half a beam's
  width at that range, the covariance it is given); otherwise the width estimate stands
  (``circle_fit=False`` switches the fit off, leaving [1]_'s estimate alone).
- Covariance: the fit's ``s^2 (J^T J)^-1`` of the centre, turned into range and bearing,
  plus the configured floor ``range_sigma_m`` / ``bearing_sigma_rad`` (the beam's own noise) in
  quadrature.

References
----------
.. [1] J. Guivant, E. Nebot, "Optimization of the simultaneous localization and map-building
   algorithm for real-time implementation", IEEE Trans. Robotics and Automation 17(3), 2001.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from slamreplay.recorder.importers.pole_config import PoleConfig as PoleConfig  # re-exported

F64 = NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class Poles:
    """Poles found in one scan: centres as range and bearing, their 1-sigma, and radii."""

    ranges_m: F64
    bearings_rad: F64
    range_sigmas_m: F64
    bearing_sigmas_rad: F64
    radii_m: F64

    def __len__(self) -> int:
        return len(self.ranges_m)


def _fit_circle(x: F64, y: F64, cx: float, cy: float, r: float, iterations: int = 20
                ) -> tuple[float, float, float, F64] | None:
    """Geometric circle fit (Gauss-Newton); centre, radius and the centre's covariance, or None."""
    p = np.array([cx, cy, r])
    for _ in range(iterations):
        dx, dy = x - p[0], y - p[1]
        d = np.hypot(dx, dy)
        if np.any(d < 1e-9):
            return None
        res = d - p[2]
        J = np.column_stack([-dx / d, -dy / d, -np.ones_like(d)])
        try:
            step = np.linalg.lstsq(J, -res, rcond=None)[0]
        except np.linalg.LinAlgError:
            return None
        p = p + step
        if np.linalg.norm(step) < 1e-9:
            break
    dx, dy = x - p[0], y - p[1]
    d = np.hypot(dx, dy)
    res = d - p[2]
    J = np.column_stack([-dx / d, -dy / d, -np.ones_like(d)])
    dof = max(len(x) - 3, 1)
    s2 = float(res @ res) / dof
    try:
        cov = np.linalg.inv(J.T @ J) * s2
    except np.linalg.LinAlgError:
        return None
    if not np.all(np.isfinite(cov)):
        return None
    return float(p[0]), float(p[1]), float(p[2]), cov[:2, :2]


def extract_poles(ranges: ArrayLike, angle_min_rad: float, angle_increment_rad: float, cfg: PoleConfig,
                  range_min_m: float = 0.0, range_max_m: float = math.inf) -> Poles:
    """Find pole-like objects in one planar scan.

    Parameters
    ----------
    ranges : (n,) ranges in metres, reading ``i`` at angle ``angle_min_rad + i * angle_increment_rad``
        (counter-clockwise from the sensor's +x); NaN, inf and readings outside
        ``[range_min_m, range_max_m]`` are invalid.
    cfg : the extractor's settings.

    Returns
    -------
    Poles : in scan order.
    """
    r = np.asarray(ranges, dtype=np.float64).ravel()
    angles = angle_min_rad + angle_increment_rad * np.arange(len(r))
    valid = np.isfinite(r) & (r >= range_min_m) & (r <= min(range_max_m, cfg.max_range_m)) & (r > 0)
    out: list[tuple[float, float, float, float, float]] = []
    n = len(r)
    i = 0
    while i < n:
        if not valid[i]:
            i += 1
            continue
        j = i
        while j + 1 < n and valid[j + 1] and abs(r[j + 1] - r[j]) <= cfg.jump_m:
            j += 1
        seg = slice(i, j + 1)
        i = j + 1
        count = seg.stop - seg.start
        if count < cfg.min_points:
            continue
        rs, th = r[seg], angles[seg]
        near = float(rs.min())
        # isolation: the neighbours are invalid (nothing behind within range) or well behind
        before = seg.start - 1
        after = seg.stop
        if before >= 0 and valid[before] and r[before] < near + cfg.jump_m:
            continue
        if after < n and valid[after] and r[after] < near + cfg.jump_m:
            continue
        width = abs(angle_increment_rad) * count
        diameter = float(np.mean(rs)) * width
        if not cfg.min_diameter_m <= diameter <= cfg.max_diameter_m:
            continue
        bearing = float(np.mean(th))
        centre_range = near + diameter / 2.0
        radius = diameter / 2.0
        cov_xy = np.zeros((2, 2))
        cx, cy = centre_range * math.cos(bearing), centre_range * math.sin(bearing)
        if cfg.circle_fit and count >= 4:
            fit = _fit_circle(rs * np.cos(th), rs * np.sin(th), cx, cy, radius)
            if fit is not None and cfg.min_diameter_m <= 2 * fit[2] <= cfg.max_diameter_m:
                fx, fy, fr, fcov = fit
                rms = float(np.sqrt(np.mean((np.hypot(rs * np.cos(th) - fx, rs * np.sin(th) - fy) - fr) ** 2)))
                # the centre must lie behind the points it was fitted to (not a concave arc)
                if rms > cfg.max_fit_rms_m:
                    continue
                # kept when behind its points and better determined than the width estimate, whose
                # range is uncertain by about one beam's width at that range
                width_var = (near * abs(angle_increment_rad) / 2.0) ** 2
                if math.hypot(fx, fy) > near and np.trace(fcov) < 2.0 * width_var:
                    cx, cy, radius, cov_xy = fx, fy, fr, fcov
        if not cov_xy.any():
            beam = near * abs(angle_increment_rad) / 2.0
            cov_xy = np.eye(2) * beam**2
        rng = math.hypot(cx, cy)
        brg = math.atan2(cy, cx)
        # Jacobian of (range, bearing) w.r.t. (x, y) at the centre
        Jp = np.array([[cx / rng, cy / rng], [-cy / rng**2, cx / rng**2]])
        cov_rb = Jp @ cov_xy @ Jp.T
        out.append((rng, brg, math.sqrt(cfg.range_sigma_m**2 + max(cov_rb[0, 0], 0.0)),
                    math.sqrt(cfg.bearing_sigma_rad**2 + max(cov_rb[1, 1], 0.0)), radius))
    arr = np.array(out, dtype=np.float64).reshape(-1, 5)
    return Poles(arr[:, 0].copy(), arr[:, 1].copy(), arr[:, 2].copy(), arr[:, 3].copy(), arr[:, 4].copy())

