"""benchmarks/peers.py's command line, and its rl-pool side with a real launch, without sb3-contrib or torch
(the ``peers`` extra is not installed here)."""

import importlib.util
import os
import subprocess
import sys

import pytest

from rl_pool.commands.presets import PRESETS

SCRIPT = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "benchmarks", "peers.py")


@pytest.fixture(scope="module")
def peers():
    spec = importlib.util.spec_from_file_location("peers_benchmark", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_every_preset_is_a_task_on_the_same_env(peers):
    assert set(peers.TASKS) == set(PRESETS)
    for preset, (env_id, hp) in peers.TASKS.items():
        assert PRESETS[preset]["env"] == env_id
        assert hp is peers.ZOO_ARS.get(env_id.split("-")[0], peers.ARS_DEFAULTS)
    # the paper's six tasks have the zoo's settings, the rest sb3-contrib's defaults
    assert sum(hp is peers.ARS_DEFAULTS for _, hp in peers.TASKS.values()) == 5


def test_the_zoo_settings(peers):
    # rl-baselines3-zoo hyperparams/ars.yml, HalfCheetah-v4 and Hopper-v4
    assert peers.ZOO_ARS["HalfCheetah"] == {"n_delta": 32, "n_top": 4, "learning_rate": 0.02, "delta_std": 0.03,
                                            "alive_bonus_offset": 0.0, "normalize": True}
    assert peers.ZOO_ARS["Hopper"]["alive_bonus_offset"] == -1.0
    assert peers.ZOO_ARS["Swimmer"]["normalize"] is False
    assert peers.ZOO_ARS["Humanoid"] == {"n_delta": 256, "n_top": 256, "learning_rate": 0.02, "delta_std": 0.0075,
                                         "alive_bonus_offset": -5.0, "normalize": True}
    # sb3-contrib 2.9.2's ARS.__init__ defaults
    assert peers.ARS_DEFAULTS == {"n_delta": 8, "n_top": None, "learning_rate": 0.02, "delta_std": 0.05,
                                  "alive_bonus_offset": 0.0, "normalize": True}


def test_task_by_preset_or_env_id(peers, monkeypatch):
    monkeypatch.setattr(peers, "have_sb3_contrib", lambda: True)
    a = peers.parse(["--task", "HalfCheetah-v5", "--minutes", "1", "--", "--eval-episodes", "5"])
    assert (a.task, a.env, a.cores, a.episodes, a.order) == ("halfcheetah", "HalfCheetah-v5", 2, 20, ["ars", "rl-pool"])
    assert a.options == ["--eval-episodes", "5"]
    assert peers.parse(["--task", "walker2d"]).env == "Walker2d-v5"
    assert (peers.parse([]).members, peers.parse(["--members", "8"]).members) == (2, 8)  # default: --cores


@pytest.mark.parametrize("argv, line", [
    (["--task", "reachers"], "peers: unknown task 'reachers' (have swimmer (Swimmer-v5), "),
    (["--minutes", "0"], "peers: --minutes must be > 0, got 0.0"),
    (["--cores", "0"], "peers: --cores must be >= 1, got 0"),
    (["--episodes", "-1"], "peers: --episodes must be >= 1, got -1"),
    (["--members", "0"], "peers: --members must be >= 1, got 0"),
    (["--order", "ars,ppo"], "peers: --order takes ars, rl-pool or both"),
    (["--minutes", "soon"], "peers: argument --minutes: invalid float value: 'soon'"),
])
def test_bad_input_is_one_line(peers, monkeypatch, capsys, argv, line):
    monkeypatch.setattr(peers, "have_sb3_contrib", lambda: True)
    assert peers.main(argv) == 2
    out, err = capsys.readouterr()
    assert out == "" and err.startswith(line) and err.count("\n") == 1


def test_missing_sb3_contrib(peers, monkeypatch, capsys):
    monkeypatch.setattr(peers, "have_sb3_contrib", lambda: False)
    assert peers.main(["--task", "swimmer", "--minutes", "1"]) == 2
    assert capsys.readouterr().err == peers.MISSING_SB3 + "\n"
    # rl-pool alone does not need it
    assert peers.parse(["--task", "swimmer", "--order", "rl-pool"]).order == ["rl-pool"]


def test_the_script_loads_neither_torch_nor_sb3_and_refuses_in_one_line():
    probe = ("import importlib.util, sys; s = importlib.util.spec_from_file_location('p', sys.argv[1]); "
             "m = importlib.util.module_from_spec(s); s.loader.exec_module(m); "
             "print(sorted(k for k in ('torch', 'sb3_contrib', 'stable_baselines3', 'jax') if k in sys.modules))")
    res = subprocess.run([sys.executable, "-c", probe, SCRIPT], capture_output=True, text=True, check=True)
    assert res.stdout.strip() == "[]"
    res = subprocess.run([sys.executable, SCRIPT, "--task", "Humanoid-v4"], capture_output=True, text=True)
    assert res.returncode == 2 and res.stdout == ""
    assert res.stderr.startswith("peers: unknown task 'Humanoid-v4'") and res.stderr.count("\n") == 1


@pytest.mark.multiprocess
def test_the_rl_pool_side_takes_the_launchs_pick_at_the_whole_budget(peers, tmp_path):
    """A real launch told the budget: it stops its members in time for its pick, and the last
    checkpoint is that pick (the earlier ones the pool's best.npz of the moment)."""
    import hashlib
    import json

    from .conftest import SHORT

    a = peers.parse(["--task", "swimmer", "--order", "rl-pool", "--minutes", "0.5", "--episodes", "2", "--",
                     *SHORT, "--pick"])
    run = peers.run_rlpool(a, str(tmp_path))
    assert "error" not in run, run.get("error")
    assert "--minutes" in run["command"] and run["seconds"] < 0.5 * 60 + 15
    *early, last = run["checkpoints"]
    assert [c["fraction"] for c in run["checkpoints"]] == [0.25, 0.5, 1.0]
    assert last["picked"] and not any(c["picked"] for c in early)
    picked = json.loads((tmp_path / "rl-pool" / "pool" / "picked.json").read_bytes())["picked"]
    data = (tmp_path / "rl-pool" / last["agent"]).read_bytes()
    assert hashlib.sha256(data).hexdigest() == picked["agent_sha256"] and last["iteration"] == picked["iteration"]
    assert last["agent_seconds"] < 0.5 * 60 + 15  # the pick, made within the budget (slack for a loaded machine)
