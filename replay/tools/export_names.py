"""The exports external programs can ask for, by name, and what each writes: read by ``export --help`` without
importing the writers (``slamreplay.replay.tools.export``, whose ``EXPORTS`` has the same names)."""

from __future__ import annotations

EXPORT_FILES: dict[str, str] = {
    "odometry_tum": "odometry.tum",
    "odometry_csv": "odometry.csv: t_ns,x_m,y_m,yaw_rad",
    "range_bearing_csv": "range_bearing.csv: t_ns,landmark_id,range_m,bearing_rad",
    "images": "images/<t_ns>.png and images/times.csv",
    "ros2_bag": "ros2_bag/: a ROS 2 bag (sqlite3) of /odom, with the images and scans the recording has",
}


def exports_help() -> str:
    """Every export and what it writes, for ``export --help``."""
    return ", ".join(f"{name} ({what})" for name, what in EXPORT_FILES.items())
