"""Reproducible installs and recorded versions: the lock, shell/setup.sh, versions in pool.json and status."""

import json
import os
import re
import shutil
import subprocess
import sys
from importlib import metadata

import pytest

from rl_pool import fsutil, versions
from rl_pool.commands import status

from .conftest import ROOT, rl_pool
from .helpers import make_pool, sign

LOCK = os.path.join(ROOT, "constraints.txt")
SETUP = os.path.join(ROOT, "shell", "setup.sh")


def _pins(lines) -> dict[str, str]:
    out = {}
    for ln in lines:
        ln = ln.strip()
        if ln and not ln.startswith("#"):
            name, _, version = ln.partition("==")
            out[re.sub(r"[-_.]+", "-", name).lower()] = version
    return out


def test_versions_names_what_decides_a_result():
    v = versions.versions()
    assert list(v)[:2] == ["python", "rl-pool"]
    assert {"numpy", "jax", "mujoco", "gymnasium"} <= set(v)
    assert v["numpy"] == metadata.version("numpy") and v["rl-pool"] == metadata.version("rl-pool")
    assert v["python"] == ".".join(map(str, sys.version_info[:3]))


@pytest.mark.skipif(not versions.threads.cpu_runs_v3(), reason="the portable level needs an x86-64-v3 CPU")
def test_members_get_the_portable_simd_level_unless_told_otherwise():
    from rl_pool import threads

    env = threads.cap_threads({"XLA_FLAGS": "--xla_dump_to=/tmp/x"})
    assert env["NPY_DISABLE_CPU_FEATURES"].split()[0] == "X86_V4" and env["OPENBLAS_CORETYPE"] == "Haswell"
    assert env["XLA_FLAGS"].split() == ["--xla_dump_to=/tmp/x", "--xla_cpu_multi_thread_eigen=false",
                                        "--xla_cpu_max_isa=AVX2"]
    assert threads.cap_threads(dict(env)) == env  # applying it twice changes nothing
    assert versions.simd(env) == "x86-64-v3"
    for yes in ("1", "true", "YES"):
        native = threads.cap_threads({"RL_POOL_NATIVE_SIMD": yes})
        assert not set(threads.PORTABLE_SIMD) & set(native) and "max_isa" not in native["XLA_FLAGS"]
        assert versions.simd(native) == "native"
    assert threads.cap_threads({"RL_POOL_NATIVE_SIMD": "0"})["OPENBLAS_CORETYPE"] == "Haswell"
    own = threads.cap_threads({"OPENBLAS_CORETYPE": "SkylakeX"})  # a user's own choice is kept
    assert own["OPENBLAS_CORETYPE"] == "SkylakeX" and versions.simd(own) == "custom"
    # What a process started like a member really runs: numpy's dispatch stops at x86-64-v3 (on a
    # CPU with AVX-512 it would use it otherwise) and OpenBLAS says it took its Haswell kernels.
    code = ("import numpy as np; from numpy._core._multiarray_umath import __cpu_features__ as f; "
            "np.ones((8, 8)) @ np.ones((8, 8)); "
            "print(int(any(f.get(k) for k in ('X86_V4', 'AVX512_SKX', 'AVX512_ICL'))))")
    clean = {k: v for k, v in os.environ.items() if k not in (*threads.VARIABLES, "RL_POOL_NATIVE_SIMD")}
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                          env=threads.cap_threads(clean | {"OPENBLAS_VERBOSE": "2"}))
    assert proc.stdout.strip() == "0" and "Core: Haswell" in proc.stderr, proc.stderr


def test_status_shows_the_versions_recorded_in_pool_json(tmp_path):
    paths, _ = make_pool(tmp_path / "p")
    doc = json.loads(open(paths.pool_json).read())
    recorded = json.loads(rl_pool("status", paths.root, "--json", check=0).stdout)["versions"]
    assert recorded == doc.get("versions")  # what pool.json says (None for a pool made before versions)
    recorded = versions.versions() | {"jax": "0.0.1\x1b[31m"}  # a pool made elsewhere, and a hostile string
    fsutil.write_json(paths.pool_json, sign(paths, doc | {"versions": recorded}))
    st = json.loads(rl_pool("status", paths.root, "--json", check=0).stdout)
    assert st["versions"] == recorded
    table = rl_pool("status", paths.root, check=0).stdout
    line = next(ln for ln in table.splitlines() if ln.startswith("versions:"))
    assert f"python {recorded['python']}" in line and f"numpy {recorded['numpy']}" in line
    assert "jax 0.0.1?[31m" in line and "\x1b" not in table  # printable only
    here = next(ln for ln in table.splitlines() if "installed here" in ln)
    assert f"jax {metadata.version('jax')}" in here and "numpy" not in here
    assert status.recorded_versions({"versions": "3.11"}) is None
    doc.pop("versions", None)
    fsutil.write_json(paths.pool_json, sign(paths, doc))
    assert json.loads(rl_pool("status", paths.root, "--json", check=0).stdout)["versions"] is None
    assert "versions:" not in rl_pool("status", paths.root, check=0).stdout


def test_the_lock_pins_every_installed_dependency_exactly():
    pins = _pins(open(LOCK))
    assert "rl-pool" not in pins and all(re.fullmatch(r"[\w.+!-]+", v) for v in pins.values())
    for name in ("numpy", "jax", "jaxlib", "mujoco", "gymnasium", "filelock", "matplotlib", "rich",
                 "tensorboardx", "tensorboard", "pytest", "scipy", "ruff"):
        assert pins.get(name) == metadata.version(name), name


def _venv(path):
    subprocess.run([sys.executable, "-m", "venv", str(path)], check=True, capture_output=True, timeout=300)


def test_setup_shows_pip_output_only_when_it_fails(tmp_path):
    """A lock that cannot be satisfied: setup stops with pip's own words and a hint, exit 1."""
    venv = tmp_path / "venv"
    _venv(venv)
    lock = tmp_path / "lock.txt"
    lock.write_text("numpy==0.0.0.1\n")
    env = dict(os.environ, RL_POOL_VENV=str(venv), RL_POOL_LOCK=str(lock), PIP_NO_INDEX="1",
               PIP_FIND_LINKS=str(tmp_path))  # nothing to find: fails at once, offline
    p = subprocess.run(["bash", "-c", f'source "{SETUP}" && echo sourced'], capture_output=True, text=True,
                       env=env, timeout=600)
    assert p.returncode == 1 and "sourced" not in p.stdout
    assert p.stdout == ""
    err = p.stderr.splitlines()
    assert err[0].startswith("setup: installing rl-pool and its dependencies (locked versions)")
    assert any("ERROR" in ln for ln in err[1:-1])  # pip's own output, shown because it failed
    assert err[-1].startswith("setup: pip failed (its output is above)") and "RL_POOL_UNLOCKED=1" in err[-1]
    assert not (venv / ".rl-pool-installed").exists()


def _index_reachable() -> str | None:
    try:
        p = subprocess.run([sys.executable, "-m", "pip", "index", "versions", "pip"], capture_output=True,
                           text=True, timeout=60)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return f"pip could not ask the package index ({exc})"
    if p.returncode != 0:
        return "the package index cannot be reached: " + (p.stderr.strip().splitlines() or ["?"])[-1]
    return None


@pytest.mark.setup
def test_setup_from_the_lock_installs_exactly_the_locked_versions(tmp_path):
    why = _index_reachable()
    if why:
        pytest.skip(why)
    if shutil.which("python3") is None:
        pytest.skip("no python3 on PATH for shell/setup.sh")
    venv = tmp_path / "venv"
    env = dict(os.environ, RL_POOL_VENV=str(venv), PYTHON=sys.executable)
    p = subprocess.run(["bash", "-c", f'source "{SETUP}" && command -v rl-pool'], capture_output=True,
                       text=True, env=env, timeout=900)
    assert p.returncode == 0, p.stderr
    # quiet: one line saying what it does, nothing from pip
    assert p.stderr.strip().splitlines() == [
        f"setup: installing rl-pool and its dependencies (locked versions) into {venv}; the first time takes a minute"]
    assert p.stdout.strip() == str(venv / "bin" / "rl-pool")
    freeze = subprocess.run([str(venv / "bin" / "python"), "-m", "pip", "freeze", "--exclude-editable"],
                            capture_output=True, text=True, check=True).stdout.splitlines()
    installed, locked = _pins(freeze), _pins(open(LOCK))
    assert {k: v for k, v in installed.items() if locked.get(k) != v} == {}  # every package at its pin
    # the lock may pin more than rl-pool needs (tools installed beside it), never less
    assert {"numpy", "jax", "mujoco", "gymnasium", "rich", "tensorboardx", "tensorboard"} <= set(installed)
    # a second run does nothing and says nothing
    again = subprocess.run(["bash", "-c", f'source "{SETUP}"'], capture_output=True, text=True, env=env,
                           timeout=300)
    assert again.returncode == 0 and again.stderr == "" and again.stdout == ""
    out = subprocess.run([str(venv / "bin" / "rl-pool"), "status", "--help"], capture_output=True, text=True)
    assert out.returncode == 0 and "--watch" in out.stdout


def test_making_envs_is_quiet_and_leaves_no_mujoco_log(tmp_path):
    """MuJoCo warns on every load of HalfCheetah's XML (a deprecated compiler attribute) and writes
    MUJOCO_LOG.TXT into the working directory; rl-pool routes that to its log at debug level."""
    code = ("from rl_pool.learning import envs\n"
            "for e in ('HalfCheetah-v5', 'HalfCheetah-v5'): envs.make(e)[0].close()\n")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path, timeout=300,
                       env=dict(os.environ, PYTHONPATH=ROOT))
    assert p.returncode == 0, p.stderr
    assert p.stdout == "" and p.stderr == ""
    assert os.listdir(tmp_path) == []
    # a warning that matters (an unstable simulation) is still said, once per kind
    code = ("import math, mujoco\nfrom rl_pool.learning import envs\nenvs.quiet_mujoco_warnings()\n"
            "m = mujoco.MjModel.from_xml_string('<mujoco><worldbody><body><freejoint/><geom size=\".1\"/>"
            "</body></worldbody></mujoco>')\nd = mujoco.MjData(m)\n"
            "for _ in range(3):\n    mujoco.mj_resetData(m, d); d.qpos[0] = math.nan; mujoco.mj_step(m, d)\n")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path, timeout=300,
                       env=dict(os.environ, PYTHONPATH=ROOT))
    assert p.returncode == 0, p.stderr
    assert p.stderr.count("MuJoCo: Nan, Inf or huge value in QPOS") == 1
    assert os.listdir(tmp_path) == []
