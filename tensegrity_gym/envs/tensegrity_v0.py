"""Tensegrity-v0: any tensegrity MJCF as an env, on the plant or on its identified twin.

The same env as ``TensegrityIco-v0`` (:mod:`tensegrity_gym.envs.tensegrity_ico_v0` holds its
observation, reward and termination, once for every model and both backends); what it derives
from the model instead of the robot preset's constants is written here.
"""

from __future__ import annotations

import os
from typing import Any

from tensegrity_gym.backends import Backend
from tensegrity_gym.envs.tensegrity_ico_v0 import TensegrityIcoEnv

__all__ = ["TensegrityEnv"]


class TensegrityEnv(TensegrityIcoEnv):
    r"""
    ## Description
    Any tensegrity written as an MJCF (Gymnasium's MuJoCo convention: `xml_file=PATH`): rods are
    the model's free bodies with their jointless descendants, cables its spatial tendons, controls
    its MuJoCo tendon actuators and its rest-length motors. The goal is to move the structure's
    centre along +x. `gym.make("Tensegrity-v0", xml_file=PATH)` is the plant;
    `gym.make("Tensegrity-v0", xml_file=PATH, backend="identified", model="F.json")` the twin
    identified from it (the MJCF gives it motors, standing pose and drawing, never parameters).

    ## Action Space
    `Box(-1, 1, (A + U,), float32)`: first the target rest length of every cable with a
    rest-length motor (A, -1 -> `rest_min`, +1 -> `rest_max`), then the command of every MuJoCo
    tendon actuator (U, -1 -> low, +1 -> high end of its `ctrlrange`; an actuator without a
    `ctrlrange` is refused). Commands are held for `frame_skip` physics steps.

    ## Observation Space
    As `TensegrityIco-v0` (`observation`): the structure's height, rod positions relative to its
    centre, rod rotation matrices, velocities and angular velocities (a rod's position and
    orientation are its free body's frame), the motors' rest lengths normalised like the action,
    then every actuator's state (its activation where it has dynamics, else its command)
    normalised over its `ctrlrange`: `1 + 18 R + A + U` floats.

    ## Rewards
    As `TensegrityIco-v0`: forward speed of the structure's centre minus `ctrl_cost_weight |a|^2`.

    ## Starting State
    The model's standing pose (`tensegrity_gym.plant.standing_pose`: its keyframe `nominal`, else
    its first keyframe, else the pose it settles in within 5 s from `qpos0`), the MJCF rest
    lengths, actuators at zero command, plus uniform noise of `reset_noise_scale`.

    ## Episode End
    Non-finite state; with `terminate_when_unhealthy=True`, the structure's centre leaving
    `healthy_z_range`, by default derived from the model (`healthy_range`: a quarter to three times
    its standing height above its ground plane; no height check without a ground plane).
    `gym.make` adds a `TimeLimit` of 1000 steps.

    ## Arguments
    Those of `TensegrityIco-v0`, with `xml_file` (required for the plant) and
    `healthy_z_range="auto"`.

    ## Version History
    * v0: first version.
    """

    def __init__(self, xml_file: str | os.PathLike | None = None, backend: str | Backend = "mujoco",
                 model: str | os.PathLike | Any | None = None,
                 healthy_z_range: tuple[float, float] | str | None = "auto", **kwargs: Any) -> None:
        if xml_file is None and model is None and backend == "mujoco":
            raise ValueError("Tensegrity-v0 needs the robot's MJCF: gym.make('Tensegrity-v0', xml_file=PATH)")
        if xml_file is None and backend == "identified" and not (kwargs.get("backend_kwargs") or {}).get("mjcf"):
            raise ValueError("Tensegrity-v0 on the twin needs the MJCF its model was fitted against: "
                             "gym.make('Tensegrity-v0', xml_file=PATH, backend='identified', model=F.json)")
        super().__init__(backend=backend, model=model, healthy_z_range=healthy_z_range, xml_file=xml_file,
                         **kwargs)
