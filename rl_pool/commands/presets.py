"""Named settings for the MuJoCo tasks, found by measurement (results/<task>/, docs/results.md).

A preset fills in options the command line leaves out: explicit options win.
Pool-wide values go to ``pool.json`` like any option; ``learning_rates`` gives
one rate per member (``launch``; ``train --member I`` takes the I-th) and
``pool_size`` its length; in pools of 3 or more members, ``merged_merge`` is the
``--merge`` rule (:func:`merge`), and when that rule merges with the rule of three
``merged_batch_episodes`` replaces ``batch_episodes`` (:func:`batch_episodes`) and the other
``merged_<option>`` keys set ``<option>`` (:func:`merged_options`), in place of the preset's
own ``<option>`` where it has one. ``pick`` makes ``launch`` end with a pick (``--pick``), and
``pick_finalists`` and ``pick_final_episodes`` give that pick a final round.
"""

from __future__ import annotations

from rl_pool.errors import UsageError
from rl_pool.protocol.selection import RULES_OF_THREE

#: Each preset was chosen by measured runs; why each value is there, with the runs that decided
#: it, is in docs/results.md (one section per task) and the dated notebook, docs/notebook.md.
#: Humanoid's learner, which six presets share: a discount of 0.99, generalised advantage estimation on a
#: learned critic, nine more passes over each batch up PPO's clipped surrogate in minibatches of 64 steps,
#: and the critic's epochs in minibatches too.
CRITIC_PPO = {"gamma": 0.99, "baseline": "value", "gae_lambda": 0.95, "policy_epochs": 10, "minibatch_steps": 64,
              "value_minibatch_steps": 64}
#: That learner on an MLP started sharp, with the branches alone competing on 10 evaluation episodes
#: and 40 training episodes in steps of 20: Walker2d's and Ant's preset, Hopper's with its rates annealed and a
#: pick, and Humanoid's with reverts.
CRITIC_PPO_BRANCHES = {**CRITIC_PPO, "selection": "branches", "eval_episodes": 10, "train_episodes": 40,
                       "batch_episodes": 20, "policy": "mlp", "hidden": "64,64", "init_shape": 20.0,
                       "learning_rates": [0.0001, 0.0003]}
#: A launch that ends with a pick whose 6 best candidates play a final round (HalfCheetah's, Hopper's and
#: InvertedDoublePendulum's presets).
PICK_WITH_FINAL_ROUND = {"pick": True, "pick_finalists": 6}

PRESETS: dict[str, dict] = {
    "swimmer": {"env": "Swimmer-v5", "learning_rates": [0.01, 0.1]},
    "halfcheetah": {"env": "HalfCheetah-v5", **CRITIC_PPO, "batch_episodes": 2,
                    "policy": "mlp", "hidden": "64,64", "init_shape": 20.0, "learning_rates": [0.0001, 0.0003],
                    "merged_merge": "momentum", "merged_parent_patience": 3, "merged_revert_after": 20,
                    "merged_revert_sharpen": 3.0, "merged_rate_patience": 3, **PICK_WITH_FINAL_ROUND},
    "hopper": {"env": "Hopper-v5", **CRITIC_PPO_BRANCHES, "rate_anneal": 300, **PICK_WITH_FINAL_ROUND},
    "walker2d": {"env": "Walker2d-v5", **CRITIC_PPO_BRANCHES},
    "ant": {"env": "Ant-v5", **CRITIC_PPO_BRANCHES, "best_score": "mean"},
    "inverted-double-pendulum": {"env": "InvertedDoublePendulum-v5", "gamma": 0.99, "baseline": "linear",
                                 "gae_lambda": 0.95, "policy_epochs": 10, "eval_episodes": 30, "policy": "mlp",
                                 "hidden": "64,64", "init_shape": 20.0, "parent_patience": 3, "revert_after": 20,
                                 "best_score": "mean", "train_env_kwargs": {"reset_noise_scale": 0.13},
                                 "learning_rates": [0.001, 0.003], **PICK_WITH_FINAL_ROUND},
    "reacher": {"env": "Reacher-v5", "eval_episodes": 20, "train_episodes": 100, "batch_episodes": 50,
                "policy": "mlp", "hidden": "64,64", "init_shape": 20.0, "baseline": "linear",
                "learning_rates": [0.001, 0.003]},
    "inverted-pendulum": {"env": "InvertedPendulum-v5", "selection": "branches", "revert_after": 20,
                          "eval_episodes": 10, "learning_rates": [0.01, 0.1], "pick": True},
    "pusher": {"env": "Pusher-v5", **CRITIC_PPO, "eval_episodes": 20, "train_episodes": 100,
               "batch_episodes": 50, "policy": "mlp", "hidden": "64,64", "init_shape": 20.0, "rate_anneal": 500,
               "learning_rates": [0.0001, 0.0003]},
    "humanoid": {"env": "Humanoid-v5", **CRITIC_PPO_BRANCHES, "revert_after": 20},
    "humanoid-standup": {"env": "HumanoidStandup-v5", "gamma": 0.99, "baseline": "linear", "gae_lambda": 0.95,
                         "eval_episodes": 5, "learning_rates": [0.003, 0.01]},
}


#: Preset keys that are ``launch`` options, not pool or member settings.
LAUNCH_ONLY = ("pick", "pick_finalists", "pick_final_episodes")


def get(name: str) -> dict:
    try:
        return PRESETS[name]
    except KeyError:
        raise UsageError(f"unknown preset {name!r} (have {', '.join(PRESETS)})") from None


def learning_rates(preset: dict, pool_size: int) -> list[float] | None:
    """The preset's rate for each member of a pool of ``pool_size``: its own list when the sizes
    agree, else, as the default launch does, the first member at the preset's first rate (the
    guard against steps that are too large) and the rest at its last."""
    lrs = preset.get("learning_rates")
    if not lrs or pool_size < 1:
        return None
    if len(lrs) == pool_size:
        return [float(x) for x in lrs]
    if pool_size == 1:
        return [float(lrs[-1])]
    return [float(lrs[0])] + [float(lrs[-1])] * (pool_size - 1)


def merge(preset: dict, pool_size: int) -> str | None:
    """The preset's ``--merge`` for a pool of ``pool_size``: its ``merged_merge`` in a pool of 3 or
    more members, else its plain ``merge`` (None: the default). A pool of 2 decides alike under every
    rule that merges from three branches, so its ``pool.json`` stays as the preset made it before."""
    if pool_size >= 3 and "merged_merge" in preset:
        return preset["merged_merge"]
    return preset.get("merge")


def batch_episodes(preset: dict, pool_size: int, merge: str) -> int | None:
    """The preset's episodes per gradient step for a pool of ``pool_size``: its
    ``merged_batch_episodes`` in a pool of 3 or more members that merges from three branches
    (``adaptive`` or ``momentum``; each member
    takes more, noisier steps per iteration and the merge averages the noise; docs/scaling.md,
    HalfCheetah), else its ``batch_episodes`` (None: the default, min(10, E))."""
    if pool_size >= 3 and merge in RULES_OF_THREE and "merged_batch_episodes" in preset:
        return preset["merged_batch_episodes"]
    return preset.get("batch_episodes")


#: ``merged_`` keys with rules of their own (:func:`merge`, :func:`batch_episodes`); the others are options.
_MERGED_SPECIAL = ("merged_merge", "merged_batch_episodes")


def merged_options(preset: dict, pool_size: int, merge: str, selection: str) -> dict:
    """The options a preset sets only in a pool of ``pool_size`` >= 3 that merges from three branches
    (``merge`` in the rule of three): its ``merged_<option>`` keys, by option name. Patience with the
    parent (``merged_parent_patience``) goes only where the parent competes (``selection`` parent)."""
    if pool_size < 3 or merge not in RULES_OF_THREE:
        return {}
    out = {key.removeprefix("merged_"): value for key, value in preset.items()
           if key.startswith("merged_") and key not in _MERGED_SPECIAL}
    if selection != "parent":
        out.pop("parent_patience", None)
    return out


def needless(preset: dict, value) -> set[str]:
    """The preset's options that the pool's other settings (``value(name)``: the final value of an
    option) leave nothing to do, and that the pool's checks would refuse for it: sharpening at
    reverts (``revert_sharpen``, or ``merged_revert_sharpen`` in pools that merge) without
    reverts or without the ``exp`` link, extra passes over each batch (``policy_epochs``) with a
    step rule other than Adam, the policy's minibatches (``minibatch_steps``) without those passes,
    and the critic's (``value_minibatch_steps``) without a critic or its extra epochs."""
    out = set()
    sharpens = "revert_sharpen" in preset or "merged_revert_sharpen" in preset
    if sharpens and (not value("revert_after") or value("link") != "exp"):
        out.add("revert_sharpen")
    if "policy_epochs" in preset and value("optimizer") != "adam":
        out.add("policy_epochs")
    if "minibatch_steps" in preset and ("policy_epochs" in out or value("policy_epochs") < 2):
        out.add("minibatch_steps")
    if "value_minibatch_steps" in preset and (value("baseline") != "value" or value("value_epochs") < 2):
        out.add("value_minibatch_steps")
    return out


def member_learning_rate(preset: dict, member: int, pool_size: int) -> float | None:
    """The preset's rate for one member (:func:`learning_rates`)."""
    lrs = learning_rates(preset, pool_size)
    if lrs and 0 <= member < pool_size:
        return lrs[member]
    return None
