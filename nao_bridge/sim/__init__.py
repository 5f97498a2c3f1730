"""The simulated NAO: a room, landmarks, an object, body and head dynamics and a rendered camera."""

from .backend import SimBackend
from .scenarios import Scenario, SimConfig, load_sim_config
from .world import SimWorld

__all__ = ["SimBackend", "SimWorld", "Scenario", "SimConfig", "load_sim_config"]
