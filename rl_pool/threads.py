"""Cap math libraries to one thread per process.

A pool runs N members on N cores. If every member lets OpenBLAS, MKL, OpenMP
and XLA start a thread per core, N members run N*N threads and are slower than
one member alone (the lesson of parallel robot evaluation). The caps only take
effect if they are in the environment *before* numpy or jax is imported, so
this module imports nothing heavy and entry points call :func:`cap_threads`
first thing.
"""

from __future__ import annotations

import os

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


def cap_threads(environ: dict | None = None) -> dict:
    """Put the one-thread caps into ``environ`` (default: this process's).

    Values the user already set are kept, except ``XLA_FLAGS`` which is
    extended rather than replaced. Returns the mapping it changed.
    """
    env = os.environ if environ is None else environ
    for key, value in THREAD_CAPS.items():
        if key == "XLA_FLAGS":
            current = env.get(key, "")
            if "xla_cpu_multi_thread_eigen" not in current:
                env[key] = f"{current} {value}".strip()
        else:
            env.setdefault(key, value)
    # JAX otherwise preallocates nothing on CPU, but keep it from probing GPUs.
    env.setdefault("JAX_PLATFORMS", "cpu")
    return env


def capped_environ() -> dict:
    """A copy of this process's environment with the caps applied (for children)."""
    return cap_threads(dict(os.environ))
