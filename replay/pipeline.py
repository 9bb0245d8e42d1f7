"""Kept for plugins written against the flat layout: this path is ``slamreplay.replay.engine.pipeline``, the same
module object (so attributes set on one are seen through the other)."""

import sys

from slamreplay.replay.engine import pipeline as _moved

sys.modules[__name__] = _moved
