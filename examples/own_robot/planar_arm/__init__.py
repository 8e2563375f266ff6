"""A robot of one's own for rl-pool: a three-link planar arm that reaches for a target.

Importing this package registers ``PlanarArm-v0`` with gymnasium, so
``rl-pool launch --env planar_arm:PlanarArm-v0`` works once this directory's parent is on
``PYTHONPATH`` (gymnasium imports ``planar_arm`` for the part before the colon).
"""

import gymnasium

from .env import XML, PlanarArmEnv

__all__ = ["XML", "PlanarArmEnv"]

if "PlanarArm-v0" not in gymnasium.registry:
    gymnasium.register(id="PlanarArm-v0", entry_point="planar_arm.env:PlanarArmEnv",
                       max_episode_steps=100)
