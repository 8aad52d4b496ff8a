"""MJCF models of spring-rod systems: the paper's presets and a SUPERball-like robot.

``build_model(system, preset, seed, integrator, overrides)`` returns MJCF text,
``write_model(path, ...)`` writes it atomically, and ``preset_parameters(...)`` gives the ground
truth (masses, inertias, stiffness, damping, rest lengths) the text was built from.
"""

from tensegrity_gym.models.builder import (
    INTEGRATORS,
    build_model,
    closed_faces,
    ico_cable_pairs,
    ico_rod_geometry,
    preset_parameters,
    resolve_preset,
    rod_inertia,
    write_model,
)
from tensegrity_gym.models.presets import DEFAULT_PRESET, OVERRIDE_KEYS, SYSTEMS

__all__ = [
    "DEFAULT_PRESET",
    "INTEGRATORS",
    "OVERRIDE_KEYS",
    "SYSTEMS",
    "build_model",
    "closed_faces",
    "ico_cable_pairs",
    "ico_rod_geometry",
    "preset_parameters",
    "resolve_preset",
    "rod_inertia",
    "write_model",
]
