"""The planar arm as a gymnasium MuJoCo environment.

Observation (13 numbers): cos and sin of the three joint angles, the three joint velocities,
the target's (x, y) and the vector from the target to the fingertip.
Action: three motor commands in [-1, 1] (the model's ``ctrlrange``), each times the motor's gear
(0.05 N m) as a joint torque.
Reward per step: minus the fingertip's distance to the target (metres), minus
``ctrl_cost_weight`` times the squared command. The episode length comes from the registration
(``max_episode_steps``); nothing ends an episode earlier.
"""

from __future__ import annotations

import os
from typing import ClassVar

import numpy as np
from gymnasium.envs.mujoco.mujoco_env import MujocoEnv
from gymnasium.spaces import Box

XML = os.path.join(os.path.dirname(os.path.abspath(__file__)), "planar_arm.xml")

#: A camera above the table looking straight down, so the replay shows the whole reach.
TOP_DOWN = {"lookat": np.array([0.0, 0.0, 0.0]), "distance": 0.95, "elevation": -90.0, "azimuth": 90.0}


class PlanarArmEnv(MujocoEnv):
    """Reach a target with the tip of a three-link planar arm."""

    metadata: ClassVar[dict] = {"render_modes": ["human", "rgb_array", "depth_array", "rgbd_tuple"]}

    def __init__(
        self,
        xml_file: str = XML,
        frame_skip: int = 2,
        ctrl_cost_weight: float = 0.01,
        target_radius: tuple[float, float] = (0.10, 0.28),
        target_angle: float = np.pi / 2,
        reset_noise_scale: float = 0.1,
        default_camera_config: dict | None = None,
        **kwargs,
    ):
        self._ctrl_cost_weight = float(ctrl_cost_weight)
        self._target_radius = (float(target_radius[0]), float(target_radius[1]))
        self._target_angle = float(target_angle)
        self._reset_noise_scale = float(reset_noise_scale)
        observation_space = Box(low=-np.inf, high=np.inf, shape=(13,), dtype=np.float64)
        MujocoEnv.__init__(
            self,
            xml_file,
            frame_skip,
            observation_space=observation_space,
            default_camera_config=TOP_DOWN if default_camera_config is None else default_camera_config,
            **kwargs,
        )
        # the frame rate follows the control step (timestep x frame_skip), whatever the XML says
        self.metadata = {**self.metadata, "render_fps": int(np.round(1.0 / self.dt))}
        self._tip = self.model.site("fingertip").id
        self._target = self.model.site("target").id

    def _distance_vector(self) -> np.ndarray:
        return self.data.site_xpos[self._tip][:2] - self.data.site_xpos[self._target][:2]

    def _get_obs(self) -> np.ndarray:
        q = self.data.qpos.ravel()
        return np.concatenate([
            np.cos(q), np.sin(q), self.data.qvel.ravel(),
            self.data.site_xpos[self._target][:2], self._distance_vector(),
        ])

    def step(self, action):
        action = np.asarray(action, dtype=np.float64)
        self.do_simulation(action, self.frame_skip)
        distance = float(np.linalg.norm(self._distance_vector()))
        ctrl_cost = self._ctrl_cost_weight * float(np.sum(np.square(action)))
        reward = -distance - ctrl_cost
        if self.render_mode == "human":
            self.render()
        info = {"distance": distance, "ctrl_cost": ctrl_cost}
        return self._get_obs(), reward, False, False, info

    def reset_model(self) -> np.ndarray:
        noise = self._reset_noise_scale
        qpos = self.init_qpos + self.np_random.uniform(-noise, noise, size=self.model.nq)
        qvel = self.init_qvel + self.np_random.uniform(-noise, noise, size=self.model.nv) * 0.1
        radius = self.np_random.uniform(*self._target_radius)
        angle = self.np_random.uniform(-self._target_angle, self._target_angle)
        self.model.site_pos[self._target][:2] = radius * np.cos(angle), radius * np.sin(angle)
        self.set_state(qpos, qvel)  # runs mj_forward, so site_xpos has the new target
        return self._get_obs()
