"""Simulator: scenes, quadrotor physics back ends (pybullet, native) and controller, depth camera, expert, rollouts.

Quick tour::

    from vitfly.sim import ExpertPolicy, RolloutConfig, make_scene, run_episodes
    scene = make_scene("spheres", "medium", seed=0)
    result = run_episodes([scene], speeds=[5.0], policy=ExpertPolicy(), config=RolloutConfig(record_depth=True))[0]
    result.summary.success, result.log.depth.shape    # True, (T, 60, 90)
"""

from vitfly.sim.camera import CAMERA_PRESETS, CameraConfig, DepthCamera
from vitfly.sim.collision import ContactChecker, signed_distances
from vitfly.sim.controller import ControllerGains, velocity_control
from vitfly.sim.expert import ExpertConfig, ExpertObstacles, expert_command
from vitfly.sim.physics import PHYSICS_BACKENDS, Fleet, make_fleet, resolve_physics
from vitfly.sim.policies import BUILTIN_POLICIES, ExpertPolicy, MixturePolicy, StraightPolicy, make_builtin_policy
from vitfly.sim.quadrotor import Airframe, DroneState
from vitfly.sim.rollout import (
    EpisodeLog,
    EpisodeResult,
    EpisodeSummary,
    LabelledCommands,
    Observation,
    Policy,
    RolloutConfig,
    TaskConfig,
    run_episodes,
)
from vitfly.sim.scenes import ENVS, PRESETS, Scene, load_scene, make_scene, save_scene

__all__ = [
    "Airframe",
    "BUILTIN_POLICIES",
    "CAMERA_PRESETS",
    "CameraConfig",
    "ContactChecker",
    "ControllerGains",
    "DepthCamera",
    "DroneState",
    "ENVS",
    "EpisodeLog",
    "EpisodeResult",
    "EpisodeSummary",
    "ExpertConfig",
    "ExpertObstacles",
    "ExpertPolicy",
    "Fleet",
    "LabelledCommands",
    "MixturePolicy",
    "Observation",
    "PHYSICS_BACKENDS",
    "PRESETS",
    "Policy",
    "RolloutConfig",
    "Scene",
    "StraightPolicy",
    "TaskConfig",
    "expert_command",
    "load_scene",
    "make_builtin_policy",
    "make_fleet",
    "make_scene",
    "resolve_physics",
    "run_episodes",
    "save_scene",
    "signed_distances",
    "velocity_control",
]
