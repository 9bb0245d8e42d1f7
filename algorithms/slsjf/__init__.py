"""SLSJF: the Sparse Local Submap Joining Filter (Huang, Wang, Dissanayake 2008), D-SLAM's authors' extension
for sparse data, and its iterated form (I-SLSJF)."""

from slamreplay.algorithms.slsjf.filter import Slsjf, SlsjfConfig, SlsjfScanResult
from slamreplay.algorithms.slsjf.joining import GlobalMap, LocalMap

__all__ = ["GlobalMap", "LocalMap", "Slsjf", "SlsjfConfig", "SlsjfScanResult"]
