"""EKF-SLAM: the full-covariance baseline ("traditional SLAM") D-SLAM is compared with."""

from slamreplay.algorithms.ekfslam.filter import EkfScanResult, EkfSlam, EkfSlamConfig

__all__ = ["EkfScanResult", "EkfSlam", "EkfSlamConfig"]
