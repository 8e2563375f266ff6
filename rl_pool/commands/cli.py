"""Command line: argument parsing and the commands; the work happens elsewhere."""

from __future__ import annotations

import argparse
import json
import os
import sys
from dataclasses import MISSING, fields

from rl_pool.threads import cap_threads

# Pool-wide and per-member options are generated from the config dataclasses,
# so their help text and defaults live in one place (rl_pool/config.py).


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # one line, exit 2 (argparse would print the usage block too)
        sys.stderr.write(f"{self.prog}: error: {message}\n")
        sys.exit(2)


def _json_object(text: str) -> dict:
    try:
        value = json.loads(text)
    except json.JSONDecodeError as exc:
        raise argparse.ArgumentTypeError(f"not valid JSON ({exc.msg})") from None
    if not isinstance(value, dict):
        raise argparse.ArgumentTypeError("must be a JSON object")
    return value


def _add_dataclass_options(parser, cls, skip=(), required=()):
    group = parser.add_argument_group(cls.__doc__.splitlines()[0].rstrip("."))
    for f in fields(cls):
        if f.name in skip or f.metadata.get("internal"):
            continue
        default = f.default if f.default is not MISSING else f.default_factory()
        kind = _json_object if isinstance(default, dict) else type(default)
        help_text = f.metadata["help"] + ("" if f.name in required else f" (default: {json.dumps(default)})")
        group.add_argument("--" + f.name.replace("_", "-"), dest=f.name, type=kind, default=None,
                           required=f.name in required, choices=f.metadata.get("choices"),
                           metavar=f.name.upper() if not f.metadata.get("choices") else None,
                           help=help_text)


def _explicit(args, cls, skip=()) -> dict:
    return {f.name: getattr(args, f.name) for f in fields(cls)
            if f.name not in skip and getattr(args, f.name, None) is not None}


def _apply_preset(args) -> dict:
    """Fill options left unset from ``--preset``; returns the preset (empty without one)."""
    if not getattr(args, "preset", None):
        return {}
    from rl_pool.commands import presets

    chosen = presets.get(args.preset)
    unset = {name for name, value in vars(args).items() if value is None}
    # A preset's gradient step size belongs to its episode count: with another --train-episodes
    # given and --batch-episodes not, the batch is the default min(10, E), not a size that may
    # not divide E.
    from rl_pool.config import PoolConfig

    own_batch = getattr(args, "train_episodes", None) in (None, chosen.get("train_episodes", PoolConfig.train_episodes))
    if getattr(args, "pool_size", None) is None and "learning_rates" in chosen:
        args.pool_size = len(chosen["learning_rates"])
    size = getattr(args, "pool_size", None) or 1
    if getattr(args, "merge", None) is None:
        args.merge = presets.merge(chosen, size)
    merge = getattr(args, "merge", None) or PoolConfig.merge
    # in a pool that merges from three branches, the preset's merged_<option> replaces its <option>
    merged = presets.merged_options(chosen, size, merge, "parent")
    for key, value in chosen.items():
        if key in ("learning_rates", "batch_episodes") or key.startswith("merged_") or key in merged:
            continue
        if key in presets.LAUNCH_ONLY and not hasattr(args, key):
            continue  # `train` runs one member: what a launch does after its members is not its own
        if getattr(args, key, None) is None:
            setattr(args, key, dict(value) if isinstance(value, dict) else value)  # never the preset's own dict
    if own_batch and getattr(args, "batch_episodes", None) is None:
        args.batch_episodes = presets.batch_episodes(chosen, size, merge)
    selection = getattr(args, "selection", None) or merged.get("selection") or PoolConfig.selection
    for key, value in presets.merged_options(chosen, size, merge, selection).items():
        if getattr(args, key, None) is None:
            setattr(args, key, value)

    def final(name):
        value = getattr(args, name, None)
        return getattr(PoolConfig, name) if value is None else value

    for key in presets.needless(chosen, final) & unset:  # the preset's, not the user's: left out
        setattr(args, key, None)
    args.preset_set = {name for name in unset if getattr(args, name, None) is not None}
    return chosen


def _check_preset_against_pool(args) -> None:
    """A pool made with other values of what ``--preset`` filled in (a preset that changed since, or
    one grown to another size) is refused in one line that says so and how to resume it; the
    pool's own check would tell the user to drop an option they never gave."""
    from rl_pool.config import PoolConfig
    from rl_pool.errors import UsageError
    from rl_pool.protocol import layout, pool

    paths = layout.Paths(args.pool_dir)
    names = set(getattr(args, "preset_set", ())) & {f.name for f in fields(PoolConfig)}
    if not names or not os.path.exists(paths.pool_json):
        return
    try:
        saved = pool.read_config(paths)
    except UsageError:
        return  # the member's own checks say what is wrong with the pool
    PoolConfig.merged({name: getattr(args, name) for name in sorted(names)}, saved, where=f"pool {paths.root}",
                      preset=args.preset)


def _member_config(args, **override):
    from rl_pool.config import MemberConfig

    return MemberConfig(**(_explicit(args, MemberConfig) | override))


# ----------------------------------------------------------------- commands
def cmd_train(args) -> int:
    from rl_pool.commands import member
    from rl_pool.config import PoolConfig

    preset = _apply_preset(args)
    _check_preset_against_pool(args)
    if args.learning_rate is None and preset:
        from rl_pool.commands.presets import member_learning_rate

        args.learning_rate = member_learning_rate(preset, args.member or 0, args.pool_size)
    requested = _explicit(args, PoolConfig)
    return member.run(args.pool_dir, requested, _member_config(args), quiet=args.quiet)


def cmd_launch(args) -> int:
    from rl_pool.commands import launch
    from rl_pool.config import MemberConfig, PoolConfig

    if args.learning_rates and args.pool_size is None:
        args.pool_size = len(args.learning_rates)  # one rate per member: the list says how many
    preset = _apply_preset(args)
    _check_preset_against_pool(args)
    lrs = args.learning_rates
    if lrs is None and args.learning_rate is None and preset.get("learning_rates"):
        from rl_pool.commands.presets import learning_rates

        lrs = learning_rates(preset, args.pool_size)  # a larger pool keeps the preset's rates
    requested = _explicit(args, PoolConfig)
    member_opts = _explicit(args, MemberConfig, skip=("member", "learning_rate"))
    return launch.launch(args.pool_dir, requested, member_opts, lrs, args.learning_rate, quiet=args.quiet,
                         interval=args.interval, minutes=args.minutes, pick=bool(args.pick),
                         **_pick_round(args))


def _pick_round(args) -> dict:
    """The launch's final round of its pick: the preset's or the user's ``--pick-finalists`` and
    ``--pick-final-episodes``. Given without a pick, or the episodes without finalists, they would
    do nothing: refused (a preset's are left out with its pick)."""
    from rl_pool.commands import pick
    from rl_pool.errors import UsageError

    given = [name for name in ("pick_finalists", "pick_final_episodes")
             if getattr(args, name) is not None and name not in getattr(args, "preset_set", ())]
    if given and not args.pick:
        raise UsageError(f"--{given[0].replace('_', '-')} sets the final round of a pick: add --pick")
    if not args.pick:
        return {}
    finalists = args.pick_finalists if args.pick_finalists is not None else 0
    final = args.pick_final_episodes if args.pick_final_episodes is not None else pick.DEFAULT_FINAL_EPISODES
    if "pick_final_episodes" in given and not finalists:
        raise UsageError("--pick-final-episodes sets the final round's episodes: add --pick-finalists K")
    return {"pick_finalists": finalists, "pick_final_episodes": final}


def cmd_status(args) -> int:
    from rl_pool.commands import status

    if args.watch:
        if args.json or args.csv:
            raise _usage("--watch shows a live view; it does not combine with --json or --csv")
        from rl_pool.commands import progress

        return progress.watch(args.pool_dir, interval=args.interval,
                              recent=5 if args.last is None else min(args.last, 50))
    st = status.status(args.pool_dir)
    if args.csv:
        status.write_csv(st, args.csv)
    if args.json:
        print(json.dumps(st, indent=1))
    else:
        print(status.format_table(st, last=10 if args.last is None else args.last))
    return 0


def _usage(message: str):
    from rl_pool.errors import UsageError

    return UsageError(message)


def cmd_compare(args) -> int:
    from rl_pool.commands import compare

    text = compare.compare(args.inputs, out=args.out, threshold=args.threshold,
                           at_minutes=args.at or (() if args.at_steps else compare.DEFAULT_AT),
                           groups=args.groups, metric=args.metric, title=args.title,
                           at_steps=args.at_steps or ())
    print(text)
    if args.out:
        print(args.out)
    return 0


def cmd_plot(args) -> int:
    from rl_pool.commands import plot

    out = plot.plot_pool(args.pool_dir, args.out)
    print(out)
    return 0


def cmd_evaluate(args) -> int:
    from rl_pool.commands import evaluate

    res = evaluate.evaluate_path(args.target, episodes=args.episodes, workers=args.workers,
                                 seed=args.seed, worker=args.worker, mode=args.mode)
    if args.json:
        print(json.dumps(res))
    else:
        print(f"{res['agent']}: {res['episodes']} episodes: mean {res['mean_return']:.2f} ± {res['std_return']:.2f} "
              f"(min {min(res['returns']):.2f}, max {max(res['returns']):.2f}) in {res['seconds']:.1f}s "
              f"on {res['workers']} workers")
    return 0


def cmd_pick(args) -> int:
    from rl_pool.commands import pick

    res = pick.pick(args.pool_dir, top=args.top, episodes=args.episodes, seed=args.seed, workers=args.workers,
                    mode=args.mode, out=args.out, finalists=args.finalists, final_episodes=args.final_episodes)
    print(json.dumps(res) if args.json else pick.format_text(res))
    return 0


def cmd_replay(args) -> int:
    from rl_pool.commands import replay

    out = replay.replay_path(args.target, args.out, steps=args.steps, seed=args.seed, fps=args.fps,
                             width=args.width, height=args.height, camera=args.camera)
    print(out)
    return 0


def build_parser() -> argparse.ArgumentParser:
    from rl_pool.config import MemberConfig, PoolConfig

    p = _Parser(prog="rl-pool", description="Branch-and-merge REINFORCE pools for MuJoCo tasks.")
    sub = p.add_subparsers(dest="command", required=True, parser_class=_Parser)

    t = sub.add_parser("train", help="run one member of a pool (creates the pool, or resumes it)")
    t.add_argument("--pool-dir", required=True, help="the shared pool directory")
    t.add_argument("--quiet", action="store_true", help="log to the pool's log file only, not stderr")
    t.add_argument("--preset", default=None, choices=_preset_names(),
                   help="named settings for a task (docs/usage.md: Presets); explicit options win")
    _add_dataclass_options(t, PoolConfig)
    _add_dataclass_options(t, MemberConfig)
    t.set_defaults(func=cmd_train)

    la = sub.add_parser("launch", help="start N members as local processes and watch them")
    la.add_argument("--pool-dir", required=True, help="the shared pool directory")
    la.add_argument("--learning-rates", type=_float_list, default=None, metavar="LR0,LR1,...",
                    help="one learning rate per member (default: the first member at 1/10 of "
                         "--learning-rate, the others at --learning-rate)")
    la.add_argument("--quiet", action="store_true", help="no progress lines: only the start and the summary")
    la.add_argument("--interval", type=_positive, default=10.0, metavar="S",
                    help="seconds between progress lines when stdout is not a terminal (default 10; "
                         "on a terminal the view is redrawn in place)")
    la.add_argument("--preset", default=None, choices=_preset_names(),
                    help="named settings for a task, learning rates included (docs/usage.md: Presets)")
    la.add_argument("--minutes", type=_positive, default=None, metavar="M",
                    help="stop the members after M minutes of wall-clock time (a pick included), as Ctrl-C "
                         "does; a later launch resumes the pool")
    la.add_argument("--pick", action=argparse.BooleanOptionalAction, default=None,
                    help="end the run with rl-pool pick (its defaults; POOL/picked.npz), within --minutes "
                         "(default: no, or the preset's choice)")
    la.add_argument("--pick-finalists", type=int, default=None, metavar="K",
                    help="with --pick: its K best candidates play --pick-final-episodes more, and the pick is "
                         "the finalist with the highest mean over all its episodes (rl-pool pick --finalists; "
                         "default 0, or the preset's)")
    la.add_argument("--pick-final-episodes", type=int, default=None, metavar="E",
                    help="with --pick-finalists: the final round's held-out episodes (default 100, or the "
                         "preset's)")
    _add_dataclass_options(la, PoolConfig)
    _add_dataclass_options(la, MemberConfig, skip=("member",))
    la.set_defaults(func=cmd_launch)

    s = sub.add_parser("status", help="show a pool: members, best, recent iterations")
    s.add_argument("pool_dir", help="the pool directory")
    s.add_argument("--json", action="store_true", help="print one JSON object")
    s.add_argument("--last", type=int, default=None,
                   help="iterations shown in the table (default 10; 5 with --watch)")
    s.add_argument("--csv", default=None, metavar="FILE",
                   help="also write the per-iteration history (returns, learning rates, wall time, env steps)")
    s.add_argument("--watch", action="store_true",
                   help="follow the pool until Ctrl-C: redrawn in place on a terminal, plain lines otherwise")
    s.add_argument("--interval", type=_positive, default=None, metavar="S",
                   help="with --watch: seconds between redraws (terminal, default 0.5) or between lines "
                        "(pipe or file, default 10)")
    s.set_defaults(func=cmd_status)

    c = sub.add_parser("compare", help="compare runs (seeds, tasks, settings): curves to a PNG and a table")
    c.add_argument("inputs", nargs="+", metavar="DIR|CSV",
                   help="pool directories or history.csv files (rl-pool status --csv)")
    c.add_argument("--out", default=None, metavar="FILE.png", help="draw the curves to this PNG")
    c.add_argument("--threshold", type=float, default=None, metavar="X",
                   help="report the wall time and env steps at which each run's return first reached X")
    c.add_argument("--at", type=_float_list, default=None, metavar="M1,M2,...",
                   help="minutes at which to report the best return so far (default 1,2,5,10,20, "
                        "up to the longest run; none by default with --at-steps)")
    c.add_argument("--at-steps", type=_float_list, default=None, metavar="S1,S2,...",
                   help="millions of env steps (all members) at which to report the best return so far: "
                        "runs made on machines of different speeds compare at equal samples")
    c.add_argument("--groups", type=_name_list, default=None, metavar="G1,G2,...",
                   help="one group name per input (default: pools that differ only in --seed, or CSVs "
                        "named ...seedN in one folder, form a group)")
    c.add_argument("--metric", choices=("selected", "best"), default="selected",
                   help="curve of the selected agent's return (default) or of the best so far")
    c.add_argument("--title", default=None, help="title of the plot")
    c.set_defaults(func=cmd_compare)

    pl = sub.add_parser("plot", help="plot the per-iteration evaluation return to a PNG")
    pl.add_argument("pool_dir")
    pl.add_argument("--out", default=None, help="output PNG (default: POOL/progress.png)")
    pl.set_defaults(func=cmd_plot)

    ev = sub.add_parser("evaluate", help="run an agent (or a pool's best) on fresh episodes")
    ev.add_argument("target", help="a pool directory (its pick, POOL/picked.npz, while that covers the pool's "
                    "last iteration; else its best.npz) or an agent .npz")
    ev.add_argument("--episodes", type=int, default=10)
    ev.add_argument("--workers", type=int, default=1, help="worker processes (spawned, one math thread each)")
    ev.add_argument("--seed", type=_seed, default=1_000_000, help="first episode's reset seed; episode k uses seed+k")
    ev.add_argument("--mode", choices=("mean", "sample"), default="mean", help="actions: Beta mean or samples")
    ev.add_argument("--worker", default=None, metavar="MODULE:CLASS",
                    help="a custom evaluation worker (subclass of rl_pool.commands.evaluate.EvalWorker)")
    ev.add_argument("--json", action="store_true")
    ev.set_defaults(func=cmd_evaluate)

    pk = sub.add_parser("pick", help="choose a pool's agent on held-out episodes (best.npz is partly the luck "
                                     "of its iteration's episodes)")
    pk.add_argument("pool_dir")
    pk.add_argument("--top", type=int, default=20,
                    help="candidates: this many distinct selected agents by evaluation return (0: all), and "
                         "the last selected agent (default 20)")
    pk.add_argument("--episodes", type=int, default=20, help="held-out episodes, the same for every candidate")
    pk.add_argument("--finalists", type=int, default=0, metavar="K",
                    help="the K best on --episodes play --final-episodes more, and the pick is the finalist "
                         "with the highest mean over all its episodes (0: no final round; default 0)")
    pk.add_argument("--final-episodes", type=int, default=100,
                    help="held-out episodes of the final round, after the first round's (default 100)")
    pk.add_argument("--seed", type=_seed, default=2_000_000,
                    help="first held-out episode's reset seed (default 2000000: not evaluate's 1000000 on)")
    pk.add_argument("--workers", type=int, default=1, help="worker processes (spawned, one math thread each)")
    pk.add_argument("--mode", choices=("mean", "sample"), default="mean", help="actions: Beta mean or samples")
    pk.add_argument("--out", default=None, metavar="FILE.npz",
                    help="where the pick goes (default POOL/picked.npz), with FILE.json beside it")
    pk.add_argument("--json", action="store_true")
    pk.set_defaults(func=cmd_pick)

    rp = sub.add_parser("replay", help="render an agent offscreen to a GIF or MP4")
    rp.add_argument("target", help="a pool directory (its current pick, else its best.npz) or an agent .npz")
    rp.add_argument("--out", required=True, help="FILE.gif or FILE.mp4")
    rp.add_argument("--steps", type=int, default=0, help="steps to render (default: one episode)")
    rp.add_argument("--seed", type=_seed, default=0, help="the episode's reset seed")
    rp.add_argument("--fps", type=int, default=30)
    rp.add_argument("--width", type=int, default=480)
    rp.add_argument("--height", type=int, default=360)
    rp.add_argument("--camera", default=None, help="a camera of the model (default: 'track' if it has one)")
    rp.set_defaults(func=cmd_replay)

    from rl_pool.protocol import doctor

    doctor.add_parser(sub)
    return p


def _preset_names() -> list[str]:
    from rl_pool.commands.presets import PRESETS

    return list(PRESETS)


def _seed(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError("must be >= 0")
    return value


def _positive(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not value > 0 or value == float("inf"):
        raise argparse.ArgumentTypeError("must be a positive number")
    return value


def _name_list(text: str) -> list[str]:
    return [x.strip() for x in text.split(",")]


def _float_list(text: str) -> list[float]:
    try:
        return [float(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {text!r}") from None


def main(argv=None) -> int:
    cap_threads()  # before numpy or jax is imported anywhere in this process
    from rl_pool.errors import Stopped, UsageError, drop_output

    args = build_parser().parse_args(argv)
    try:
        code = args.func(args)
        sys.stdout.flush()  # here, where a reader that has gone can be told apart from an error
        return code
    except UsageError as exc:
        sys.stderr.write(f"rl-pool: error: {exc}\n")
        return 2
    except BrokenPipeError:
        # The reader of our output left (`rl-pool status DIR | head`): not an error. Caught before
        # OSError, which it is one of.
        drop_output(sys.stdout)
        return 0
    except OSError as exc:
        # a path the user gave that cannot be written or read (no such directory, permissions, full disk)
        where = f" {exc.filename!r}" if exc.filename else ""
        sys.stderr.write(f"rl-pool: error: {exc.strerror or exc}{where}\n")
        return 2
    except Stopped as exc:
        sys.stderr.write(f"rl-pool: stopped by {exc}\n")
        return 128 + exc.signum
    except KeyboardInterrupt:
        sys.stderr.write("rl-pool: interrupted\n")
        return 130


if __name__ == "__main__":
    sys.exit(main())
