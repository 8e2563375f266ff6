"""Parallel evaluation under spawn, custom workers, replay."""

import json
import os

import numpy as np
import pytest

from rl_pool import Agent
from rl_pool.commands.evaluate import EvalWorker, evaluate_bytes

from .conftest import SHORT, rl_pool
from .helpers import reference_episode


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    d = tmp_path_factory.mktemp("ev") / "pool"
    rl_pool("train", "--pool-dir", d, "--iterations", 2, *SHORT, "--quiet", check=0)
    return d


def test_evaluate_json_matches_a_plain_loop_and_workers_agree(trained):
    one = json.loads(rl_pool("evaluate", trained, "--episodes", 4, "--json", check=0).stdout)
    two = json.loads(rl_pool("evaluate", trained, "--episodes", 4, "--workers", 2, "--json", check=0).stdout)
    assert one["returns"] == two["returns"]  # episode order and values do not depend on workers
    agent = Agent.load(trained / "best.npz")
    ref = [reference_episode(agent, 1_000_000 + k)[0] for k in range(4)]
    np.testing.assert_allclose(one["returns"], ref, rtol=1e-12)
    assert one["episodes"] == 4 and one["mean_return"] == pytest.approx(np.mean(ref))
    assert one["std_return"] == pytest.approx(np.std(ref))


def test_example_worker_scores_x_distance_under_spawn(trained):
    out = json.loads(rl_pool("evaluate", trained / "best.npz", "--episodes", 3, "--workers", 2,
                             "--worker", "rl_pool.commands.examples:XDistance", "--json", check=0).stdout)
    agent = Agent.load(trained / "best.npz")
    ref = [reference_episode(agent, 1_000_000 + k)[1] for k in range(3)]
    np.testing.assert_allclose(out["returns"], ref, rtol=1e-12)


class Constant(EvalWorker):
    def evaluate(self, env, agent, seed):
        return float(seed % 7)


def test_custom_worker_class_pickles_under_spawn(trained):
    data = (trained / "best.npz").read_bytes()
    res = evaluate_bytes(data, 5, workers=2, seed=10, worker_cls=Constant)
    assert res["returns"] == [3.0, 4.0, 5.0, 6.0, 0.0]


@pytest.mark.parametrize("args, says", [
    (["--worker", "os:path"], "not a subclass"),
    (["--worker", "no_such_module:X"], "cannot import"),
    (["--episodes", 0], "must be positive"),
    (["--episodes", 10**10], "must be at most 1000000"),
])
def test_evaluate_bad_input(trained, args, says):
    proc = rl_pool("evaluate", trained, *args)
    assert proc.returncode == 2 and says in proc.stderr and len(proc.stderr.strip().splitlines()) == 1


def test_evaluate_refuses_non_agent_files(tmp_path):
    f = tmp_path / "x.npz"
    f.write_bytes(b"not a zip")
    proc = rl_pool("evaluate", f)
    assert proc.returncode == 2 and "not an rl-pool agent file" in proc.stderr
    proc = rl_pool("evaluate", tmp_path / "missing.npz")
    assert proc.returncode == 2 and "no agent file" in proc.stderr


def test_replay_writes_an_animated_gif(trained, tmp_path):
    from PIL import Image

    out = tmp_path / "swim.gif"
    proc = rl_pool("replay", trained, "--out", out, "--steps", 20, "--width", 64, "--height", 48, "--fps", 25)
    if proc.returncode != 0 and "render" in proc.stderr:
        pytest.skip(f"no offscreen OpenGL here: {proc.stderr.strip()}")
    assert proc.returncode == 0, proc.stderr
    im = Image.open(out)
    assert im.size == (64, 48) and im.n_frames == 21
    frames = []
    for k in (0, 20):
        im.seek(k)
        frames.append(np.asarray(im.convert("RGB"), dtype=float))
    assert frames[0].std() > 0  # a rendered scene, not a blank image
    # Swimmer steps 25 times a second: at 5 fps every 5th step is rendered, 0, 5, ..., 20
    slow = tmp_path / "slow.gif"
    proc = rl_pool("replay", trained, "--out", slow, "--steps", 20, "--width", 64, "--height", 48, "--fps", 5)
    assert proc.returncode == 0, proc.stderr
    im = Image.open(slow)
    assert im.n_frames == 5 and im.info["duration"] == 200
    assert "5 frames at 5.0 fps" in proc.stdout


def test_action_noise_benchmark_scores_mean_actions_as_a_plain_gymnasium_loop(tmp_path, capsys):
    """``benchmarks/action_noise.py``: the mean-action column equals an independent TimeLimit-wrapped
    gymnasium loop on the same reset seeds; sharper agents report a larger concentration; bad
    input gets one line and exit code 2."""
    import importlib.util

    import gymnasium as gym

    from .helpers import agent

    script = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "benchmarks", "action_noise.py")
    spec = importlib.util.spec_from_file_location("action_noise_benchmark", script)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    a = agent(3)
    a.save(tmp_path / "a.npz")
    assert mod.main([str(tmp_path / "a.npz"), "--episodes", "2", "--sharpen", "1,10"]) == 0
    rows = [line.split(" | ") for line in capsys.readouterr().out.splitlines()[1:]]
    want = []
    for k in range(2):
        env = gym.make("Swimmer-v5", max_episode_steps=60)
        obs, _ = env.reset(seed=1_000_000 + k)
        total, done = 0.0, False
        while not done:
            obs, r, term, trunc, _ = env.step(a.act(obs))
            total += r
            done = term or trunc
        want.append(total)
    assert [r[1] for r in rows] == ["1", "10"]
    assert float(rows[0][2].split(" ± ")[0]) == pytest.approx(np.mean(want), abs=0.051)
    assert float(rows[1][4]) > float(rows[0][4])
    for bad in (["--episodes", "0"], ["--sharpen", "0.5"], ["--sharpen", "x"]):
        assert mod.main([str(tmp_path / "a.npz"), *bad]) == 2
        assert capsys.readouterr().err.count("\n") == 1
    assert mod.main([str(tmp_path / "missing.npz")]) == 2
    assert capsys.readouterr().err.count("\n") == 1
