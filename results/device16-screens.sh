#!/bin/bash
# Eight 2-core screens side by side on the 16-core machine, each pool pinned with taskset.
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
S 0-1 w2-g99gae-s1 --preset walker2d --seed 1 --gamma 0.99 --baseline linear --gae-lambda 0.95 &
S 2-3 w2-g99gae-s2 --preset walker2d --seed 2 --gamma 0.99 --baseline linear --gae-lambda 0.95 &
S 4-5 w8-merge-s0 --preset walker2d --seed 0 --pool-size 8 --selection parent --merge momentum --batch-episodes 10 --parent-patience 3 &
S 6-7 w8-merge-g99gae-s0 --preset walker2d --seed 0 --pool-size 8 --selection parent --merge momentum --batch-episodes 10 --parent-patience 3 --gamma 0.99 --baseline linear --gae-lambda 0.95 &
S 8-9 ant8-merge-s0 --preset ant --seed 0 --pool-size 8 --merge momentum --batch-episodes 5 --parent-patience 3 &
S 10-11 hum8-merge-s0 --preset humanoid --seed 0 --pool-size 8 --selection parent --merge momentum --batch-episodes 10 --parent-patience 3 &
S 12-13 push8-merge-s0 --preset pusher --seed 0 --pool-size 8 --merge momentum --batch-episodes 25 --parent-patience 3 &
S 14-15 idp8-merge-s0 --preset inverted-double-pendulum --seed 0 --pool-size 8 --merge momentum --batch-episodes 5 --parent-patience 3 &
wait
cd /tmp/w && for d in *; do python3 -m rl_pool status $d --csv /tmp/res/$d-history.csv > /dev/null 2>&1; cp $d/best.npz /tmp/res/$d-best.npz 2>/dev/null; done
cd /tmp/res && tar czf $OUT/screens.tgz * && ls -la $OUT
echo "[$SECONDS s] end"
