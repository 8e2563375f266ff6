"""Cap math libraries to one thread per process, and to SIMD code every x86-64-v3 CPU runs alike.

A pool runs N members on N cores. If every member lets OpenBLAS, MKL, OpenMP
and XLA start a thread per core, N members run N*N threads and are slower than
one member alone (the lesson of parallel robot evaluation).

numpy picks its SIMD kernels (exp, log, tanh, ...) and OpenBLAS its matrix
kernels by the CPU they run on, and kernels for other instruction sets round
differently: the same pool, seed and versions gives another history on an
AVX-512 CPU than on an AVX2 one. Capping numpy's dispatch and XLA's code
generation at x86-64-v3 (AVX2 and FMA, which x86 machines of the last decade
have) and pinning OpenBLAS to its AVX2 ("Haswell") kernels makes every such CPU
compute the same bits (measured in docs/reproducibility.md). ``RL_POOL_NATIVE_SIMD=1``
lets them use all of the CPU; a value of your own for any of these variables is
kept; a CPU without AVX2 runs natively.

All of this only takes effect if it is in the environment *before* numpy or
jax is imported, so this module imports nothing heavy and entry points call
:func:`cap_threads` first thing.
"""

from __future__ import annotations

import functools
import os
import platform

#: Environment variables that bound the thread pools of the math libraries.
THREAD_CAPS = {
    "OMP_NUM_THREADS": "1",
    "OPENBLAS_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
    "VECLIB_MAXIMUM_THREADS": "1",
    "NUMEXPR_NUM_THREADS": "1",
    # XLA's own thread pool has no flag; this keeps its Eigen kernels single-threaded.
    "XLA_FLAGS": "--xla_cpu_multi_thread_eigen=false",
}


#: numpy's dispatch targets above x86-64-v3: numpy 2.4's group and the names numpy 1.26 used
#: (a name a numpy does not know is ignored).
NPY_ABOVE_V3 = ("X86_V4 AVX512F AVX512CD AVX512_KNL AVX512_KNM AVX512_SKX AVX512_CLX AVX512_CNL "
                "AVX512_ICL AVX512_SPR")
#: The same numbers on every x86-64-v3 CPU: numpy's dispatch, OpenBLAS's kernels (numpy's wheels
#: build it for every CPU and pick at start-up) and MKL's code path where numpy uses MKL.
PORTABLE_SIMD = {"NPY_DISABLE_CPU_FEATURES": NPY_ABOVE_V3, "OPENBLAS_CORETYPE": "Haswell", "MKL_CBWR": "AVX2"}
#: The most XLA's CPU code generation may use.
XLA_MAX_ISA = "--xla_cpu_max_isa=AVX2"
#: Every variable this module may set, for callers that set them for a while and restore them.
VARIABLES = (*THREAD_CAPS, *PORTABLE_SIMD, "JAX_PLATFORMS")


#: What x86-64-v3 code needs of a CPU, as /proc/cpuinfo names it.
V3_FLAGS = frozenset({"avx", "avx2", "fma", "f16c", "bmi1", "bmi2", "movbe"})


def is_x86_64() -> bool:
    return platform.machine().lower() in ("x86_64", "amd64")


@functools.lru_cache(maxsize=1)
def cpu_runs_v3() -> bool:
    """Whether this CPU runs x86-64-v3 code (AVX2, FMA, ...): read from /proc/cpuinfo (Linux); False
    where it cannot be read or the machine is not x86-64. Forcing AVX2 kernels on a CPU without AVX2
    would stop the process with an illegal instruction."""
    if not is_x86_64():
        return False
    try:
        with open("/proc/cpuinfo", encoding="ascii", errors="replace") as fh:  # not a pool file
            for line in fh:
                if line.startswith("flags"):
                    return set(line.partition(":")[2].split()) >= V3_FLAGS
    except OSError:
        pass
    return False


def native_requested(environ) -> bool:
    """``RL_POOL_NATIVE_SIMD`` set to 1, true, yes or on."""
    return environ.get("RL_POOL_NATIVE_SIMD", "").strip().lower() in ("1", "true", "yes", "on")


def portable_simd(environ) -> bool:
    """Whether processes started with ``environ`` hold numpy, OpenBLAS and XLA to x86-64-v3 code:
    on x86-64 CPUs that run it, unless ``RL_POOL_NATIVE_SIMD`` asks for all of the CPU."""
    return cpu_runs_v3() and not native_requested(environ)


def cap_threads(environ: dict | None = None) -> dict:
    """Put the one-thread caps and, where :func:`portable_simd`, the portable SIMD level into
    ``environ`` (default: this process's).

    Values the user already set are kept, except ``XLA_FLAGS`` which is
    extended rather than replaced. Returns the mapping it changed.
    """
    env = os.environ if environ is None else environ
    portable = portable_simd(env)
    for key, value in THREAD_CAPS.items():
        if key == "XLA_FLAGS":
            current = env.get(key, "")
            if "xla_cpu_multi_thread_eigen" not in current:
                current = f"{current} {value}".strip()
            if portable and "xla_cpu_max_isa" not in current:
                current = f"{current} {XLA_MAX_ISA}"
            env[key] = current
        else:
            env.setdefault(key, value)
    if portable:
        for key, value in PORTABLE_SIMD.items():
            env.setdefault(key, value)
    # JAX otherwise preallocates nothing on CPU, but keep it from probing GPUs.
    env.setdefault("JAX_PLATFORMS", "cpu")
    return env


def capped_environ() -> dict:
    """A copy of this process's environment with the caps applied (for children)."""
    return cap_threads(dict(os.environ))
