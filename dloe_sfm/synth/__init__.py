"""Capture simulation for tests and benchmarks (the paper's motion-capture protocol)."""

from .mocap import (
    MocapSequence,
    SimulationSettings,
    load_mocap,
    load_pipeline,
    pipeline_parser,
    resolve_motion,
    ring_cameras,
    sibling_pipeline,
    simulate,
)

__all__ = ["MocapSequence", "SimulationSettings", "load_mocap", "load_pipeline", "pipeline_parser",
           "resolve_motion", "ring_cameras", "sibling_pipeline", "simulate"]
