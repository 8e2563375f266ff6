"""The bring-your-own-robot example (examples/own_robot/): its package registers PlanarArm-v0, a
pool of real members trains it through `rl-pool launch --env planar_arm:PlanarArm-v0`, the
modified Swimmer model loads through Swimmer-v5's xml_file, and a module that cannot be imported
is refused in one line."""

import json
import math
import os

import numpy as np
import pytest

from .conftest import ROOT, rl_pool

EXAMPLE = os.path.join(ROOT, "examples", "own_robot")
ENV = "planar_arm:PlanarArm-v0"


def _environ(*paths):
    """This process's environment with ``paths`` in front of PYTHONPATH."""
    old = os.environ.get("PYTHONPATH")
    return {**os.environ, "PYTHONPATH": os.pathsep.join([*map(str, paths), *([old] if old else [])])}


@pytest.fixture
def planar_arm(monkeypatch):
    monkeypatch.syspath_prepend(EXAMPLE)
    import planar_arm

    return planar_arm


def test_the_package_registers_a_bounded_env_with_an_episode_limit(planar_arm):
    import gymnasium

    assert gymnasium.spec("PlanarArm-v0").max_episode_steps == 100
    env = gymnasium.make(ENV).unwrapped
    assert env.observation_space.shape == (13,)
    assert np.all(env.action_space.low == -1.0) and np.all(env.action_space.high == 1.0)
    obs, _ = env.reset(seed=5)
    assert obs.shape == (13,) and np.all(np.isfinite(obs))
    action = np.array([0.5, -0.25, 1.0])
    obs, reward, terminated, truncated, step_info = env.step(action)
    tip = env.data.site_xpos[env.model.site("fingertip").id][:2]
    target = env.data.site_xpos[env.model.site("target").id][:2]
    assert np.allclose(obs[-2:], tip - target) and np.allclose(obs[-4:-2], target)
    assert math.isclose(step_info["distance"], float(np.linalg.norm(tip - target)))
    assert math.isclose(reward, -step_info["distance"] - 0.01 * float(action @ action))
    assert not terminated and not truncated
    # the target moves with the reset seed, and the same seed gives the same episode
    first, _ = env.reset(seed=1)
    again, _ = env.reset(seed=1)
    other, _ = env.reset(seed=2)
    assert np.array_equal(first, again) and not np.allclose(first[9:11], other[9:11])


def test_the_longer_swimmer_loads_through_xml_file():
    import gymnasium

    stock = gymnasium.make("Swimmer-v5")
    longer = gymnasium.make("Swimmer-v5", xml_file=os.path.join(EXAMPLE, "swimmer4.xml"))
    assert (stock.observation_space.shape, stock.action_space.shape) == ((8,), (2,))
    assert (longer.observation_space.shape, longer.action_space.shape) == ((10,), (3,))
    assert longer.spec.max_episode_steps == 1000


@pytest.mark.multiprocess
def test_launch_trains_the_example_with_real_members(tmp_path):
    d = tmp_path / "pool"
    # the committed result's settings, with short episodes and few of them
    rl_pool("launch", "--pool-dir", d, "--env", ENV, "--policy", "mlp", "--hidden", "32,32",
            "--init-shape", 20, "--baseline", "linear", "--learning-rates", "0.001,0.003",
            "--max-episode-steps", 30, "--train-episodes", 4, "--batch-episodes", 2,
            "--eval-episodes", 2, "--iterations", 3, "--quiet",
            env=_environ(EXAMPLE), check=0)
    cfg = json.loads((d / "pool.json").read_text())
    assert cfg["env"] == ENV and cfg["pool_size"] == 2 and cfg["max_episode_steps"] == 30
    for i in (1, 2, 3):
        sel = json.loads((d / f"iterations/{i:06d}/selected.json").read_text())
        assert math.isfinite(sel["eval_return"])
        for m in (0, 1):
            dep = json.loads((d / f"iterations/{i:06d}/member-{m:03d}.json").read_text())
            assert len(dep["eval_returns"]) == 2 and all(math.isfinite(r) for r in dep["eval_returns"])
            # a return is minus a distance (at most 0.6 m: twice the reach) minus a small cost, per step
            assert all(-30 * 0.7 < r < 0 for r in dep["eval_returns"])
    status = json.loads(rl_pool("status", d, "--json", check=0).stdout)
    assert status["iterations_completed"] == 3 and math.isfinite(status["best"]["eval_return"])


@pytest.mark.parametrize("module", ["no_such_robot_pkg", "needs_a_missing_dependency"])
def test_a_module_that_cannot_be_imported_is_refused_in_one_line(tmp_path, module):
    (tmp_path / "needs_a_missing_dependency.py").write_text("import no_such_dependency_for_a_robot\n")
    proc = rl_pool("launch", "--pool-dir", tmp_path / "pool", "--env", f"{module}:Robot-v0",
                   "--iterations", 1, env=_environ(tmp_path))
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert lines[0].startswith("rl-pool: error:") and module in lines[0] and "No module named" in lines[0]


@pytest.mark.parametrize("source,why", [
    ("def broken(:\n", "SyntaxError"),
    ("import gymnasium\ngymnasium.register(id='Robot-v0', entry_point=__name__ + ':Robot')\n"
     "class Robot:\n    def __init__(self, **kw):\n        raise KeyError('no such joint')\n", "KeyError"),
])
def test_a_module_or_environment_that_raises_is_refused_in_one_line(tmp_path, source, why):
    (tmp_path / "raising_robot.py").write_text(source)
    proc = rl_pool("launch", "--pool-dir", tmp_path / "pool", "--env", "raising_robot:Robot-v0",
                   "--iterations", 1, env=_environ(tmp_path))
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert lines[0].startswith("rl-pool: error:") and why in lines[0]
    assert not (tmp_path / "pool").exists()  # nothing written for a pool that cannot start
