"""Built-in pipelines; importing this package registers them."""

from replay.pipelines import ifmi, odometry

__all__ = ["ifmi", "odometry"]
