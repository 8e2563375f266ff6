#!/bin/bash
# Humanoid: the full observation against qpos/qvel only, four seeds, 2 cores each;
# eight 2-core screens side by side on the 16-core machine, each pool pinned with taskset.
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
S 0-1 hum-preset-s0 --preset humanoid --seed 0 &
S 2-3 hum-qpos-s0 --preset humanoid --seed 0 --env-kwargs '{"include_cinert_in_observation": false, "include_cvel_in_observation": false, "include_qfrc_actuator_in_observation": false, "include_cfrc_ext_in_observation": false}' &
S 4-5 hum-preset-s1 --preset humanoid --seed 1 &
S 6-7 hum-qpos-s1 --preset humanoid --seed 1 --env-kwargs '{"include_cinert_in_observation": false, "include_cvel_in_observation": false, "include_qfrc_actuator_in_observation": false, "include_cfrc_ext_in_observation": false}' &
S 8-9 hum-preset-s2 --preset humanoid --seed 2 &
S 10-11 hum-qpos-s2 --preset humanoid --seed 2 --env-kwargs '{"include_cinert_in_observation": false, "include_cvel_in_observation": false, "include_qfrc_actuator_in_observation": false, "include_cfrc_ext_in_observation": false}' &
S 12-13 hum-preset-s3 --preset humanoid --seed 3 &
S 14-15 hum-qpos-s3 --preset humanoid --seed 3 --env-kwargs '{"include_cinert_in_observation": false, "include_cvel_in_observation": false, "include_qfrc_actuator_in_observation": false, "include_cfrc_ext_in_observation": false}' &
wait
cd /tmp/w && for d in *; do python3 -m rl_pool status $d --csv /tmp/res/$d-history.csv > /dev/null 2>&1; cp $d/best.npz /tmp/res/$d-best.npz 2>/dev/null; done
cd /tmp/res && tar czf $OUT/humanoid.tgz * && ls -la $OUT
echo "[$SECONDS s] end"
