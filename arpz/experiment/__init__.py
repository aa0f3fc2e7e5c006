"""Reproduce seed 001's experiments (and extend them): ``python -m arpz.experiment``.

docs/experiments.md describes the spec, the presets, results.csv and the figures;
EXPERIMENTS.md has the results of the full runs.
"""

from arpz.experiment.spec import (
    PROFILES,
    Cell,
    ExperimentSpec,
    MissionSpec,
    NetworkProfile,
    SpecError,
    load_spec,
)

__all__ = [
    "PROFILES",
    "Cell",
    "ExperimentSpec",
    "MissionSpec",
    "NetworkProfile",
    "SpecError",
    "load_spec",
]
