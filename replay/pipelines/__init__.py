"""Built-in pipelines; importing this package registers them."""

from replay.pipelines import dslam, ekfslam, ifmi, odometry, topometric, topometric_nav

__all__ = ["dslam", "ekfslam", "ifmi", "odometry", "topometric", "topometric_nav"]
