"""Simulators that produce slamreplay recordings."""

from slamreplay.recorder.sim.landmarks import LandmarkSimConfig, SimSummary, simulate_landmarks

__all__ = ["LandmarkSimConfig", "SimSummary", "simulate_landmarks"]
