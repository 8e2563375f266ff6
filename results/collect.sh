#!/usr/bin/env bash
# Export a finished (or stopped) pool into results/<task>/: history, plot, best agent, config,
# versions and a fresh-episode re-score (50 episodes on seeds the pool never trained or evaluated on).
#   results/collect.sh POOL_DIR TASK "the command that made the pool"
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
"$HERE/.venv/bin/python" - "$OUT" <<'PY' > "$OUT/versions.txt"
import platform, sys
from importlib.metadata import version
print("python", platform.python_version())
for p in ("numpy", "jax", "jaxlib", "mujoco", "gymnasium", "rl-pool"):
    print(p, version(p))
PY
{ echo "# $(date -u +%F): made on the 2-core development machine with the versions in versions.txt"; echo "$CMD";
  echo "# exported with:"; echo "results/collect.sh $POOL $TASK '...'"; } > "$OUT/command.txt"
echo "$OUT: $(python3 -c "import json,sys; d=json.load(open('$OUT/rescore.json')); print(f\"re-score {d['mean_return']:.1f} ± {d['std_return']:.1f} over {d['episodes']} episodes\")")"
