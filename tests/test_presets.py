"""Presets: every one names real options and makes a valid pool; explicit options win."""

import json
import os
from dataclasses import fields

import pytest

from rl_pool.commands import cli, presets
from rl_pool.config import MemberConfig, PoolConfig
from rl_pool.errors import UsageError

POOL_FIELDS = {f.name for f in fields(PoolConfig)}
KNOWN = POOL_FIELDS | {f.name for f in fields(MemberConfig)} | {"learning_rates", *presets.LAUNCH_ONLY} | {
    f"merged_{name}" for name in POOL_FIELDS}


def _launch_config(name, tmp_path, *extra):
    args = cli.build_parser().parse_args(["launch", "--pool-dir", str(tmp_path), "--preset", name, *extra])
    chosen = cli._apply_preset(args)
    return chosen, PoolConfig.merged(cli._explicit(args, PoolConfig), None)


@pytest.mark.parametrize("name", list(presets.PRESETS))
def test_every_preset_sets_known_options_into_a_valid_pool(name, tmp_path):
    # _apply_preset sets any key on the parsed arguments: a misspelt key would be dropped silently
    assert set(presets.PRESETS[name]) <= KNOWN, set(presets.PRESETS[name]) - KNOWN
    chosen, cfg = _launch_config(name, tmp_path)
    assert cfg.pool_size == len(chosen["learning_rates"])
    for key, value in chosen.items():
        if key in POOL_FIELDS:
            assert getattr(cfg, key) == value, key
    assert cfg.train_episodes % cfg.batch_episodes == 0  # whole gradient steps per iteration


def test_explicit_options_win_over_the_preset(tmp_path):
    chosen, cfg = _launch_config("walker2d", tmp_path, "--train-episodes", "20", "--batch-episodes", "10")
    assert (chosen["train_episodes"], chosen["batch_episodes"]) == (40, 20)
    assert (cfg.train_episodes, cfg.batch_episodes, cfg.policy) == (20, 10, "mlp")


@pytest.mark.parametrize("name", ["hopper", "walker2d", "reacher"])
def test_preset_batch_size_goes_with_its_own_train_episodes(name, tmp_path):
    # --train-episodes alone: the preset's batch (20 or 50) need not divide it, so the default
    # min(10, E) applies; the rest of the preset still does
    chosen, cfg = _launch_config(name, tmp_path, "--train-episodes", "4")
    assert chosen["batch_episodes"] > 4
    assert (cfg.train_episodes, cfg.batch_episodes, cfg.env) == (4, 4, chosen["env"])
    _, cfg = _launch_config(name, tmp_path, "--train-episodes", "30")
    assert (cfg.train_episodes, cfg.batch_episodes) == (30, 10)
    _, cfg = _launch_config(name, tmp_path, "--batch-episodes", "10")  # the preset's E, the given batch
    assert (cfg.train_episodes, cfg.batch_episodes) == (chosen["train_episodes"], 10)
    _, cfg = _launch_config(name, tmp_path, "--train-episodes", str(chosen["train_episodes"]))  # its own E
    assert (cfg.train_episodes, cfg.batch_episodes) == (chosen["train_episodes"], chosen["batch_episodes"])


@pytest.mark.parametrize("size,want", [(2, [0.0001, 0.0003]), (8, [0.0001] + [0.0003] * 7), (1, [0.0003])])
def test_a_preset_grown_to_more_members_keeps_its_rates(size, want, tmp_path, monkeypatch):
    # the first member at the preset's first (guard) rate, the rest at its last; never the
    # linear defaults (0.01, then 0.1), a hundred times the MLP preset's rates and more
    from rl_pool.commands import launch

    seen = {}
    monkeypatch.setattr(launch, "launch", lambda pool_dir, requested, opts, lrs, *a, **kw: seen.update(lrs=lrs))
    cli.main(["launch", "--pool-dir", str(tmp_path / "p"), "--preset", "halfcheetah", "--pool-size", str(size)])
    assert seen["lrs"] == want
    assert [presets.member_learning_rate(presets.PRESETS["halfcheetah"], m, size) for m in range(size)] == want


#: Where each preset's committed run lives (results/README.md); swimmer's pool.json is of an older
#: protocol (its policy named "linear-exp"), made before presets existed.
COMMITTED = {"halfcheetah": "halfcheetah-v5", "hopper": "hopper-v5", "walker2d": "walker2d-v5", "ant": "ant-v5",
             "inverted-double-pendulum": "inverted-double-pendulum-v5", "reacher": "reacher-v5",
             "inverted-pendulum": "inverted-pendulum-v5", "pusher": "pusher-v5", "humanoid": "humanoid-v5",
             "humanoid-standup": "humanoidstandup-v5"}


def _results_pool(where):
    with open(os.path.join(os.path.dirname(__file__), "..", "results", where, "pool.json")) as fh:
        return json.load(fh)


def _settings_unlike(cfg, made):
    """The settings of ``cfg`` that a made pool's ``pool.json`` holds otherwise (max_episode_steps is 0
    in a config: the env's own, resolved when the pool is made)."""
    return [f.name for f in fields(cfg) if f.name in made and f.name != "max_episode_steps"
            and json.loads(json.dumps(getattr(cfg, f.name))) != made[f.name]]


@pytest.mark.parametrize("name", sorted(COMMITTED))
def test_each_committed_run_is_its_preset(name, tmp_path):
    """The pool.json of ``results/<task>/`` holds the pool-wide settings ``--preset NAME`` makes for
    that run's seed and size: a preset changed without its committed run redone fails here (the
    learning rates are members' settings, in command.txt, not pool.json)."""
    assert set(COMMITTED) == set(presets.PRESETS) - {"swimmer"}
    made = _results_pool(COMMITTED[name])
    _, cfg = _launch_config(name, tmp_path, "--seed", str(made["seed"]), "--pool-size", str(made["pool_size"]))
    assert _settings_unlike(cfg, made) == []


#: Committed runs a preset's change replaced, and the options docs/usage.md gives to resume such a
#: pool with the preset now.
REPLACED = [
    ("hopper", "hopper-v5/screening/critic-ppo-seed0-20min-2026-12-07", ("--rate-anneal", "0")),
    ("hopper", "hopper-v5/screening/revert-sharpen3-seed2-2026-11-28",
     ("--policy", "linear", "--init-shape", "0", "--gamma", "1", "--baseline", "time", "--gae-lambda", "1",
      "--policy-epochs", "1", "--reward-shift", "1", "--revert-after", "20", "--revert-sharpen", "3",
      "--rate-anneal", "0")),
    ("ant", "ant-v5/screening/critic-ppo-seed0-20min-2026-12-07",
     ("--selection", "parent", "--train-episodes", "20", "--batch-episodes", "10", "--revert-after", "20")),
    ("ant", "ant-v5/screening/policy-epochs10-seed0-20min",
     ("--baseline", "linear", "--minibatch-steps", "0", "--selection", "parent", "--train-episodes", "20",
      "--batch-episodes", "10", "--revert-after", "20")),
    ("walker2d", "walker2d-v5/screening/critic-ppo-shift-reverts-seed0-2026-12-06",
     ("--reward-shift", "1", "--revert-after", "20")),
    ("walker2d", "walker2d-v5/screening/policy-epochs10-gae0.95-linear-seed0-20min",
     ("--baseline", "linear", "--minibatch-steps", "0", "--reward-shift", "1", "--revert-after", "20")),
    ("pusher", "pusher-v5/screening/anneal500-seed0-20min",
     ("--gamma", "1", "--baseline", "time", "--gae-lambda", "1", "--policy-epochs", "1")),
    ("halfcheetah", "halfcheetah-v5/screening/momentum-eight-members-seed0-20min",
     ("--pool-size", "8", "--gamma", "1", "--baseline", "time", "--gae-lambda", "1", "--policy-epochs", "1",
      "--batch-episodes", "5", "--rate-patience", "0")),
]


@pytest.mark.parametrize("name, where, resume", REPLACED)
def test_a_pool_of_the_preset_before_resumes_with_the_options_the_docs_give(name, where, resume, tmp_path):
    made = _results_pool(where)
    _, now = _launch_config(name, tmp_path / "now", "--seed", str(made["seed"]))
    _, cfg = _launch_config(name, tmp_path / "before", "--seed", str(made["seed"]), *resume)
    assert _settings_unlike(now, made)  # the preset did change
    assert _settings_unlike(cfg, made) == []
    with open(os.path.join(os.path.dirname(__file__), "..", "docs", "usage.md")) as fh:
        usage = " ".join(fh.read().split())
    assert f"`{name}` pool made before" in usage and " ".join(resume) in usage


@pytest.mark.parametrize("doc", ["README.md", "docs/usage.md"])
def test_every_preset_is_in_the_docs_tables(doc):
    """The presets tables of the README and the usage page name every preset and its env."""
    with open(os.path.join(os.path.dirname(__file__), "..", doc)) as fh:
        text = fh.read()
    rows = {line.split("|")[1].strip().strip("`"): line for line in text.splitlines()
            if line.startswith("| `")}
    for name, preset in presets.PRESETS.items():
        assert name in rows, f"{doc} has no row for preset {name!r}"
        assert preset["env"] in rows[name], f"{doc}: the row of {name!r} does not name {preset['env']}"


def test_a_preset_gives_its_pick_a_final_round_and_the_options_that_win(tmp_path):
    def launch_pick(*argv):
        args = cli.build_parser().parse_args(["launch", "--pool-dir", str(tmp_path), *argv])
        cli._apply_preset(args)
        return cli._pick_round(args)

    idp = ("--preset", "inverted-double-pendulum")
    assert launch_pick(*idp) == {"pick_finalists": 6, "pick_final_episodes": 100}
    assert launch_pick(*idp, "--pick-finalists", "2", "--pick-final-episodes", "50") == {
        "pick_finalists": 2, "pick_final_episodes": 50}
    assert launch_pick(*idp, "--no-pick") == {}  # the preset's final round goes with its pick
    assert launch_pick("--preset", "halfcheetah") == {"pick_finalists": 6, "pick_final_episodes": 100}
    assert launch_pick("--preset", "swimmer", "--pick") == {"pick_finalists": 0, "pick_final_episodes": 100}
    with pytest.raises(UsageError, match="--pick-finalists sets the final round of a pick: add --pick"):
        launch_pick(*idp, "--no-pick", "--pick-finalists", "3")
    # the preset's dict is the pool's, never shared with the parsed arguments
    args = cli.build_parser().parse_args(["launch", "--pool-dir", str(tmp_path), *idp])
    cli._apply_preset(args)
    assert args.train_env_kwargs == {"reset_noise_scale": 0.13}
    assert args.train_env_kwargs is not presets.PRESETS["inverted-double-pendulum"]["train_env_kwargs"]


@pytest.mark.parametrize("extra, batch", [
    ((), 10),  # 2 members: min(10, E)
    (("--pool-size", "2"), 10),
    (("--pool-size", "3"), 5), (("--pool-size", "8"), 5), (("--pool-size", "16"), 5),  # merged pools
    (("--pool-size", "8", "--merge", "none"), 10), (("--pool-size", "8", "--merge", "mean"), 10),
    (("--pool-size", "8", "--batch-episodes", "4"), 4), (("--pool-size", "2", "--batch-episodes", "4"), 4),
    (("--pool-size", "8", "--train-episodes", "30"), 10),  # another E: the default min(10, E)
    (("--pool-size", "8", "--train-episodes", "20"), 5),  # the preset's own E (the default), given
])
def test_a_merged_batch_goes_to_pools_that_merge(extra, batch, tmp_path, monkeypatch):
    monkeypatch.setitem(presets.PRESETS, "merged-batch", {
        "env": "HalfCheetah-v5", "policy": "mlp", "hidden": "64,64", "learning_rates": [0.001, 0.003],
        "merged_batch_episodes": 5, "merged_merge": "momentum"})
    _, cfg = _launch_config("merged-batch", tmp_path, *extra)
    assert cfg.batch_episodes == batch


@pytest.mark.parametrize("extra", [(), ("--pool-size", "8"), ("--pool-size", "16", "--merge", "none")])
def test_halfcheetah_steps_on_two_episodes_at_every_pool_size(extra, tmp_path):
    # PPO's rollout of about 2000 steps: 10 clipped updates per iteration, alone or merged
    _, cfg = _launch_config("halfcheetah", tmp_path, *extra)
    assert (cfg.train_episodes, cfg.batch_episodes, cfg.baseline, cfg.policy_epochs) == (20, 2, "value", 10)


@pytest.mark.parametrize("extra,merge", [
    ((), "adaptive"), (("--pool-size", "2"), "adaptive"),  # 2 members: pool.json as before
    (("--pool-size", "3"), "momentum"), (("--pool-size", "16"), "momentum"),
    (("--pool-size", "8", "--merge", "adaptive"), "adaptive"),  # given explicitly, it wins
])
def test_halfcheetah_merges_with_momentum_in_pools_of_three_or_more(extra, merge, tmp_path):
    _, cfg = _launch_config("halfcheetah", tmp_path, *extra)
    assert cfg.merge == merge


def test_merged_batch_only_where_a_preset_has_one():
    for name, preset in presets.PRESETS.items():
        assert presets.batch_episodes(preset, 2, "adaptive") == preset.get("batch_episodes")
        assert presets.batch_episodes(preset, 8, "adaptive") == preset.get(
            "merged_batch_episodes", preset.get("batch_episodes")), name


@pytest.mark.parametrize("extra,patience,revert,rate_patience", [
    ((), 0, 0, 0), (("--pool-size", "2"), 0, 0, 0),  # 2 members: pool.json as before
    (("--pool-size", "3"), 3, 20, 3), (("--pool-size", "8"), 3, 20, 3), (("--pool-size", "16"), 3, 20, 3),
    (("--pool-size", "8", "--merge", "none"), 0, 0, 0), (("--pool-size", "8", "--merge", "mean"), 0, 0, 0),
    (("--pool-size", "8", "--parent-patience", "5"), 5, 20, 3),  # given explicitly, each wins
    (("--pool-size", "8", "--revert-after", "0"), 3, 0, 3),
    (("--pool-size", "8", "--rate-patience", "5"), 3, 20, 5),
    (("--pool-size", "8", "--selection", "branches"), 0, 20, 3),  # no parent to be patient with
])
def test_halfcheetah_pools_that_merge_end_long_parent_runs_and_plateaus(extra, patience, revert, rate_patience,
                                                                         tmp_path):
    # past 3500 the members at 0.0003 fall in most iterations: after 3 without a new best every rate halves
    _, cfg = _launch_config("halfcheetah", tmp_path, *extra)
    assert (cfg.parent_patience, cfg.revert_after, cfg.rate_patience) == (patience, revert, rate_patience)


def test_merged_options_only_in_pools_that_merge_from_three():
    preset = presets.PRESETS["halfcheetah"]
    want = {"parent_patience": 3, "revert_after": 20, "revert_sharpen": 3.0, "rate_patience": 3}
    assert presets.merged_options(preset, 8, "momentum", "parent") == want
    assert presets.merged_options(preset, 8, "adaptive", "parent") == want
    assert presets.merged_options(preset, 2, "momentum", "parent") == {}
    assert presets.merged_options(preset, 8, "none", "parent") == {}
    assert presets.merged_options(preset, 8, "momentum", "branches") == {"revert_after": 20, "revert_sharpen": 3.0,
                                                                         "rate_patience": 3}
    for name, other in presets.PRESETS.items():
        if not any(key.startswith("merged_") for key in other):
            assert presets.merged_options(other, 8, "adaptive", "parent") == {}, name


def test_a_merged_option_replaces_the_plain_one_in_pools_that_merge(tmp_path, monkeypatch):
    monkeypatch.setitem(presets.PRESETS, "plain-and-merged", {
        "env": "Hopper-v5", "selection": "branches", "learning_rates": [0.01, 0.03],
        "merged_merge": "momentum", "merged_selection": "parent", "merged_parent_patience": 3})
    cases = [((), ("branches", "adaptive", 0)),  # 2 members: the plain values
             (("--pool-size", "8"), ("parent", "momentum", 3)),
             (("--pool-size", "8", "--selection", "branches"), ("branches", "momentum", 0)),  # given: it wins
             (("--pool-size", "8", "--merge", "none"), ("branches", "none", 0))]  # a pool that never merges
    for extra, want in cases:
        _, cfg = _launch_config("plain-and-merged", tmp_path, *extra)
        assert (cfg.selection, cfg.merge, cfg.parent_patience) == want, extra


def test_ants_extra_passes_leave_with_another_step_rule(tmp_path):
    """``--preset ant`` takes 10 passes over each batch in minibatches, which need Adam: with
    ``--optimizer normalized`` the pool is made without them (not refused for an option the user
    never gave); given explicitly, they are refused."""
    cfg = _launch_config("ant", tmp_path)[1]
    assert (cfg.policy_epochs, cfg.minibatch_steps) == (10, 64)
    cfg = _launch_config("ant", tmp_path, "--optimizer", "normalized")[1]
    assert (cfg.optimizer, cfg.policy_epochs, cfg.minibatch_steps) == ("normalized", 1, 0)
    with pytest.raises(UsageError, match="--policy-epochs above 1 needs --optimizer adam"):
        _launch_config("ant", tmp_path, "--optimizer", "normalized", "--policy-epochs", "3")


@pytest.mark.parametrize("name", ["ant", "humanoid"])
def test_a_presets_minibatches_leave_with_the_passes_or_the_critic_they_serve(name, tmp_path):
    """The policy's minibatches go with ``--policy-epochs 1``, the critic's with another baseline or
    ``--value-epochs 1``, each only where the preset gave them; given explicitly, they are refused."""
    cfg = _launch_config(name, tmp_path)[1]
    assert (cfg.baseline, cfg.minibatch_steps, cfg.value_minibatch_steps) == ("value", 64, 64)
    cfg = _launch_config(name, tmp_path, "--policy-epochs", "1")[1]
    assert (cfg.policy_epochs, cfg.minibatch_steps, cfg.value_minibatch_steps) == (1, 0, 64)
    cfg = _launch_config(name, tmp_path, "--baseline", "linear")[1]
    assert (cfg.baseline, cfg.minibatch_steps, cfg.value_minibatch_steps) == ("linear", 64, 0)
    assert _launch_config(name, tmp_path, "--value-epochs", "1")[1].value_minibatch_steps == 0
    with pytest.raises(UsageError, match="--minibatch-steps needs --policy-epochs above 1"):
        _launch_config(name, tmp_path, "--policy-epochs", "1", "--minibatch-steps", "32")
    with pytest.raises(UsageError, match="--value-minibatch-steps needs --baseline value"):
        _launch_config(name, tmp_path, "--baseline", "linear", "--value-minibatch-steps", "32")


@pytest.mark.parametrize(("extra", "sharpen"), [
    ((), 1.0), (("--pool-size", "8"), 3.0), (("--pool-size", "16"), 3.0),
    (("--pool-size", "8", "--merge", "none"), 1.0),  # a pool that never merges has no reverts either
    (("--pool-size", "8", "--revert-after", "0"), 1.0),  # no reverts: left out, not refused
    (("--pool-size", "8", "--link", "softplus"), 1.0),  # sharpening needs the exp link: left out too
    (("--pool-size", "8", "--revert-sharpen", "2"), 2.0),
])
def test_halfcheetah_pools_that_merge_sharpen_at_reverts(extra, sharpen, tmp_path):
    assert _launch_config("halfcheetah", tmp_path, *extra)[1].revert_sharpen == sharpen


def test_sharpening_given_explicitly_without_reverts_is_refused(tmp_path):
    with pytest.raises(UsageError, match="--revert-sharpen needs --revert-after"):
        _launch_config("halfcheetah", tmp_path, "--pool-size", "8", "--revert-after", "0", "--revert-sharpen", "2")


def test_a_preset_that_ends_with_a_pick_and_the_option_that_wins(tmp_path):
    def pick(*argv):
        args = cli.build_parser().parse_args(["launch", "--pool-dir", str(tmp_path), *argv])
        cli._apply_preset(args)
        return bool(args.pick)

    assert pick("--preset", "halfcheetah") and pick("--preset", "halfcheetah", "--pool-size", "8")
    assert not pick("--preset", "halfcheetah", "--no-pick")
    assert pick("--preset", "hopper") and not pick("--preset", "hopper", "--no-pick")
    assert pick("--preset", "inverted-pendulum")
    assert not pick("--preset", "walker2d") and pick("--preset", "walker2d", "--pick") and not pick()
    # `train` runs one member and has no pick: the preset leaves the launch's key out there
    args = cli.build_parser().parse_args(["train", "--pool-dir", str(tmp_path), "--preset", "halfcheetah"])
    cli._apply_preset(args)
    assert not hasattr(args, "pick") and args.env == "HalfCheetah-v5"
