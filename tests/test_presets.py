"""Presets: every one names real options and makes a valid pool; explicit options win."""

import os
from dataclasses import fields

import pytest

from rl_pool.commands import cli, presets
from rl_pool.config import MemberConfig, PoolConfig, default_batch

POOL_FIELDS = {f.name for f in fields(PoolConfig)}
KNOWN = POOL_FIELDS | {f.name for f in fields(MemberConfig)} | {"learning_rates"}


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


@pytest.mark.parametrize("size,want", [(2, [0.001, 0.003]), (8, [0.001] + [0.003] * 7), (1, [0.003])])
def test_a_preset_grown_to_more_members_keeps_its_rates(size, want, tmp_path, monkeypatch):
    # the first member at the preset's first (guard) rate, the rest at its last; never the
    # linear defaults (0.01, then 0.1), ten to a hundred times the MLP preset's rates
    from rl_pool.commands import launch

    seen = {}
    monkeypatch.setattr(launch, "launch", lambda pool_dir, requested, opts, lrs, *a, **kw: seen.update(lrs=lrs))
    cli.main(["launch", "--pool-dir", str(tmp_path / "p"), "--preset", "halfcheetah", "--pool-size", str(size)])
    assert seen["lrs"] == want
    assert [presets.member_learning_rate(presets.PRESETS["halfcheetah"], m, size) for m in range(size)] == want


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


@pytest.mark.parametrize("size, merge, train, batch", [
    (1, "adaptive", 20, 10), (2, "adaptive", 20, 10),  # no merges: min(10, E)
    (3, "adaptive", 20, 5), (8, "adaptive", 20, 5), (16, "adaptive", 40, 5),
    (8, "none", 20, 10), (8, "mean", 20, 10), (8, "sum", 20, 10),  # only the adaptive merge halves it
    (8, "adaptive", 4, 2), (8, "adaptive", 6, 3), (8, "adaptive", 3, 3),  # odd: no half-episode batches
    (8, "adaptive", 30, 5), (8, "adaptive", 15, 5),
    (8, "adaptive", 1, 1),
])
def test_the_default_batch_halves_in_pools_that_merge(size, merge, train, batch):
    cfg = PoolConfig(pool_size=size, merge=merge, train_episodes=train)
    assert default_batch(cfg) == batch
    resolved = cfg.validate()
    assert resolved.batch_episodes == batch and train % batch == 0
    # an explicit batch is never changed
    assert PoolConfig(pool_size=size, merge=merge, train_episodes=train, batch_episodes=1).validate().batch_episodes == 1
