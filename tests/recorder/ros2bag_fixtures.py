"""The tests' ROS 2 bags: the writer behind `slamreplay record sim-ros2-bag` (recorder/sim/ros2bag.py)."""

from slamreplay.recorder.sim.ros2bag import CUSTOM, LASER_X_M, BagTruth, write_bag

__all__ = ["CUSTOM", "LASER_X_M", "BagTruth", "write_bag"]
