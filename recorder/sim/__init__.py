"""Simulators that produce slamreplay recordings."""

from recorder.sim.landmarks import LandmarkSimConfig, SimSummary, simulate_landmarks

__all__ = ["LandmarkSimConfig", "SimSummary", "simulate_landmarks"]
