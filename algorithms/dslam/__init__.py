"""D-SLAM (Wang, Huang, Dissanayake 2005): decoupled EIF mapping and Covariance Intersection localization."""

from slamreplay.algorithms.dslam.filter import DSlam, DSlamConfig, ScanResult, ScanStatus

__all__ = ["DSlam", "DSlamConfig", "ScanResult", "ScanStatus"]
