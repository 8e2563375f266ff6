"""Typed configuration: what a pool shares (``pool.json``) and what each member sets.

Each field's one-line ``help`` is also its command-line help. Options left
unset on the command line take the pool's saved value when the pool exists,
else the default here; options set explicitly must agree with the pool.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import re
from dataclasses import MISSING, asdict, dataclass, field, fields

from rl_pool.errors import UsageError

#: 2: policy family (policy/hidden/link), parent in the selection, reward shift.
PROTOCOL = 3  # 3: create-once decisions in .NAME.once/ (rl_pool.protocol.claim)
#: Pools that read-only commands (status, plot, evaluate, compare) still read: 2 differs from 3 only
#: in how create-once files are made, not in what they hold.
READABLE_PROTOCOLS = (2, 3)


def _sizes(text: str, what: str) -> tuple[int, ...]:
    if not re.fullmatch(r"\d+(,\d+)*", text):
        raise ValueError(f"{what} sizes must be comma-separated integers such as 64,64, got {text!r}")
    return tuple(int(h) for h in text.split(","))


def opt(default, help: str, choices=None, **kw):
    return field(default=default, metadata={"help": help, "choices": choices, **kw})


@dataclass(frozen=True)
class PoolConfig:
    """Settings every member of a pool must share; saved in ``POOL/pool.json``."""

    env: str = opt("Swimmer-v5", "gymnasium environment id (bounded Box actions)")
    env_kwargs: dict = field(default_factory=dict, metadata={
        "help": "JSON object of keyword arguments for gymnasium.make", "choices": None})
    train_env_kwargs: dict = field(default_factory=dict, metadata={
        "help": "JSON object of keyword arguments that training episodes add to --env-kwargs (e.g. a wider "
                "reset_noise_scale); evaluation and selection keep --env-kwargs alone, the task itself",
        "choices": None, "added": True})
    max_episode_steps: int = opt(0, "episode length (0: the environment's own limit)")
    pool_size: int = opt(1, "number of members N")
    train_episodes: int = opt(20, "training episodes per member per iteration")
    batch_episodes: int = opt(0, "episodes per gradient step, stepped in lockstep (0: min(10, --train-episodes))")
    eval_episodes: int = opt(3, "evaluation episodes per member per iteration (no updates)")
    eval_mode: str = opt("mean", "evaluation actions: Beta mean or samples", ("mean", "sample"))
    gamma: float = opt(1.0, "discount factor (Swimmer needs ~1: 0.99 traps it near 40)")
    baseline: str = opt("time", "baseline: leave-one-out time-indexed mean return, a cross-fitted linear "
                                "function of the state (observation, its square, time), a value network "
                                "learned beside the policy (--value-hidden), or none",
                        ("time", "linear", "value", "none"))
    value_hidden: str = opt("64,64", "hidden layer sizes of the value network of --baseline value, "
                                     "comma-separated (tanh units)", added=True)
    value_epochs: int = opt(10, "Adam steps the value network of --baseline value takes on each batch (the "
                                "first beside the policy's step, the rest on the value network alone)",
                            added=True, before=1)
    policy_epochs: int = opt(1, "Adam steps the policy takes on each batch: the REINFORCE step, then K - 1 "
                                "more up PPO's clipped surrogate against the policy that drew the batch "
                                "(1: REINFORCE alone)", added=True)
    clip: float = opt(0.2, "with --policy-epochs above 1: a sampled action adds no more gradient to the extra "
                           "steps once its probability ratio has moved past 1 +- C in the direction its "
                           "advantage favours (PPO's epsilon)", added=True)
    minibatch_steps: int = opt(0, "with --policy-epochs above 1: each extra pass goes through the batch's steps "
                                  "in a fresh random order, S at a time, one Adam step per minibatch (PPO's "
                                  "minibatches; 0: one step on the whole batch per pass)", added=True)
    value_minibatch_steps: int = opt(0, "with --baseline value: the value network's steps after the first go "
                                        "through the batch's steps in passes, S steps at a time in a fresh "
                                        "random order, one Adam step per minibatch (--value-epochs - 1 passes, "
                                        "as PPO fits its critic; 0: one step on the whole batch per epoch)",
                                     added=True)
    gae_lambda: float = opt(1.0, "lambda of generalised advantage estimation, with the baseline as the value "
                                 "function (1: the return-to-go minus the baseline; below 1: less variance, "
                                 "some bias)", added=True)
    optimizer: str = opt("adam", "step-size rule: Adam, or fixed-length normalised gradient", ("adam", "normalized"))
    policy: str = opt("linear", "policy network: linear in the normalised observation, or an MLP",
                      ("linear", "mlp"))
    hidden: str = opt("64,64", "MLP hidden layer sizes, comma-separated (tanh units; --policy mlp only)")
    link: str = opt("exp", "Beta shapes from pre-activations z: exp(z)+1 or softplus(z)+1", ("exp", "softplus"))
    init_shape: float = opt(0.0, "Beta shapes alpha = beta of every action at the start (> 1; larger explores "
                                 "less; 0: link(0) + 1, i.e. 2 with the exp link)", added=True)
    reward_shift: float = opt(0.0, "subtracted from every training reward (e.g. 1 = the survival bonus of "
                                   "Hopper/Walker2d/Ant); evaluation scores the env's own reward")
    selection: str = opt("parent", "who competes for an iteration: the branches and the parent re-scored on "
                                   "the same episodes (the pool never loses ground), or branches only",
                         ("parent", "branches"))
    selection_margin: float = opt(0.0, "with --selection parent: a branch replaces the parent only if its "
                                       "per-episode evaluation scores beat the parent's on the same episodes "
                                       "by K standard errors of the differences (0: any branch at least as "
                                       "good)", added=True)
    parent_patience: int = opt(0, "with --selection parent: after K iterations in a row that the parent (or a "
                                  "merge's fallback) kept, the next one's branches compete without it, as with "
                                  "--selection branches (0: never); --revert-after and the best agent keep "
                                  "what was reached",
                               added=True)
    revert_after: int = opt(0, "go back to the best selected agent after K iterations without a new best "
                               "(0: never)")
    rate_patience: int = opt(0, "after K iterations without a new best, every member's learning rate is "
                                "multiplied by --rate-decay (again after each further K, down to 1/100); a new best divides "
                                "it by --rate-decay, up to the rates given (0: the rates never change)",
                             added=True)
    rate_decay: float = opt(0.5, "with --rate-patience: the factor a plateau multiplies the learning rates by "
                                 "(0 < F < 1)", added=True)
    rate_anneal: int = opt(0, "a linear decay of every member's learning rate: iteration I trains at "
                              "max(1/100, 1 - (I-1)/K) times its rate (0: no decay); K is about the iterations "
                              "the run will make; with --rate-patience the two shares multiply", added=True)
    best_score: str = opt("first", "what ranks the best selected agent (the one --revert-after goes back to): "
                                   "its score in the iteration it was selected, or the mean of that and every "
                                   "later re-score of it as the parent (a lucky first score wears off; with "
                                   "--selection branches a best is re-scored in the iteration after it became "
                                   "the best or was reverted to)", ("first", "mean"), added=True)
    merge: str = opt("adaptive", "how the next agent is made from the branches that beat the parent: the best "
                                 "one alone (none); the parent plus the rank-weighted mean of their updates "
                                 "(mean), or that mean times their number (sum); or, from 3 such branches, "
                                 "times a scale that doubles after a merge that beat the best branch of its "
                                 "iteration and halves after one that did not (adaptive), or plus "
                                 "--merge-momentum times the previous merge's step (momentum); with adaptive "
                                 "and momentum 2 members go on as with none",
                     ("none", "mean", "sum", "adaptive", "momentum"), added=True, before="none")
    merge_momentum: float = opt(0.5, "with --merge momentum: the fraction of the previous merge's step that a "
                                     "merge made right after it takes again (heavy-ball momentum across "
                                     "iterations)", added=True)
    sharpen: float = opt(1.0, "after an iteration the parent (or a merge's fallback) kept, member I of N starts "
                              "from that agent with its Beta shapes' excess over 1 times F^(I/(N-1)): less action "
                              "noise, so the sampled return REINFORCE climbs comes closer to the mean-action score "
                              "selection compares (1: never)", added=True)
    revert_sharpen: float = opt(1.0, "with --revert-after: a revert sends every member back to the best agent "
                                     "with its Beta shapes' excess over 1 times F: less action noise from there "
                                     "on, kept where the branches then find a new best, so it compounds only "
                                     "while it pays (1: never)", added=True)
    init_agent: str = opt("", "start the pool from this agent (an agent file, or a pool directory: its "
                              "current pick, else its best agent) instead of a fresh one: its weights and "
                              "observation statistics, with fresh Adam moments; it must be an agent for the same "
                              "task and policy (--init-shape then does not apply)", added=True)
    #: the sha256 of --init-agent's bytes, recorded when the pool is made: a member that builds
    #: iteration 0 later (a racing start, another host) must read the same agent
    init_agent_sha256: str = opt("", "", added=True, internal=True)
    seed: int = opt(0, "root seed; every random draw derives from (seed, member, iteration)")

    @property
    def spec(self):
        """The policy this pool trains (:class:`rl_pool.maths.policy.PolicySpec`)."""
        from rl_pool.maths.policy import PolicySpec

        hidden = _sizes(self.hidden, "hidden") if self.policy == "mlp" else ()
        value = _sizes(self.value_hidden, "value hidden") if self.baseline == "value" else ()
        return PolicySpec(self.policy, hidden, self.link, value)

    @property
    def updates_per_iteration(self) -> int:
        return self.train_episodes // self.batch_episodes

    @property
    def majority(self) -> int:
        return self.pool_size // 2 + 1

    def validate(self) -> PoolConfig:
        """Check every field; returns the config with derived defaults resolved (``batch_episodes`` 0)."""
        if self.batch_episodes == 0 and self.train_episodes >= 1:
            return dataclasses.replace(self, batch_episodes=min(10, self.train_episodes)).validate()
        for name in ("pool_size", "train_episodes", "batch_episodes", "eval_episodes", "value_epochs",
                     "policy_epochs"):
            if getattr(self, name) < 1:
                raise UsageError(f"--{name.replace('_', '-')} must be a positive integer, got {getattr(self, name)}")
        for name in ("value_epochs", "policy_epochs"):
            if getattr(self, name) > 1000:
                raise UsageError(f"--{name.replace('_', '-')} must be at most 1000, got {getattr(self, name)}")
        for name in ("minibatch_steps", "value_minibatch_steps"):
            if not 0 <= getattr(self, name) <= 10**6:
                raise UsageError(f"--{name.replace('_', '-')} must be in [0, 1000000], got {getattr(self, name)}")
        if not (math.isfinite(self.clip) and 0.0 < self.clip <= 10.0):
            raise UsageError(f"--clip must be in (0, 10], got {self.clip}")
        if self.policy_epochs > 1 and self.optimizer != "adam":
            raise UsageError("--policy-epochs above 1 needs --optimizer adam")
        if self.max_episode_steps < 0:
            raise UsageError(f"--max-episode-steps must be >= 0, got {self.max_episode_steps}")
        if self.train_episodes % self.batch_episodes:
            raise UsageError(
                f"--train-episodes ({self.train_episodes}) must be a multiple of --batch-episodes ({self.batch_episodes})")
        if not (math.isfinite(self.gamma) and 0.0 <= self.gamma <= 1.0):
            raise UsageError(f"--gamma must be in [0, 1], got {self.gamma}")
        if not (math.isfinite(self.gae_lambda) and 0.0 <= self.gae_lambda <= 1.0):
            raise UsageError(f"--gae-lambda must be in [0, 1], got {self.gae_lambda}")
        if self.seed < 0:
            raise UsageError(f"--seed must be >= 0, got {self.seed}")
        for f in fields(self):
            choices = f.metadata.get("choices")
            if choices and getattr(self, f.name) not in choices:
                raise UsageError(f"--{f.name.replace('_', '-')} must be one of {', '.join(choices)}")
        if not isinstance(self.env_kwargs, dict):
            raise UsageError("--env-kwargs must be a JSON object")
        if not isinstance(self.train_env_kwargs, dict):
            raise UsageError("--train-env-kwargs must be a JSON object")
        if not math.isfinite(self.reward_shift):
            raise UsageError(f"--reward-shift must be a finite number, got {self.reward_shift}")
        if self.init_shape:
            from rl_pool.maths.policy import init_bias

            try:
                init_bias(self.link, self.init_shape)
            except ValueError as exc:
                raise UsageError(f"--init-shape: {exc}") from None
        if not (math.isfinite(self.selection_margin) and self.selection_margin >= 0):
            raise UsageError(f"--selection-margin must be a finite number >= 0, got {self.selection_margin}")
        if self.selection_margin and self.selection != "parent":
            raise UsageError("--selection-margin needs --selection parent (it is a margin over the parent)")
        if not (math.isfinite(self.merge_momentum) and 0.0 <= self.merge_momentum < 1.0):
            raise UsageError(f"--merge-momentum must be in [0, 1), got {self.merge_momentum}")
        if not (math.isfinite(self.sharpen) and 1.0 <= self.sharpen <= 1000.0):
            raise UsageError(f"--sharpen must be in [1, 1000], got {self.sharpen}")
        if self.sharpen != 1.0 and self.link != "exp":
            raise UsageError("--sharpen needs --link exp")
        if self.sharpen != 1.0 and self.selection != "parent":
            raise UsageError("--sharpen needs --selection parent (it follows iterations that kept the parent)")
        if not (math.isfinite(self.revert_sharpen) and 1.0 <= self.revert_sharpen <= 1000.0):
            raise UsageError(f"--revert-sharpen must be in [1, 1000], got {self.revert_sharpen}")
        if self.revert_sharpen != 1.0 and self.link != "exp":
            raise UsageError("--revert-sharpen needs --link exp")
        if self.revert_sharpen != 1.0 and not self.revert_after:
            raise UsageError("--revert-sharpen needs --revert-after (it sharpens the agent a revert goes back to)")
        if self.parent_patience < 0:
            raise UsageError(f"--parent-patience must be >= 0, got {self.parent_patience}")
        if self.parent_patience and self.selection != "parent":
            raise UsageError("--parent-patience needs --selection parent (it ends a run of parent wins)")
        if self.revert_after < 0:
            raise UsageError(f"--revert-after must be >= 0, got {self.revert_after}")
        if self.rate_patience < 0:
            raise UsageError(f"--rate-patience must be >= 0, got {self.rate_patience}")
        if self.rate_anneal < 0:
            raise UsageError(f"--rate-anneal must be >= 0, got {self.rate_anneal}")
        if not (math.isfinite(self.rate_decay) and 0.0 < self.rate_decay < 1.0):
            raise UsageError(f"--rate-decay must be in (0, 1), got {self.rate_decay}")
        try:
            self.spec  # noqa: B018 (parses --hidden and checks the policy)
        except ValueError as exc:
            raise UsageError(f"--policy/--hidden/--link/--value-hidden: {exc}") from None
        return self

    def to_json(self) -> dict:
        return {"protocol": PROTOCOL, **asdict(self)}

    @classmethod
    def from_json(cls, d: dict, protocols: tuple = (PROTOCOL,)) -> PoolConfig:
        if not isinstance(d, dict):
            raise ValueError("not a JSON object")
        if d.get("protocol") not in protocols:
            raise OldProtocol(d.get("protocol"))
        names = {f.name for f in fields(cls)}
        # fields added after protocol 3 began take, in pools made before them, the value that
        # behaves as those pools did (``before``), else their default
        added = {f.name: f.metadata["before"] if "before" in f.metadata
                 else f.default if f.default is not MISSING else f.default_factory()
                 for f in fields(cls) if f.metadata.get("added")}
        missing = names - d.keys() - added.keys()
        if missing:
            raise ValueError(f"missing {', '.join(sorted(missing))}")
        return cls(**{k: d.get(k, added.get(k)) for k in names})

    @classmethod
    def merged(cls, requested: dict, saved: PoolConfig | None, where: str = "the pool",
               preset: str | None = None) -> PoolConfig:
        """Combine explicitly requested values with a saved pool config.

        ``requested`` maps field names to values the user set (unset fields are
        absent). Against a saved config every requested value must agree. ``preset``: the
        values were filled in by that ``--preset``, and a refusal says so and how to resume.
        """
        if saved is None:
            base = {f.name: (f.default if f.default is not MISSING else f.default_factory())
                    for f in fields(cls)}
            base.update(requested)
            cfg = cls(**base).validate()
            if "merge_momentum" in requested and cfg.merge != "momentum":
                raise UsageError("--merge-momentum needs --merge momentum")
            if "rate_decay" in requested and not cfg.rate_patience:
                raise UsageError("--rate-decay needs --rate-patience")
            if "clip" in requested and cfg.policy_epochs < 2:
                raise UsageError("--clip needs --policy-epochs above 1")
            if requested.get("minibatch_steps") and cfg.policy_epochs < 2:
                raise UsageError("--minibatch-steps needs --policy-epochs above 1")
            if requested.get("value_minibatch_steps") and (cfg.baseline != "value" or cfg.value_epochs < 2):
                raise UsageError("--value-minibatch-steps needs --baseline value and --value-epochs above 1")
            return cfg
        for name, value in requested.items():
            have = getattr(saved, name)
            if name == "max_episode_steps" and value == 0:
                continue  # 0 means "the env's limit", resolved when the pool was made
            if name == "init_agent" and value:
                value = os.path.abspath(value)  # recorded so when the pool was made
            if _norm(value) != _norm(have):
                flag = "--" + name.replace("_", "-")
                if have == "":
                    raise UsageError(f"{where} was made without {flag}, this run asks for {_show(value)} "
                                     "(drop the option, or use another --pool-dir)")
                if preset:
                    raise UsageError(
                        f"{where} was made with {flag} {_show(have)}, and --preset {preset} sets {_show(value)} "
                        f"for this pool (the preset changed since, or the pool size differs): give {flag} "
                        f"{_show(have)} to resume it, or use another --pool-dir")
                raise UsageError(
                    f"{where} was made with {flag} {_show(have)}, this run asks for {_show(value)} "
                    "(drop the option to use the pool's, or use another --pool-dir)")
        return saved


class OldProtocol(ValueError):
    """A pool made by another version of rl-pool (its ``protocol`` differs)."""

    def __init__(self, protocol):
        self.protocol = protocol
        super().__init__(f"protocol {protocol!r}, this rl-pool speaks {PROTOCOL}")


def _norm(v):
    return json.dumps(v, sort_keys=True)


def _show(v) -> str:
    return json.dumps(v) if isinstance(v, dict) else str(v)


@dataclass(frozen=True)
class MemberConfig:
    """Per-member settings: not in ``pool.json``, free to differ between members."""

    member: int = opt(0, "this member's index I in 0..N-1")
    learning_rate: float = opt(0.1, "this member's step size (recorded in its deposits)")
    iterations: int = opt(100, "the pool's target: stop once iteration K is selected")
    barrier_timeout: float = opt(1800.0, "seconds to wait at a barrier before going on with a quorum (or giving up)")
    heartbeat_timeout: float = opt(60.0, "a member whose heartbeat has not changed for this long is stale")
    quorum: int = opt(0, "deposits needed to go on without stale members (0: majority, floor(N/2)+1)")
    keep_iterations: int = opt(5, "keep non-selected agents of the last K iterations (selected ones are always kept)")
    poll_max: float = opt(0.0, "longest pause between polls for the iteration's decision, seconds (0: "
                               "max(0.01, N x 0.0005), about 2,000 lookups a second for the whole pool)")
    key_file: str = opt("", "the pool's secret key file (default: ~/.config/rl-pool/keys/<pool id>.key, "
                            "made with the pool; or $RL_POOL_KEY_FILE, or the key in hex in $RL_POOL_KEY)")
    lr_adapt: float = opt(0.0, "after losing an iteration, take the winner's learning rate times F or 1/F "
                               "(population-based training); 0: keep this member's own rate")

    def validate(self, pool_size: int) -> MemberConfig:
        if not 0 <= self.member < pool_size:
            raise UsageError(f"--member must be in 0..{pool_size - 1} for a pool of {pool_size}, got {self.member}")
        if not (math.isfinite(self.learning_rate) and self.learning_rate > 0):
            raise UsageError(f"--learning-rate must be positive, got {self.learning_rate}")
        if self.iterations < 1:
            raise UsageError(f"--iterations must be a positive integer, got {self.iterations}")
        if not (self.barrier_timeout > 0 and self.heartbeat_timeout > 0):
            raise UsageError("--barrier-timeout and --heartbeat-timeout must be positive")
        if not (math.isfinite(self.poll_max) and self.poll_max >= 0):
            raise UsageError(f"--poll-max must be >= 0 (0: chosen from the pool size), got {self.poll_max}")
        if not 0 <= self.quorum <= pool_size:
            raise UsageError(f"--quorum must be in 1..{pool_size} (0 for the majority), got {self.quorum}")
        if self.lr_adapt and not (math.isfinite(self.lr_adapt) and self.lr_adapt >= 1.0):
            raise UsageError(f"--lr-adapt must be >= 1 (or 0 for off), got {self.lr_adapt}")
        if self.keep_iterations < 0:
            raise UsageError(f"--keep-iterations must be >= 0, got {self.keep_iterations}")
        return self

    def poll_max_for(self, pool_size: int) -> float:
        """The longest pause between decision polls: ``--poll-max``, or one that grows with N so the
        lookups the waiting members make stay near 2,000 a second (docs/cluster.md)."""
        return self.poll_max or max(0.01, 0.0005 * pool_size)

    def quorum_for(self, pool_size: int) -> int:
        return self.quorum or pool_size // 2 + 1
