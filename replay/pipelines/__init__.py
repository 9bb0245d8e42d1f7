"""Built-in pipelines; importing this package registers them."""

from replay.pipelines import odometry

__all__ = ["odometry"]
