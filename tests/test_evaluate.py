"""Parallel evaluation under spawn, custom workers, replay."""

import json

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
