"""Reference points for Reacher-v5 (not rl-pool agents): what a hand-written controller and the
best linear fit of it score on the same 100 fresh episodes (reset seeds 1000-1099).

    .venv/bin/python results/reacher-v5/reference_controllers.py

The controller is Jacobian-transpose PD control, tau = -Kp J(q)^T (tip - target) - Kd qdot, clipped
to the action box, with the arm's link lengths (0.1, 0.11) and the observation's cos/sin of the
joint angles, joint velocities and fingertip-minus-target vector. The linear fit regresses its
actions on the raw observation (and 1) over 300 episodes of states it visits (with a little noise),
to show how much of it a policy linear in the observation can express.
"""

import gymnasium as gym
import numpy as np

L1, L2 = 0.1, 0.11


def pd(o, kp, kd):
    c1, c2, s1, s2 = o[0], o[1], o[2], o[3]
    c12, s12 = c1 * c2 - s1 * s2, s1 * c2 + c1 * s2
    jac = np.array([[-L1 * s1 - L2 * s12, -L2 * s12], [L1 * c1 + L2 * c12, L2 * c12]])
    return np.clip(-kp * jac.T @ o[8:10] - kd * o[6:8], -1.0, 1.0)


def fmt(mean_std):
    return f"{mean_std[0]:.2f} ± {mean_std[1]:.2f}"


def score(env, act, episodes=100):
    out = []
    for s in range(episodes):
        o, _ = env.reset(seed=1000 + s)
        total, done = 0.0, False
        while not done:
            o, r, term, trunc, _ = env.step(act(o))
            total, done = total + r, term or trunc
        out.append(total)
    return float(np.mean(out)), float(np.std(out))


def main():
    env = gym.make("Reacher-v5")
    print("zero action:            " + fmt(score(env, lambda o: np.zeros(2))))
    for kp, kd in [(20, 0.05), (20, 0.1), (50, 0.3)]:
        print(f"PD Kp={kp:<3} Kd={kd:<4}:        " + fmt(score(env, lambda o, kp=kp, kd=kd: pd(o, kp, kd))))
    rng = np.random.default_rng(0)
    xs, ys = [], []
    for s in range(300):
        o, _ = env.reset(seed=s)
        for _ in range(50):
            a = pd(o, 20, 0.1)
            xs.append(np.r_[o, 1.0])
            ys.append(a)
            o, *_ = env.step(np.clip(a + 0.1 * rng.standard_normal(2), -1.0, 1.0))
    x, y = np.array(xs), np.array(ys)
    w, *_ = np.linalg.lstsq(x, y, rcond=None)
    r2 = 1 - ((x @ w - y) ** 2).sum() / ((y - y.mean(0)) ** 2).sum()
    print(f"linear fit of PD (R2 {r2:.2f}): " + fmt(score(env, lambda o: np.clip(np.r_[o, 1.0] @ w, -1, 1))))


if __name__ == "__main__":
    main()
