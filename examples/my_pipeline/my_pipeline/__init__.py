"""An example slamreplay pipeline plugin: a constant-velocity Kalman filter over wheel odometry."""

__version__ = "0.1.0"
