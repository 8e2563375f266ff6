"""What a return on PlanarArm-v0 means: two hand-written controllers on the episodes that
``rl-pool evaluate AGENT --episodes 50`` uses (reset seeds 1000000 + k).

* ``still``: every command 0 (the arm stays where it starts; the untrained agent's Beta mean);
* ``jacobian``: a torque at each joint equal to the z-component of (tip - joint) x (target - tip),
  times a gain, minus damping on the joint velocity (the Jacobian-transpose controller of robotics
  textbooks), clipped to [-1, 1]. It reads the simulator's state, not the observation. Its gain
  and damping are the best of a 4 x 3 grid on other episodes (reset seeds 0..49).

    PYTHONPATH=examples/own_robot python examples/own_robot/reference.py [--episodes 50]
"""

import argparse

import gymnasium
import numpy as np
import planar_arm  # noqa: F401  (registers PlanarArm-v0)

LINKS = ("upper", "fore", "hand")


def jacobian(env, gain=1000.0, damping=2.0):
    m, d = env.model, env.data
    tip = d.site_xpos[m.site("fingertip").id][:2]
    error = d.site_xpos[m.site("target").id][:2] - tip
    torque = []
    for link in LINKS:
        lever = tip - d.xpos[m.body(link).id][:2]
        torque.append(lever[0] * error[1] - lever[1] * error[0])
    return np.clip(gain * np.asarray(torque) - damping * d.qvel, -1.0, 1.0)


def still(env):
    return np.zeros(env.model.nu)


def score(controller, episodes, seed=1_000_000):
    env = gymnasium.make("PlanarArm-v0").unwrapped
    steps = gymnasium.spec("PlanarArm-v0").max_episode_steps
    returns = []
    for k in range(episodes):
        env.reset(seed=seed + k)
        total = 0.0
        for _ in range(steps):
            _, reward, _, _, _ = env.step(controller(env))
            total += reward
        returns.append(total)
    return np.asarray(returns)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=50)
    args = parser.parse_args()
    for name, controller in (("still", still), ("jacobian", jacobian)):
        r = score(controller, args.episodes)
        print(f"{name:9s} {r.mean():7.2f} ± {r.std():.2f} (min {r.min():.2f}, max {r.max():.2f}) "
              f"over {args.episodes} episodes")
