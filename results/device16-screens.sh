#!/bin/bash
# 2-core screens side by side on a 16-core machine, each pool pinned with taskset:
#   DUR=SECONDS bash results/device16-screens.sh LIST
# LIST holds one line per pool, "S CORES NAME launch-options... &" (e.g. results/device16-suite.list).
# Wheels of what that machine lacks (mujoco, gymnasium, tensorboardX, ...) are carried in .whl/.
SECONDS=0
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1
python3 -c "import sys,numpy,jax,jaxlib,mujoco,gymnasium,os;print({'python':sys.version.split()[0],'numpy':numpy.__version__,'jax':jax.__version__,'mujoco':mujoco.__version__,'gymnasium':gymnasium.__version__},os.cpu_count())" | tee $OUT/versions.txt
lscpu | grep -i "model name" | tee -a $OUT/versions.txt
git rev-parse HEAD 2>/dev/null | tee -a $OUT/versions.txt
mkdir -p /tmp/w /tmp/res
D=${DUR:-440}
S() { # cores name args...
  local c=$1 n=$2; shift 2
  echo "$n: $*" >> /tmp/res/commands.txt
  taskset -c $c timeout -s INT $D python3 -m rl_pool launch --pool-dir /tmp/w/$n --iterations 100000 --quiet "$@" > /tmp/res/$n.log 2>&1
  echo "[$SECONDS s] $n done rc=$?"
}
source "$1"
wait
cd /tmp/w && for d in *; do python3 -m rl_pool status $d --csv /tmp/res/$d-history.csv > /dev/null 2>&1; cp $d/best.npz /tmp/res/$d-best.npz 2>/dev/null; done
cd /tmp/res && tar czf $OUT/$(basename "$1" .list).tgz * && ls -la $OUT
echo "[$SECONDS s] end"
