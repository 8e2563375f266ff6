"""ARS and rl-pool side by side: one MuJoCo task, the same wall-clock budget, the same cores.

    python benchmarks/peers.py --task halfcheetah --minutes 20 --cores 2 --out peers.jsonl
    python benchmarks/peers.py --task swimmer --minutes 1 --episodes 3      # a smoke run

Needs the ``peers`` extra (sb3-contrib, which brings torch) in its own venv, never the project's
``.venv``::

    python3 -m venv .venv-peers && .venv-peers/bin/pip install torch==2.13.0   # a CPU build
    .venv-peers/bin/pip install -c constraints.txt -e '.[peers]'
    .venv-peers/bin/python benchmarks/peers.py --task halfcheetah --minutes 20

The peer is sb3-contrib's ARS (Mania et al. 2018, augmented random search) with a linear policy
and the settings rl-baselines3-zoo keeps "closest to the original paper" for the MuJoCo tasks:
``hyperparams/ars.yml`` of github.com/DLR-RM/rl-baselines3-zoo (commit 22e3ff2, 2026-04-23), its
``Swimmer-v4``, ``Hopper-v4``, ``HalfCheetah-v4``, ``Walker2d-v4``, ``Ant-v4`` and ``Humanoid-v4``
entries (``-v3`` in older versions of the file; there are no v5 entries, so the v5 task takes
its v4 entry). Those entries set n_delta, n_top, learning_rate, delta_std, alive_bonus_offset
and ``normalize: "dict(norm_obs=True, norm_reward=False)"`` (all but Swimmer), and leave
``zero_policy`` at its default (True). Neither the zoo nor the paper has settings for
HumanoidStandup, InvertedPendulum, InvertedDoublePendulum, Reacher and Pusher: there ARS runs
with sb3-contrib's defaults and observation normalisation (:data:`ARS_DEFAULTS`). Candidates are evaluated by sb3-contrib's ``AsyncEval``
in ``--cores`` processes, one torch thread each, one episode per candidate. The observation
filter is a ``VecNormalize`` wrapper whose statistics AsyncEval merges from its workers; a
checkpoint saves them beside the model (``model.save`` and ``VecNormalize.save``).

rl-pool runs as ``rl-pool launch --preset TASK --pool-size CORES --minutes BUDGET`` (``--members
N``: N members sharing the cores; options after ``--`` are added): the launch stops its members at
the end of the budget, and a preset that ends with a pick (``--pick``) stops them early enough for
the pick to fit in the budget. A launch still running a minute after the budget gets SIGINT.

The sides run one after the other (``--order``), each with every core. Each clock starts when
its side's process is started (imports, JIT and environment set-up count). At 1/4, 1/2 and
the whole budget each side's agent is kept: the agent the side had at that time (ARS: its
policy after the last update finished by then; rl-pool: the pool's ``best.npz`` as last read
by then, polled every ``--poll`` seconds, and at the whole budget the launch's pick where it made
one). After both runs every checkpoint is re-scored on
the same ``--episodes`` fresh episodes (reset seeds ``--eval-seed`` + k, which neither side
trains on): rl-pool's with ``rl-pool evaluate``, ARS's with a loop of deterministic actions on
observations normalised with the checkpoint's statistics. Env steps are every step the side
had simulated by the last update or iteration finished before the mark.
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import importlib.util
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time

#: rl-baselines3-zoo hyperparams/ars.yml (commit 22e3ff2), the ``<Task>-v4`` entries; policy
#: 'LinearPolicy' and n_envs 1 in every one, zero_policy not set (sb3-contrib's default: True).
#: ``normalize``: the entry's ``dict(norm_obs=True, norm_reward=False)`` (commented out for Swimmer).
ZOO_ARS: dict[str, dict] = {
    "Swimmer": {"n_delta": 1, "n_top": 1, "learning_rate": 0.02, "delta_std": 0.01,
                "alive_bonus_offset": 0.0, "normalize": False},
    "Hopper": {"n_delta": 8, "n_top": 4, "learning_rate": 0.01, "delta_std": 0.025,
               "alive_bonus_offset": -1.0, "normalize": True},
    "HalfCheetah": {"n_delta": 32, "n_top": 4, "learning_rate": 0.02, "delta_std": 0.03,
                    "alive_bonus_offset": 0.0, "normalize": True},
    "Walker2d": {"n_delta": 40, "n_top": 30, "learning_rate": 0.03, "delta_std": 0.025,
                 "alive_bonus_offset": -1.0, "normalize": True},
    "Ant": {"n_delta": 60, "n_top": 20, "learning_rate": 0.015, "delta_std": 0.025,
            "alive_bonus_offset": -1.0, "normalize": True},
    "Humanoid": {"n_delta": 256, "n_top": 256, "learning_rate": 0.02, "delta_std": 0.0075,
                 "alive_bonus_offset": -5.0, "normalize": True},
}

#: For the tasks the zoo (and the ARS paper) has no settings for: sb3-contrib's own ARS defaults
#: (n_delta 8, every direction kept, step 0.02, noise 0.05, no survival offset), which is what a
#: user gets from ``ARS("LinearPolicy", env)``, with the observation normalisation every zoo
#: MuJoCo entry but Swimmer's turns on.
ARS_DEFAULTS: dict = {"n_delta": 8, "n_top": None, "learning_rate": 0.02, "delta_std": 0.05,
                      "alive_bonus_offset": 0.0, "normalize": True}

#: The tasks both sides have settings for: rl-pool preset -> (env id, ARS settings).
TASKS: dict[str, tuple[str, dict]] = {
    "swimmer": ("Swimmer-v5", ZOO_ARS["Swimmer"]),
    "hopper": ("Hopper-v5", ZOO_ARS["Hopper"]),
    "halfcheetah": ("HalfCheetah-v5", ZOO_ARS["HalfCheetah"]),
    "walker2d": ("Walker2d-v5", ZOO_ARS["Walker2d"]),
    "ant": ("Ant-v5", ZOO_ARS["Ant"]),
    "humanoid": ("Humanoid-v5", ZOO_ARS["Humanoid"]),
    "humanoid-standup": ("HumanoidStandup-v5", ARS_DEFAULTS),
    "inverted-pendulum": ("InvertedPendulum-v5", ARS_DEFAULTS),
    "inverted-double-pendulum": ("InvertedDoublePendulum-v5", ARS_DEFAULTS),
    "reacher": ("Reacher-v5", ARS_DEFAULTS),
    "pusher": ("Pusher-v5", ARS_DEFAULTS),
}

FRACTIONS = (0.25, 0.5, 1.0)
LABELS = {0.25: "1/4", 0.5: "1/2", 1.0: "1"}
SIDES = ("ars", "rl-pool")
MISSING_SB3 = ("peers: sb3-contrib is not installed; pip install -e '.[peers]' in a separate venv "
               "(docs/results.md: ARS side by side)")


class Refused(Exception):
    """Bad input: one line on stderr, exit code 2."""


class _Parser(argparse.ArgumentParser):
    def error(self, message):
        raise Refused(message)


def find_task(name: str) -> str:
    """The preset name for ``name``, a preset (``halfcheetah``) or its env id (``HalfCheetah-v5``)."""
    for preset, (env_id, _) in TASKS.items():
        if name.lower() in (preset, env_id.lower()):
            return preset
    have = ", ".join(f"{p} ({e})" for p, (e, _) in TASKS.items())
    raise Refused(f"unknown task {name!r} (have {have})")


def have_sb3_contrib() -> bool:
    return importlib.util.find_spec("sb3_contrib") is not None


def parse(argv=None) -> argparse.Namespace:
    p = _Parser(prog="peers.py", description=__doc__.splitlines()[0])
    p.add_argument("--task", default="halfcheetah",
                   help=f"an rl-pool preset or its env id: {', '.join(TASKS)} (default halfcheetah)")
    p.add_argument("--minutes", type=float, default=20.0, help="wall-clock budget of each side (default 20)")
    p.add_argument("--cores", type=int, default=2,
                   help="ARS evaluation processes, and rl-pool members unless --members (default 2)")
    p.add_argument("--members", type=int, default=None,
                   help="rl-pool members (default: --cores; more members than cores share them)")
    p.add_argument("--episodes", type=int, default=20, help="fresh episodes per re-score (default 20)")
    p.add_argument("--eval-seed", type=int, default=1_000_000,
                   help="first re-score episode's reset seed; episode k uses seed+k (default 1000000)")
    p.add_argument("--seed", type=int, default=0, help="training seed of both sides (default 0)")
    p.add_argument("--order", default="ars,rl-pool", help="sides to run, in order (default ars,rl-pool)")
    p.add_argument("--poll", type=float, default=0.2, help="seconds between reads of the pool's best.npz")
    p.add_argument("--workdir", default=None, help="where runs and checkpoints go (default: a temporary directory)")
    p.add_argument("--out", default=None, help="also append one JSON line per checkpoint here")
    p.add_argument("options", nargs=argparse.REMAINDER, help="-- then further rl-pool launch options")
    a = p.parse_args(argv)
    a.task = find_task(a.task)
    a.env = TASKS[a.task][0]
    a.order = [s.strip() for s in a.order.split(",") if s.strip()]
    if not a.order or any(s not in SIDES for s in a.order) or len(set(a.order)) != len(a.order):
        raise Refused(f"--order takes ars, rl-pool or both, comma-separated, got {','.join(a.order)!r}")
    if not a.minutes > 0:
        raise Refused(f"--minutes must be > 0, got {a.minutes}")
    for name in ("cores", "episodes"):
        if getattr(a, name) < 1:
            raise Refused(f"--{name} must be >= 1, got {getattr(a, name)}")
    if a.members is None:
        a.members = a.cores
    elif a.members < 1:
        raise Refused(f"--members must be >= 1, got {a.members}")
    if not a.poll > 0:
        raise Refused(f"--poll must be > 0, got {a.poll}")
    a.options = [o for o in a.options if o != "--"]
    if "ars" in a.order and not have_sb3_contrib():
        raise Refused(MISSING_SB3.removeprefix("peers: "))
    return a


def _env_with_one_thread() -> dict:
    env = dict(os.environ)
    for k in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        env[k] = "1"
    return env


def _stop(proc: subprocess.Popen, grace: float = 60.0) -> None:
    """SIGINT to the process group (as Ctrl-C would), then SIGKILL after ``grace`` seconds."""
    if proc.poll() is not None:
        return
    with contextlib.suppress(ProcessLookupError):
        os.killpg(proc.pid, signal.SIGINT)
    try:
        proc.wait(timeout=grace)
    except subprocess.TimeoutExpired:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()


def _tail(path: str, n: int = 400) -> str:
    try:
        with open(path, errors="replace") as fh:
            return fh.read()[-n:].strip()
    except OSError:
        return ""


# ---------------------------------------------------------------------------------------------
# ARS: a child process of this script (``_ars-train``), so that its clock, like rl-pool's,
# starts with the interpreter, and torch never loads in the parent.


def _make_vec(env_id: str, normalize: bool):
    """One environment as sb3 vector env, behind ``VecNormalize`` when the zoo's entry normalises."""
    import gymnasium as gym
    import torch
    from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

    torch.set_num_threads(1)  # also in AsyncEval's workers, which call this
    venv = DummyVecEnv([lambda: gym.make(env_id)])
    if normalize:
        venv = VecNormalize(venv, norm_obs=True, norm_reward=False)
    return venv


def ars_train(env_id: str, hp: dict, workdir: str, seconds: float, cores: int, seed: int, t0: float) -> dict:
    """Train ARS until the first update that ends after ``seconds`` (wall clock from ``t0``, epoch).

    At each mark the policy as it was after the last update finished by then is saved
    (``ck-<pct>.zip``, with ``ck-<pct>.vecnormalize.pkl``); returns what ``run.json`` holds.
    """
    import functools

    import torch
    from sb3_contrib import ARS
    from sb3_contrib.common.vec_env import AsyncEval
    from stable_baselines3.common.callbacks import BaseCallback

    torch.set_num_threads(1)
    os.makedirs(workdir, exist_ok=True)
    marks = [(f, f * seconds) for f in FRACTIONS]
    checkpoints: list[dict] = []

    class BudgetSpent(Exception):
        pass

    class Clock(BaseCallback):
        """Keeps the state after each update; writes the one in force at each mark; stops after the last."""

        def __init__(self):
            super().__init__()
            self.steps = 0
            self.updates = 0
            self.prev = None

        def _snapshot(self) -> dict:
            vn = self.model.get_vec_normalize_env()
            weights = torch.nn.utils.parameters_to_vector(self.model.policy.parameters()).detach().clone()
            return {"weights": weights, "obs_rms": None if vn is None else vn.obs_rms.copy(),
                    "steps": self.steps, "updates": self.updates, "seconds": time.time() - t0}

        def _save(self, snap: dict, fraction: float, mark: float) -> None:
            if snap["seconds"] > mark:  # still setting up at the mark: no agent yet, as for a pool
                checkpoints.append({"fraction": fraction, "mark_seconds": mark, "agent_seconds": None,
                                    "env_steps": 0, "updates": None, "model": None, "vecnormalize": None})
                print(f"ars: {LABELS[fraction]} of the budget ({mark / 60:.2f} min): no agent yet (set-up "
                      f"took {snap['seconds']:.0f} s)", flush=True)
                return
            vn = self.model.get_vec_normalize_env()
            name = f"ck-{round(fraction * 100)}"
            now = torch.nn.utils.parameters_to_vector(self.model.policy.parameters()).detach().clone()
            self.model.policy.load_from_vector(snap["weights"])
            try:
                self.model.save(os.path.join(workdir, name + ".zip"))
            finally:
                self.model.policy.load_from_vector(now)
            stats = None
            if vn is not None:
                live, vn.obs_rms = vn.obs_rms, snap["obs_rms"]
                try:
                    stats = name + ".vecnormalize.pkl"
                    vn.save(os.path.join(workdir, stats))
                finally:
                    vn.obs_rms = live
            checkpoints.append({"fraction": fraction, "mark_seconds": mark, "agent_seconds": snap["seconds"],
                                "env_steps": snap["steps"], "updates": snap["updates"],
                                "model": name + ".zip", "vecnormalize": stats})
            print(f"ars: {LABELS[fraction]} of the budget ({mark / 60:.2f} min): update {snap['updates']}, "
                  f"{snap['steps'] / 1e6:.2f} M env steps", flush=True)

        def _on_training_start(self) -> None:
            self.prev = self._snapshot()

        def _on_rollout_start(self) -> None:  # right after an update (and before the first)
            now = time.time() - t0
            while marks and now > marks[0][1]:
                self._save(self.prev, *marks.pop(0))
            if not marks:
                raise BudgetSpent
            self.prev = self._snapshot()

        def _on_rollout_end(self) -> None:  # the candidates' episodes are in: count their steps
            self.steps += int(sum(ep["l"] for ep in self.model.ep_info_buffer))
            self.updates += 1  # the update that follows

        def _on_step(self) -> bool:
            return True

    env = _make_vec(env_id, hp["normalize"])
    model = ARS("LinearPolicy", env, n_delta=hp["n_delta"], n_top=hp["n_top"], learning_rate=hp["learning_rate"],
                delta_std=hp["delta_std"], alive_bonus_offset=hp["alive_bonus_offset"], zero_policy=True,
                seed=seed, verbose=0, device="cpu")
    async_eval = AsyncEval([functools.partial(_make_vec, env_id, hp["normalize"]) for _ in range(cores)],
                           model.policy)
    async_eval.seed(seed)
    clock = Clock()
    try:
        model.learn(total_timesteps=2**62, callback=clock, log_interval=None, async_eval=async_eval)
    except BudgetSpent:
        pass
    finally:
        async_eval.close()
    return {"side": "ars", "env": env_id, "settings": hp | {"policy": "LinearPolicy", "zero_policy": True},
            "checkpoints": checkpoints, "updates": clock.updates, "env_steps": clock.steps,
            "seconds": time.time() - t0, "cores": cores, "seed": seed}


def ars_score(env_id: str, workdir: str, names: list[tuple[str, str | None]], episodes: int,
              seed: int) -> list[list[float]]:
    """Each saved ARS model's returns on reset seeds ``seed + k``: deterministic actions, observations
    normalised with the checkpoint's frozen statistics (no updates)."""
    import gymnasium as gym
    import torch
    from sb3_contrib import ARS
    from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

    torch.set_num_threads(1)
    out = []
    for model_name, stats_name in names:
        model = ARS.load(os.path.join(workdir, model_name), device="cpu")
        norm = None
        if stats_name:
            norm = VecNormalize.load(os.path.join(workdir, stats_name), DummyVecEnv([lambda: gym.make(env_id)]))
            norm.training = False
        env = gym.make(env_id)
        returns = []
        for k in range(episodes):
            obs, _ = env.reset(seed=seed + k)
            total, done = 0.0, False
            while not done:
                action, _ = model.predict(norm.normalize_obs(obs) if norm is not None else obs, deterministic=True)
                obs, reward, terminated, truncated, _ = env.step(action)
                total += float(reward)
                done = terminated or truncated
            returns.append(total)
        env.close()
        out.append(returns)
    return out


def run_ars(a, workdir: str) -> dict:
    """The ARS side in a child process; its ``run.json`` (``error`` set if it failed)."""
    d = os.path.join(workdir, "ars")
    os.makedirs(d, exist_ok=True)
    with contextlib.suppress(FileNotFoundError):
        os.remove(os.path.join(d, "run.json"))  # an earlier run's
    seconds = a.minutes * 60
    t0 = time.time()
    log = os.path.join(d, "train.log")
    cmd = [sys.executable, os.path.abspath(__file__), "_ars-train", a.env, d, str(seconds), str(a.cores),
           str(a.seed), repr(t0)]
    with open(log, "w") as fh:
        # its lines at each mark (stdout) show as it runs; warnings and errors (stderr) go to the log
        # cwd: MuJoCo appends its warnings to MUJOCO_LOG.TXT in the working directory
        proc = subprocess.Popen(cmd, stdout=sys.stderr, stderr=fh, start_new_session=True, cwd=d,
                                env=_env_with_one_thread())
        # it stops itself after the first update past the budget; this is only a guard
        try:
            proc.wait(timeout=seconds + max(300.0, seconds))
        except subprocess.TimeoutExpired:
            _stop(proc)
        except BaseException:
            _stop(proc)
            raise
    try:
        with open(os.path.join(d, "run.json")) as fh:
            return json.load(fh)
    except (OSError, ValueError):
        return {"side": "ars", "checkpoints": [], "error": f"exit {proc.returncode}: {_tail(log)}"}


# ---------------------------------------------------------------------------------------------
# rl-pool: ``rl-pool launch``; this process reads best.npz while it runs.


def _read_agent(pool_dir: str, stem: str, record: str | None = None) -> tuple[bytes, dict, float] | None:
    """``STEM.npz``'s bytes, ``STEM.json`` (or its ``record`` entry) and when the JSON was written,
    when the two agree (a reader can land between the writes)."""
    try:
        with open(os.path.join(pool_dir, stem + ".npz"), "rb") as fh:
            data = fh.read()
        with open(os.path.join(pool_dir, stem + ".json")) as fh:
            written = os.fstat(fh.fileno()).st_mtime
            doc = json.load(fh)
    except (OSError, ValueError):
        return None
    if record is not None and isinstance(doc, dict):
        doc = doc.get(record)
    if not isinstance(doc, dict) or doc.get("agent_sha256") != hashlib.sha256(data).hexdigest():
        return None
    return data, doc, written


#: Seconds past the budget that a launch gets to stop on its own before it is sent SIGINT.
LAUNCH_GRACE = 60.0


def run_rlpool(a, workdir: str) -> dict:
    """The rl-pool side: launch with the budget, keep best.npz as it was at each mark (at the whole
    budget the launch's pick if it made one), SIGINT if the launch runs on past the budget."""
    d = os.path.join(workdir, "rl-pool")
    pool_dir = os.path.join(d, "pool")
    os.makedirs(d, exist_ok=True)
    seconds = a.minutes * 60
    marks = [(f, f * seconds) for f in FRACTIONS]
    cmd = [sys.executable, "-m", "rl_pool", "launch", "--preset", a.task, "--pool-dir", pool_dir,
           "--pool-size", str(a.members), "--seed", str(a.seed), "--iterations", "100000000",
           "--minutes", repr(a.minutes), "--quiet", *a.options]
    log = os.path.join(d, "launch.log")
    checkpoints, latest, seen, overran = [], None, None, False
    t0 = time.time()
    with open(log, "w") as fh:
        proc = subprocess.Popen(cmd, stdout=fh, stderr=subprocess.STDOUT, start_new_session=True)
        try:
            while True:
                now = time.time() - t0
                exited = proc.poll() is not None
                # The launch stops itself at the budget (a pick within it): when it has ended well, its
                # last agent is the whole budget's. One that ended badly before the budget is an error.
                while marks and (now > marks[0][1] if marks[0][0] < 1.0
                                 else exited and (proc.returncode == 0 or now > seconds)):
                    fraction, mark = marks.pop(0)
                    name = f"ck-{round(fraction * 100)}.npz"
                    picked = _read_agent(pool_dir, "picked", "picked") if fraction == 1.0 else None
                    if picked is not None and picked[2] >= t0:  # this launch's pick, not an old one
                        latest = {"data": picked[0], "doc": picked[1] | {"picked": True},
                                  "seconds": picked[2] - t0}
                    if latest is not None:
                        with open(os.path.join(d, name), "wb") as out:
                            out.write(latest["data"])
                    checkpoints.append({"fraction": fraction, "mark_seconds": mark,
                                        "agent": name if latest else None,
                                        "agent_seconds": latest["seconds"] if latest else None,
                                        "iteration": latest["doc"].get("iteration") if latest else None,
                                        "own_eval_return": latest["doc"].get("eval_return") if latest else None,
                                        "picked": bool(latest and latest["doc"].get("picked"))})
                    what = "the pick" if latest and latest["doc"].get("picked") else "best.npz"
                    print(f"rl-pool: {LABELS[fraction]} of the budget ({mark / 60:.2f} min): "
                          + (f"{what} of iteration {latest['doc'].get('iteration')}" if latest
                             else "no best.npz yet"), file=sys.stderr, flush=True)
                if not marks or exited:
                    break
                if now > seconds + LAUNCH_GRACE:
                    overran = True
                    _stop(proc)  # it was told the budget; this is the fallback
                    continue
                try:
                    st = os.stat(os.path.join(pool_dir, "best.json"))
                    key = (st.st_mtime_ns, st.st_size, st.st_ino)
                except OSError:
                    key = None
                if key is not None and key != seen and now <= seconds:  # none made after the budget counts
                    got = _read_agent(pool_dir, "best")
                    if got is not None:
                        latest, seen = {"data": got[0], "doc": got[1], "seconds": now}, key
                time.sleep(max(0.01, min(a.poll, marks[0][1] - (time.time() - t0) + 0.001)) if marks[0][0] < 1.0
                           else a.poll)
        finally:
            _stop(proc)
    run = {"side": "rl-pool", "env": a.env, "preset": a.task, "command": cmd[1:], "checkpoints": checkpoints,
           "seconds": time.time() - t0, "cores": a.cores, "seed": a.seed}
    if marks:
        run["error"] = f"rl-pool launch exited ({proc.returncode}) before the budget: {_tail(log)}"
    elif proc.returncode != 0 and not overran:
        run["error"] = f"rl-pool launch failed ({proc.returncode}): {_tail(log)}"
    last = checkpoints[-1] if checkpoints else {}
    if overran or (last.get("agent_seconds") or 0) > seconds:
        run["overran"] = True  # the launch, or its pick, ran past the budget (the table says when)
        print(f"rl-pool: the launch ran past the budget ({'stopped by SIGINT' if overran else 'its pick'})",
              file=sys.stderr, flush=True)
    # env steps by each mark: the pool's history, on this host's clock
    try:
        from rl_pool.commands import status

        st = status.status(pool_dir)
        rows, hist = status.curve(st), st["history"]
        for ck in checkpoints:
            done = [c for c, h in zip(rows, hist) if h["time"] is not None and h["time"] - t0 <= ck["mark_seconds"]]
            ck["env_steps"] = done[-1]["env_steps"] if done else 0
            ck["iterations"] = done[-1]["iteration"] if done else 0
    except Exception as e:  # no pool was made
        run.setdefault("error", f"cannot read the pool: {e}")
    return run


def rlpool_score(path: str, episodes: int, seed: int, workers: int) -> list[float]:
    cmd = [sys.executable, "-m", "rl_pool", "evaluate", path, "--episodes", str(episodes), "--seed", str(seed),
           "--workers", str(workers), "--json"]
    res = subprocess.run(cmd, capture_output=True, text=True)
    if res.returncode != 0:
        raise RuntimeError(res.stderr.strip()[-400:])
    return [float(x) for x in json.loads(res.stdout)["returns"]]


# ---------------------------------------------------------------------------------------------


def _stats(returns: list[float]) -> tuple[float, float]:
    """Mean and population standard deviation, as ``rl-pool evaluate`` reports them."""
    m = sum(returns) / len(returns)
    return m, (sum((x - m) ** 2 for x in returns) / len(returns)) ** 0.5


def rescore(a, workdir: str, runs: dict) -> None:
    """Every checkpoint's returns on the same fresh episodes, into ``ck["returns"]``."""
    if "ars" in runs and any(c["model"] for c in runs["ars"]["checkpoints"]):
        d = os.path.join(workdir, "ars")
        cks = runs["ars"]["checkpoints"]
        cks = [c for c in cks if c["model"]]
        spec = json.dumps([[c["model"], c["vecnormalize"]] for c in cks])
        res = subprocess.run([sys.executable, os.path.abspath(__file__), "_ars-score", a.env, d, spec,
                              str(a.episodes), str(a.eval_seed)], capture_output=True, text=True,
                             env=_env_with_one_thread(), cwd=d)
        if res.returncode != 0:
            runs["ars"]["error"] = "re-score failed: " + res.stderr.strip()[-400:]
        else:
            for c, r in zip(cks, json.loads(res.stdout)):
                c["returns"] = r
    if "rl-pool" in runs:
        d = os.path.join(workdir, "rl-pool")
        for c in runs["rl-pool"]["checkpoints"]:
            if c["agent"]:
                try:
                    c["returns"] = rlpool_score(os.path.join(d, c["agent"]), a.episodes, a.eval_seed, a.cores)
                except RuntimeError as e:
                    runs["rl-pool"]["error"] = f"re-score failed: {e}"


def _versions() -> dict:
    from importlib import metadata

    out = {"python": sys.version.split()[0]}
    for dist in ("rl-pool", "sb3-contrib", "stable-baselines3", "torch", "gymnasium", "mujoco", "jax", "numpy"):
        try:
            out[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            out[dist] = None
    return out


def report(a, runs: dict, workdir: str) -> list[dict]:
    rows = []
    for side in a.order:
        run = runs[side]
        for c in run["checkpoints"]:
            mean, std = _stats(c["returns"]) if c.get("returns") else (None, None)
            rows.append({"task": a.env, "preset": a.task, "side": side, "fraction": c["fraction"],
                         "minutes": round(c["mark_seconds"] / 60, 3),
                         "agent_minutes": None if c.get("agent_seconds") is None else round(c["agent_seconds"] / 60, 3),
                         "env_steps": c.get("env_steps"),
                         "agent": (f"update {c['updates']}" if side == "ars" and c.get("model") else
                                   f"iteration {c['iteration']}" + (", picked" if c.get("picked") else "")
                                   if side == "rl-pool" and c.get("agent") else None),
                         "mean_return": mean, "std_return": std, "returns": c.get("returns"),
                         "episodes": a.episodes, "eval_seed": a.eval_seed, "cores": a.cores, "seed": a.seed,
                         "budget_minutes": a.minutes,
                         "settings": run.get("settings") if side == "ars" else {"preset": a.task,
                                                                                "members": a.members,
                                                                                "options": a.options},
                         "workdir": workdir})
    return rows


def _fmt_steps(n) -> str:
    return "-" if n is None else f"{n / 1e6:.2f} M"


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["_ars-train"]:
        env_id, d, seconds, cores, seed, t0 = argv[1:7]
        hp = next(h for e, h in TASKS.values() if e == env_id)
        run = ars_train(env_id, hp, d, float(seconds), int(cores), int(seed), float(t0))
        with open(os.path.join(d, "run.json"), "w") as fh:
            json.dump(run, fh, indent=1)
        return 0
    if argv[:1] == ["_ars-score"]:
        env_id, d, spec, episodes, seed = argv[1:6]
        print(json.dumps(ars_score(env_id, d, json.loads(spec), int(episodes), int(seed))))
        return 0
    try:
        a = parse(argv)
    except Refused as e:
        print(f"peers: {e}", file=sys.stderr)
        return 2
    workdir = os.path.abspath(a.workdir or tempfile.mkdtemp(prefix="rl-pool-peers-"))
    if os.path.isdir(os.path.join(workdir, "rl-pool", "pool")) and "rl-pool" in a.order:
        shutil.rmtree(os.path.join(workdir, "rl-pool", "pool"))  # a launch would resume it, not start anew
    how = "one after the other, " if len(a.order) > 1 else ""
    members = f" (rl-pool: {a.members} members)" if a.members != a.cores else ""
    print(f"# {a.env}: {', '.join(a.order)} {how}{a.minutes:g} min each on {a.cores} cores{members}; "
          f"re-scored on {a.episodes} fresh episodes (reset seeds {a.eval_seed}+k); runs in {workdir}",
          file=sys.stderr, flush=True)
    runs = {}
    for side in a.order:
        runs[side] = (run_ars if side == "ars" else run_rlpool)(a, workdir)
        if runs[side].get("error"):
            print(f"{side}: {runs[side]['error']}", file=sys.stderr, flush=True)
    print("# re-scoring every checkpoint", file=sys.stderr, flush=True)
    rescore(a, workdir, runs)
    rows = report(a, runs, workdir)
    print(f"{'task':<15} {'side':<8} {'minutes':>7} {'env steps':>10}  {'agent, made at min':<30} "
          f"re-scored return ({a.episodes} episodes)")
    for r in rows:
        score = "-" if r["mean_return"] is None else f"{r['mean_return']:.1f} ± {r['std_return']:.1f}"
        agent = "-" if r["agent"] is None else f"{r['agent']}, {r['agent_minutes']:.2f}"
        print(f"{r['task']:<15} {r['side']:<8} {r['minutes']:>7.2f} {_fmt_steps(r['env_steps']):>10}  "
              f"{agent:<30} {score}")
    if a.out:
        versions = _versions()
        with open(a.out, "a") as fh:
            for r in rows:
                fh.write(json.dumps(r | {"versions": versions}) + "\n")
    failed = [s for s in a.order if runs[s].get("error")]
    for s in failed:
        print(f"peers: {s}: {runs[s]['error']}", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
