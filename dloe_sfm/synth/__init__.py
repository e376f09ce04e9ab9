"""Capture simulation for tests and benchmarks (the paper's motion-capture protocol)."""

from .mocap import (
    MocapSequence,
    SimulationSettings,
    load_mocap,
    pipeline_parser,
    resolve_motion,
    ring_cameras,
    sibling_pipeline,
    simulate,
)

__all__ = ["MocapSequence", "SimulationSettings", "load_mocap", "pipeline_parser",
           "resolve_motion", "ring_cameras", "sibling_pipeline", "simulate"]
