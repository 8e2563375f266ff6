"""The real CLI on real Swimmer-v5 (short episodes): pool files, status, bad input."""

import hashlib
import json
import os
import subprocess
import sys

import numpy as np
import pytest

from rl_pool import Agent
from rl_pool.errors import UsageError

from .conftest import ROOT, SHORT, rl_pool


def _tree(root):
    out = {}
    for dp, _, fs in os.walk(root):
        for f in fs:
            p = os.path.join(dp, f)
            out[os.path.relpath(p, root)] = open(p, "rb").read()
    return out


@pytest.fixture(scope="module")
def single_pool(tmp_path_factory):
    d = tmp_path_factory.mktemp("single") / "pool"
    rl_pool("train", "--pool-dir", d, "--pool-size", 1, "--iterations", 3, *SHORT, "--quiet", check=0)
    return d


def test_single_member_run_writes_the_pool_files(single_pool):
    d = single_pool
    for rel in ["pool.json", "best.npz", "iterations/000000/initial.npz", "members/member-000.json",
                "logs/member-000.log"]:
        assert (d / rel).exists(), rel
    for i in (1, 2, 3):
        for name in ["member-000.npz", "member-000.json", "member-000.wait.json", "selected.json"]:
            assert (d / f"iterations/{i:06d}" / name).exists()
    hb = json.loads((d / "members/member-000.json").read_text())
    assert hb["state"] == "finished"
    best = Agent.load(d / "best.npz")
    assert best.meta.env == "Swimmer-v5" and best.meta.max_episode_steps == 60
    best_it = json.loads((d / "best.json").read_text())["iteration"]
    # every training observation of the best agent's line so far (a parent win trains nothing), none
    # from evaluation
    trained = sum(json.loads((d / f"iterations/{i:06d}/selected.json").read_text())["winner"] == "branch"
                  for i in range(1, best_it + 1))
    assert best.norm.count == trained * 4 * 60


def test_status_json_has_the_contract_keys(single_pool):
    st = json.loads(rl_pool("status", single_pool, "--json", check=0).stdout)
    assert st["pool_size"] == 1 and st["env"] == "Swimmer-v5" and st["iterations_completed"] == 3
    assert [h["iteration"] for h in st["history"]] == [1, 2, 3]
    rets = [h["eval_return"] for h in st["history"]]
    assert st["best"]["eval_return"] == max(rets)
    assert st["best"]["iteration"] == 1 + int(np.argmax(rets))
    for h in st["history"]:
        (m,) = h["members"]
        if h["winner"] == "branch":
            assert h["selected_member"] == 0 and m["eval_return"] == h["eval_return"]
        else:  # the parent, re-scored on the same episodes, beat the branch
            assert h["winner"] == "parent" and h["selected_member"] is None
            assert h["eval_return"] > m["eval_return"]
        assert m["learning_rate"] == 0.1 and m["train_steps"] == 4 * 60
        assert m["train_seconds"] > 0 and m["eval_seconds"] > 0 and m["wait_seconds"] >= 0
    table = rl_pool("status", single_pool, check=0).stdout
    assert "best:" in table and "finished" in table


def test_status_csv_history(single_pool, tmp_path):
    import csv

    out = tmp_path / "history.csv"
    rl_pool("status", single_pool, "--csv", out, check=0)
    rows = list(csv.DictReader(out.open()))
    st = json.loads(rl_pool("status", single_pool, "--json", check=0).stdout)
    assert [int(r["iteration"]) for r in rows] == [1, 2, 3]
    assert [float(r["eval_return"]) for r in rows] == [h["eval_return"] for h in st["history"]]
    # training, evaluation and the parent's re-scoring on the same episodes
    assert [int(r["env_steps"]) for r in rows] == [k * (4 * 60 + 2 * 60 + 2 * 60) for k in (1, 2, 3)]
    assert float(rows[-1]["best_so_far"]) == st["best"]["eval_return"]
    assert rows[0]["member0_learning_rate"] == "0.1"


@pytest.mark.parametrize("fmt, when", [([], "before"), (["--json"], "before"),
                                       (["--watch", "--interval", "0.1"], "before"),
                                       (["--watch", "--interval", "0.1"], "after the first line")])
def test_status_into_a_closed_pipe_exits_quietly(single_pool, fmt, when):
    """`rl-pool status DIR | head` where the reader has gone: no traceback, no error line; a
    watcher ends instead of following the pool for nobody, also when it has nothing new to write
    (the pool here is finished). Python's own buffering is left on, as in a user's shell."""
    import subprocess
    import sys

    from .conftest import ROOT

    env = {k: v for k, v in os.environ.items() if k != "PYTHONUNBUFFERED"}
    r, w = os.pipe()
    if when == "before":
        os.close(r)  # the reader is gone before the command writes a byte
    proc = subprocess.Popen([sys.executable, "-m", "rl_pool", "status", str(single_pool), *fmt],
                            stdout=w, stderr=subprocess.PIPE, text=True, cwd=ROOT, env=env)
    os.close(w)
    if when != "before":
        with os.fdopen(r, "rb") as reader:
            assert reader.readline()  # `| head -1`: one line, then the reader leaves
    _, err = proc.communicate(timeout=30)
    assert err == "" and proc.returncode == 0


def test_rerun_on_finished_pool_changes_nothing_and_larger_target_continues(tmp_path):
    d = tmp_path / "p"
    rl_pool("train", "--pool-dir", d, "--iterations", 2, *SHORT, "--quiet", check=0)
    data = {k: v for k, v in _tree(d).items() if not k.startswith(("logs", "members"))}
    rl_pool("train", "--pool-dir", d, "--iterations", 2, "--quiet", check=0)
    rl_pool("train", "--pool-dir", d, "--iterations", 1, "--quiet", check=0)
    assert {k: v for k, v in _tree(d).items() if not k.startswith(("logs", "members"))} == data
    assert "nothing to do" in (d / "logs/member-000.log").read_text()
    rl_pool("train", "--pool-dir", d, "--iterations", 3, "--quiet", check=0)
    st = json.loads(rl_pool("status", d, "--json", check=0).stdout)
    assert st["iterations_completed"] == 3
    assert json.loads((d / "iterations/000003/member-000.json").read_text())["parent"]["iteration"] == 2


def test_status_before_any_iteration_has_null_best(tmp_path):
    d = tmp_path / "p"
    # A pool whose only member has not finished an iteration: create it and stop at once.
    rl_pool("train", "--pool-dir", d, "--pool-size", 2, "--member", 0, "--iterations", 1, *SHORT,
            "--barrier-timeout", 0.5, "--quiet", check=3)
    st = json.loads(rl_pool("status", d, "--json", check=0).stdout)
    assert st["best"] is None and st["iterations_completed"] == 0 and st["history"] == []


BAD = [
    (["--env", "NoSuchEnv-v0"], "NoSuchEnv-v0"),
    (["--env", "CartPole-v1"], "action space"),
    (["--pool-size", 2, "--member", 5], "--member must be in 0..1"),
    (["--train-episodes", 0], "--train-episodes must be a positive"),
    (["--eval-episodes", -1], "--eval-episodes must be a positive"),
    (["--train-episodes", 5, "--batch-episodes", 2], "multiple of"),
    (["--gamma", 1.5], "--gamma"),
    (["--gae-lambda", -0.1], "--gae-lambda must be in [0, 1]"),
    (["--env-kwargs", "[1, 2]"], "JSON object"),
    (["--train-env-kwargs", "3"], "JSON object"),
    (["--train-env-kwargs", '{"no_such_option": 1}'], "cannot make environment"),
    (["--train-env-kwargs", '{"max_episode_steps": 7}'], "training and evaluation must share them"),
    (["--learning-rate", "fast"], "invalid float"),
    (["--policy", "mlp", "--hidden", "64x64"], "hidden sizes must be comma-separated integers"),
    (["--policy", "mlp", "--hidden", "0,8"], "hidden sizes must be 1 to 8 layers"),
]


@pytest.mark.parametrize("args, says", BAD)
def test_bad_train_arguments_one_line_exit_2_nothing_created(tmp_path, args, says):
    d = tmp_path / "p"
    proc = rl_pool("train", "--pool-dir", d, *SHORT, *args)
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and says in lines[0], proc.stderr
    assert "Traceback" not in proc.stderr
    assert not d.exists()


def test_existing_pool_with_other_settings_is_refused_untouched(single_pool):
    before = _tree(single_pool)
    for args, says in [(["--pool-size", 3], "--pool-size 1"), (["--env", "Hopper-v5"], "--env Swimmer-v5"),
                       (["--gamma", 0.9], "--gamma 1.0")]:
        proc = rl_pool("train", "--pool-dir", single_pool, *args, "--iterations", 5)
        assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1, proc.stderr
        assert says in proc.stderr
    assert _tree(single_pool) == before


@pytest.mark.parametrize("setup, says", [
    (lambda d: None, "no pool directory"),
    (lambda d: (d.mkdir(), (d / "x.txt").write_text("hi")), "not an rl-pool pool"),
    (lambda d: (d.mkdir(), (d / "pool.json").write_text("[1, 2")), "not a valid rl-pool pool config"),
])
def test_status_on_missing_or_foreign_directory(tmp_path, setup, says):
    d = tmp_path / "d"
    setup(d)
    for args in (["status", d], ["status", d, "--json"], ["plot", d]):
        proc = rl_pool(*args)
        assert proc.returncode == 2 and "Traceback" not in proc.stderr
        assert len(proc.stderr.strip().splitlines()) == 1 and says in proc.stderr


def test_train_refuses_foreign_directory_untouched(tmp_path):
    d = tmp_path / "d"
    d.mkdir()
    (d / "results.csv").write_text("precious")
    proc = rl_pool("train", "--pool-dir", d, *SHORT)
    assert proc.returncode == 2 and "not an rl-pool pool" in proc.stderr
    assert os.listdir(d) == ["results.csv"]


def test_walker2d_preset_terminating_task_short_run(tmp_path):
    """A terminating task through its preset with the survival bonus shifted off: episodes end
    early, the shift shapes training only."""
    d = tmp_path / "walker2d"
    rl_pool("train", "--pool-dir", d, "--preset", "walker2d", "--reward-shift", 1, "--member", 0, "--pool-size", 1,
            "--iterations", 3, "--max-episode-steps", 80, "--train-episodes", 4, "--eval-episodes", 2,
            "--quiet", check=0)
    cfg = json.loads((d / "pool.json").read_text())
    assert (cfg["env"], cfg["reward_shift"], cfg["selection"]) == ("Walker2d-v5", 1.0, "branches")
    assert cfg["batch_episodes"] == 4  # min(10, --train-episodes): no --batch-episodes needed
    for i in (1, 2, 3):
        dep = json.loads((d / f"iterations/{i:06d}/member-000.json").read_text())
        lengths = dep["eval_lengths"]
        assert all(1 <= n <= 80 for n in lengths) and dep["train_steps"] <= 4 * 80
        # eval_return is the env's own return; eval_score takes the shift off every step
        assert dep["eval_score"] == pytest.approx(dep["eval_return"] - np.mean(lengths))
        sel = json.loads((d / f"iterations/{i:06d}/selected.json").read_text())
        assert sel["winner"] == "branch" and sel["score"] == dep["eval_score"]
    assert Agent.load(d / "best.npz").meta.env == "Walker2d-v5"


def test_halfcheetah_mlp_non_terminating_task_short_run(tmp_path):
    d = tmp_path / "cheetah"
    rl_pool("train", "--pool-dir", d, "--env", "HalfCheetah-v5", "--policy", "mlp", "--hidden", "16,8",
            "--iterations", 2, "--max-episode-steps", 40, "--train-episodes", 2, "--eval-episodes", 2,
            "--quiet", check=0)
    for i in (1, 2):
        dep = json.loads((d / f"iterations/{i:06d}/member-000.json").read_text())
        assert dep["eval_lengths"] == [40, 40] and dep["train_steps"] == 2 * 40  # never terminates early
    agent = Agent.load(d / "best.npz")
    assert agent.spec.kind == "mlp" and agent.spec.hidden == (16, 8)
    assert {k: v.shape for k, v in agent.params.items()} == {
        "w0": (17, 16), "b0": (16,), "w1": (16, 8), "b1": (8,), "w2": (8, 12), "b2": (12,)}
    st = json.loads(rl_pool("status", d, "--json", check=0).stdout)
    assert st["config"]["policy"] == "mlp" and st["iterations_completed"] == 2


def test_training_picks_no_gl_backend(tmp_path):
    """Training never renders, so the CLI leaves MUJOCO_GL alone: forcing EGL made every member
    fail at import on a machine without libEGL. Only ``replay`` chooses a backend."""
    code = ("import os, sys\n"
            "from rl_pool.commands.cli import main\n"
            "code = main(sys.argv[1:])\n"
            "print('MUJOCO_GL', os.environ.get('MUJOCO_GL'), 'EGL', 'OpenGL.EGL' in sys.modules)\n"
            "sys.exit(code)\n")
    env = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "PYOPENGL_PLATFORM")}
    proc = subprocess.run([sys.executable, "-c", code, "train", "--pool-dir", str(tmp_path / "p"),
                           "--pool-size", "1", "--iterations", "1", *SHORT, "--quiet"],
                          capture_output=True, text=True, timeout=180, env=env, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr
    assert "MUJOCO_GL None EGL False" in proc.stdout


def test_merge_momentum_without_the_momentum_merge_is_refused(tmp_path):
    """A preset's 2-member pool keeps the default --merge, so a momentum for it means nothing."""
    for args in (["--preset", "halfcheetah", "--pool-size", 2], ["--merge", "adaptive", "--pool-size", 4]):
        proc = rl_pool("launch", "--pool-dir", tmp_path / "p", *args, "--merge-momentum", 0.7, "--iterations", 1)
        assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1, proc.stderr
        assert "--merge-momentum needs --merge momentum" in proc.stderr
        assert not (tmp_path / "p").exists()


def test_a_pool_made_before_its_preset_changed_is_refused_with_how_to_resume_it(tmp_path):
    """What a preset fills in and the pool has otherwise (here: an 8-member halfcheetah pool made
    before the preset's patience) is refused in one line naming the preset and the setting to give."""
    d = tmp_path / "p"
    made = ["--preset", "halfcheetah", "--pool-size", 3, *SHORT, "--iterations", 1, "--quiet"]
    rl_pool("train", "--pool-dir", d, *made, "--member", 0, "--parent-patience", 0, "--revert-after", 0,
            "--barrier-timeout", 0.5, check=3)
    before = _tree(d)
    for command in (["train", "--member", 1], ["launch"]):
        proc = rl_pool(*command, "--pool-dir", d, *made)
        assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1, proc.stderr
        assert ("was made with --parent-patience 0, and --preset halfcheetah sets 3" in proc.stderr
                and "give --parent-patience 0 to resume it" in proc.stderr), proc.stderr
    assert _tree(d) == before


def test_a_merge_without_its_members_is_described_as_a_merge():
    from rl_pool.commands import status

    assert status.describe({"winner": "merge", "merge": {"members": [3, 1]}}) == "a merge of members 3, 1"
    assert status.describe({"winner": "merge", "member": None}) == "a merge"  # best.json's record


def test_training_env_kwargs_change_the_training_episodes_only(tmp_path):
    """--train-env-kwargs: training runs the changed task, evaluation the task itself. Two one-member
    pools, one with a control cost 10^6 times Swimmer's: the same first training actions score far
    lower in it, while the initial agent (the parent both pools re-score on iteration 1's shared
    episodes) scores the same in both, and the pool records the option."""
    deps = {}
    for name, extra in (("plain", []), ("costly", ["--train-env-kwargs", '{"ctrl_cost_weight": 100.0}'])):
        d = tmp_path / name
        rl_pool("train", "--pool-dir", d, "--iterations", 1, "--max-episode-steps", 40, "--train-episodes", 2,
                "--eval-episodes", 2, "--quiet", *extra, check=0)
        deps[name] = json.loads((d / "iterations/000001/member-000.json").read_text())
    assert json.loads((tmp_path / "costly/pool.json").read_text())["train_env_kwargs"] == {"ctrl_cost_weight": 100.0}
    assert deps["costly"]["parent_eval_returns"] == deps["plain"]["parent_eval_returns"]
    assert deps["costly"]["train_return_mean"] < deps["plain"]["train_return_mean"] - 1.0
    assert Agent.load(tmp_path / "costly/best.npz").meta.env_kwargs == {}  # the agent is for the task itself


def test_a_pool_started_from_another_pools_agent_keeps_its_numbers_with_fresh_moments(single_pool, tmp_path):
    """--init-agent POOL: iteration 0 is that pool's best agent (weights and observation statistics),
    with Adam's moments and step count reset; the pool resumes without the option."""
    from rl_pool.protocol import deposits, layout

    d = tmp_path / "fine-tune"
    args = ["--pool-dir", d, "--member", 0, "--pool-size", 1, *SHORT, "--quiet"]
    rl_pool("train", *args, "--iterations", 1, "--init-agent", single_pool, check=0)
    start = deposits.load_selected_agent(layout.Paths(str(d)), 0)
    best = Agent.load(single_pool / "best.npz")
    assert best.opt_t > 0 and start.opt_t == 0.0
    assert start.meta == best.meta and start.params.keys() == best.params.keys()
    for k in best.params:
        np.testing.assert_array_equal(start.params[k], best.params[k])
        assert not start.opt_m[k].any() and not start.opt_v[k].any()
    for a, b in zip(start.norm, best.norm, strict=True):
        np.testing.assert_array_equal(a, b)
    saved = json.loads((d / "pool.json").read_text())
    assert saved["init_agent"] == str(single_pool)
    assert saved["init_agent_sha256"] == hashlib.sha256((single_pool / "best.npz").read_bytes()).hexdigest()
    rl_pool("train", *args, "--iterations", 2, check=0)  # resumed: the option is the pool's
    assert json.loads(rl_pool("status", d, "--json", check=0).stdout)["iterations_completed"] == 2


def test_a_starting_agent_is_pinned_by_its_hash_and_its_path_may_be_relative(single_pool, tmp_path):
    """The pool records the absolute path and the sha256 of --init-agent's file: a resume may name it
    relative to where it runs, and a member that would build iteration 0 from a file that changed
    since (a racing start on another host, a pool still writing its best) is refused."""
    from rl_pool.commands.member import make_initial
    from rl_pool.config import PoolConfig
    from rl_pool.protocol import layout, pool

    (tmp_path / "agent.npz").write_bytes((single_pool / "best.npz").read_bytes())
    d = tmp_path / "pool"
    args = ["--pool-dir", d, "--member", 0, "--pool-size", 1, *SHORT, "--quiet", "--init-agent", "agent.npz"]
    rl_pool("train", *args, "--iterations", 1, check=0, cwd=tmp_path)
    rl_pool("train", *args, "--iterations", 2, check=0, cwd=tmp_path)  # the same relative name: resumed
    cfg = pool.read_config(layout.Paths(str(d)))
    assert cfg.init_agent == str(tmp_path / "agent.npz")
    agent, again = make_initial(cfg)  # what a late member builds: the same bytes
    assert agent.to_bytes() == (d / "iterations" / "000000" / "initial.npz").read_bytes() and again == cfg
    (tmp_path / "agent.npz").write_bytes((single_pool / "iterations" / "000000" / "initial.npz").read_bytes())
    with pytest.raises(UsageError, match=r"is not the agent this pool was made from .* it changed since"):
        make_initial(cfg)
    elsewhere = rl_pool("train", *args[:-1], str(single_pool), "--iterations", 3, check=2, cwd=tmp_path)
    assert "was made with --init-agent" in elsewhere.stderr and elsewhere.stderr.count("\n") == 1
    plain = rl_pool("train", "--pool-dir", single_pool, "--pool-size", 1, "--iterations", 3, *SHORT,
                    "--init-agent", "agent.npz", check=2, cwd=tmp_path)
    assert "was made without --init-agent" in plain.stderr and plain.stderr.count("\n") == 1
    assert PoolConfig().init_agent_sha256 == ""


@pytest.mark.parametrize("what, says", [
    ("mlp", "is an agent for Swimmer-v5 {}, 60 steps, 8 observations, 2 actions, linear (exp link); this pool "
            "trains Swimmer-v5 {}, 60 steps, 8 observations, 2 actions, mlp 64,64 (exp link)"),
    ("fifo", "a FIFO, not a regular file"),
    ("missing", "no agent file or pool directory at"),
    ("garbage", "garbage.npz: not an rl-pool agent file"),
])
def test_a_starting_agent_that_does_not_fit_is_refused_in_one_line_and_nothing_is_made(single_pool, tmp_path,
                                                                                       what, says):
    source = {"mlp": single_pool / "best.npz", "fifo": tmp_path / "fifo.npz", "missing": tmp_path / "none.npz",
              "garbage": tmp_path / "garbage.npz"}[what]
    if what == "fifo":
        os.mkfifo(source)
    if what == "garbage":
        source.write_bytes(b"not an agent")
    extra = ["--policy", "mlp"] if what == "mlp" else []
    d = tmp_path / "pool"
    proc = rl_pool("train", "--pool-dir", d, "--member", 0, "--pool-size", 1, "--iterations", 1, *SHORT, *extra,
                   "--init-agent", source, "--quiet", check=2, timeout=60)
    assert proc.stderr.count("\n") == 1 and says in proc.stderr and "Traceback" not in proc.stderr
    assert not d.exists()
