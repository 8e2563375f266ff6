#!/usr/bin/env bash
# Export a finished (or stopped) pool into results/<task>/: history, plot, best agent, config,
# versions and a fresh-episode re-score (50 episodes on seeds the pool never trained or evaluated on),
# of best.npz and of picked.npz (`rl-pool pick`: the top 20 selected agents and the last one on 20
# held-out episodes, seeds 2000000+k; then re-scored on the same 50 episodes as best.npz).
#   results/collect.sh POOL_DIR TASK "the command that made the pool"
#   PICK_OPTS="--finalists 6"   further `rl-pool pick` options (a preset's final round)
set -euo pipefail
POOL="$1"; TASK="$2"; CMD="$3"
HERE="$(cd "$(dirname "$0")/.." && pwd)"
RL="${RL_POOL:-$HERE/.venv/bin/rl-pool}"
OUT="$HERE/results/$TASK"
mkdir -p "$OUT"
"$RL" status "$POOL" --csv "$OUT/history.csv" > /dev/null
"$RL" plot "$POOL" --out "$OUT/progress.png" > /dev/null
cp "$POOL/best.npz" "$OUT/best.npz"
cp "$POOL/best.json" "$POOL/pool.json" "$OUT/"
"$RL" evaluate "$OUT/best.npz" --episodes 50 --workers 2 --json > "$OUT/rescore.json"
# shellcheck disable=SC2086  # PICK_OPTS is a list of options
"$RL" pick "$POOL" --top 20 --episodes 20 ${PICK_OPTS:-} --workers 2 --out "$OUT/picked.npz" > /dev/null
"$RL" evaluate "$OUT/picked.npz" --episodes 50 --workers 2 --json > "$OUT/rescore-picked.json"
"$HERE/.venv/bin/python" - "$OUT" <<'PY' > "$OUT/versions.txt"
import platform, sys
from importlib.metadata import version
print("python", platform.python_version())
for p in ("numpy", "jax", "jaxlib", "mujoco", "gymnasium", "rl-pool"):
    print(p, version(p))
PY
{ echo "# $(date -u +%F): made on the 2-core development machine with the versions in versions.txt"; echo "$CMD";
  echo "# exported with:"; echo "${PICK_OPTS:+PICK_OPTS=\"$PICK_OPTS\" }results/collect.sh $POOL $TASK '...'"; } > "$OUT/command.txt"
"$HERE/.venv/bin/python" - "$OUT" "$TASK" "$CMD" <<'PY'
import csv, json, sys
out, task, cmd = sys.argv[1:4]
rows = list(csv.DictReader(open(f"{out}/history.csv")))
res = json.load(open(f"{out}/rescore.json"))
pool = json.load(open(f"{out}/pool.json"))
best = json.load(open(f"{out}/best.json"))
picked = json.load(open(f"{out}/picked.json"))
res_p = json.load(open(f"{out}/rescore-picked.json"))
def f(x):  # Reacher's returns are a few units: two decimals there
    return f"{x:.2f}" if abs(x) < 100 else f"{x:.1f}"
def at(minutes):
    b, steps = None, None
    for r in rows:
        if r["elapsed_seconds"] and float(r["elapsed_seconds"]) <= 60 * minutes and r["eval_return"]:
            v = float(r["eval_return"])
            if b is None or v > b:
                b = v
            steps = int(r["env_steps"])
    return ("—", "—") if b is None else (f(b), f"{steps / 1e6:.2f} M")
end = float(rows[-1]["elapsed_seconds"])
cols = [m for m in (5, 10, 20) if m * 60 <= end + 30]
wins = {}
for r in rows:
    wins[r["winner"]] = wins.get(r["winner"], 0) + 1
vers = open(f"{out}/versions.txt").read().strip().replace("\n", ", ")
lines = [f"# {pool['env']}: {task}", "",
         "Everything here comes from one real run on the 2-core development machine (one root seed,",
         f"seed {pool['seed']}); nothing was edited by hand. Versions: {vers}.", "",
         "Command (see command.txt):", "", "```", cmd, "```", "",
         f"| best selected return ({pool['eval_episodes']} deterministic evaluation episodes) by | " + " | ".join(f"{m} min" for m in cols) + " |",
         "|---|" + "---|" * len(cols),
         "| return | " + " | ".join(at(m)[0] for m in cols) + " |",
         "| env steps so far (all members, training + evaluation) | " + " | ".join(at(m)[1] for m in cols) + " |", "",
         f"The run was stopped after {end / 60:.1f} minutes ({len(rows)} iterations; winners: "
         + ", ".join(f"{k} {v}" for k, v in sorted(wins.items())) + ").",
         f"`best.npz` is the best selected agent (iteration {best['iteration']}, evaluation return "
         f"{f(best['eval_return'])}); re-scored on {res['episodes']} fresh episodes (reset seeds 1000000+k, "
         f"deterministic Beta mean): **{f(res['mean_return'])} ± {f(res['std_return'])}** "
         f"(min {f(min(res['returns']))}, max {f(max(res['returns']))}).", "",
         f"`picked.npz` (`rl-pool pick --top 20 --episodes 20`: {len(picked['candidates'])} of the "
         f"{picked['distinct_agents']} distinct selected agents on the same 20 held-out episodes, reset seeds "
         f"{picked['seed']}+k"
         + (f"; its {picked['finalists']} best then played {picked['final_episodes']} more, `--finalists "
            f"{picked['finalists']} --final-episodes {picked['final_episodes']}`" if picked.get("finalists") else "")
         + f") is the agent of iteration {picked['picked']['iteration']} (held-out mean "
         f"{f(picked['picked']['mean_return'])}); re-scored on the same 50 fresh episodes: "
         f"**{f(res_p['mean_return'])} ± {f(res_p['std_return'])}** (min {f(min(res_p['returns']))}, "
         f"max {f(max(res_p['returns']))}).", "",
         "Files: `history.csv` (per iteration: winner, returns, wall time, env steps), `progress.png`",
         "(`rl-pool plot`), `best.npz`/`best.json`, `pool.json` (the exact pool config and versions),",
         "`rescore.json` (`rl-pool evaluate --episodes 50 --json`), `picked.npz`/`picked.json` (`rl-pool pick`),",
         "`rescore-picked.json`, `versions.txt`, `command.txt`."]
open(f"{out}/README.md", "w").write("\n".join(lines) + "\n")
PY
echo "$OUT: $(python3 -c "import json,sys; d=json.load(open('$OUT/rescore.json')); print(f\"re-score {d['mean_return']:.1f} ± {d['std_return']:.1f} over {d['episodes']} episodes\")"); picked: $(python3 -c "import json,sys; d=json.load(open('$OUT/rescore-picked.json')); print(f\"{d['mean_return']:.1f} ± {d['std_return']:.1f}\")")"
