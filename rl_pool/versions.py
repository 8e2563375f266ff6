"""The versions of what a pool runs on, for ``pool.json`` and ``rl-pool status``.

Read from the installed distributions' metadata, so nothing heavy (jax,
mujoco) is imported to learn its version.
"""

from __future__ import annotations

import os
import platform
import sys
from importlib import metadata

from rl_pool import threads

#: Distributions whose versions decide what a pool computes, in display order.
PACKAGES = ("rl-pool", "numpy", "jax", "jaxlib", "mujoco", "gymnasium")


def versions() -> dict[str, str | None]:
    """``{"python": "3.11.7", "rl-pool": "0.1.0", "numpy": ..., ..., "simd": "x86-64-v3"}``; None for
    a package not installed. ``simd``: the SIMD code numpy and XLA may use in this process, which
    decides the last bits as the versions do (:mod:`rl_pool.threads`)."""
    out: dict[str, str | None] = {"python": platform.python_version()}
    for name in PACKAGES:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = None
    out["simd"] = simd(os.environ)
    return out


def simd(environ) -> str:
    """``x86-64-v3`` (rl-pool's portable level), ``native`` (all the CPU has), ``custom`` (values of
    the user's own, or numpy loaded before they were set), ``below-x86-64-v3`` (a CPU without AVX2,
    run natively) or the machine (not x86-64)."""
    if not threads.is_x86_64():
        return platform.machine().lower() or "unknown"
    if not threads.cpu_runs_v3():
        return "below-x86-64-v3"
    xla = environ.get("XLA_FLAGS", "").split()
    if all(environ.get(k) == v for k, v in threads.PORTABLE_SIMD.items()) and threads.XLA_MAX_ISA in xla:
        return "custom" if _numpy_dispatches_avx512() else "x86-64-v3"
    if not any(environ.get(k) for k in threads.PORTABLE_SIMD) and not any("xla_cpu_max_isa" in f for f in xla):
        return "native"
    return "custom"


def _numpy_dispatches_avx512() -> bool:
    """Whether numpy, if this process has loaded it, runs its AVX-512 kernels (the environment is
    read when numpy loads: set later, it changes nothing in this process)."""
    if "numpy" not in sys.modules:
        return False
    try:
        from numpy._core._multiarray_umath import __cpu_features__ as features
    except ImportError:  # numpy 1.x
        from numpy.core._multiarray_umath import __cpu_features__ as features
    return any(features.get(k) for k in ("X86_V4", "AVX512_SKX", "AVX512_ICL", "AVX512_SPR"))


def differences(recorded: dict, current: dict | None = None) -> dict[str, tuple]:
    """``{name: (recorded, current)}`` for every recorded version that differs from this installation."""
    current = versions() if current is None else current
    return {k: (v, current.get(k)) for k, v in recorded.items()
            if isinstance(k, str) and k in current and v != current.get(k)}


def format_versions(v: dict) -> str:
    """``python 3.11.7, rl-pool 0.1.0, numpy 2.4.6, ...`` (names and values made printable)."""
    return ", ".join(f"{_text(k)} {_text(x) if x is not None else '-'}" for k, x in v.items())


def _text(x) -> str:
    # a pool file is not trusted: keep whatever it holds on one short printable line
    s = str(x)
    return "".join(c if c.isprintable() else "?" for c in s)[:40]
