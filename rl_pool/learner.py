"""REINFORCE update (Williams 1992), one jitted JAX call per batch of episodes.

For a batch of episodes padded to ``[B, T]`` the objective is

    J(w) = (1 / n) * sum_{b,t} mask[b,t] * log pi_w(u[b,t] | x[b,t]) * A[b,t]

with ``A`` the scaled advantages (returns minus baseline) and ``n`` the number
of valid steps; its gradient is the REINFORCE estimate of the policy gradient.
The whole batch goes through JAX in one call: rollouts stay in NumPy, and JAX
never sees a single environment step.

Step-size rules ("optimizer", pool-wide):

* ``adam``: Adam (Kingma & Ba 2015) on the ascent direction; its moments are
  part of the agent and travel with it through the pool.
* ``normalized``: ``w += lr * g / ||g||``, a fixed-length step.
"""

from __future__ import annotations

import os
from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.special import gammaln

from . import policy

jax.config.update("jax_enable_x64", True)

ADAM_B1 = 0.9
ADAM_B2 = 0.999
ADAM_EPS = 1e-8
OPTIMIZERS = ("adam", "normalized")


def enable_compilation_cache() -> None:
    """Keep compiled XLA programs on disk so each new member skips recompiling.

    ``RL_POOL_JAX_CACHE`` overrides the location; an empty value disables it.
    """
    path = os.environ.get("RL_POOL_JAX_CACHE")
    if path is None:
        base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
        path = os.path.join(base, "rl-pool", "jax")
    if not path:
        return
    try:
        os.makedirs(path, exist_ok=True)
    except OSError:
        return
    jax.config.update("jax_compilation_cache_dir", path)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)


class OptState(NamedTuple):
    """Adam moments (unused by ``normalized``), same shape as the weights, and the step count."""

    m: np.ndarray
    v: np.ndarray
    t: float


def init_opt_state(w: np.ndarray) -> OptState:
    return OptState(np.zeros_like(w), np.zeros_like(w), 0.0)


def objective(w, x, u, adv, mask, kind="linear"):
    """Surrogate ``J(w)`` above; ``x`` ``[B,T,obs]``, ``u`` ``[B,T,act]``, ``adv``/``mask`` ``[B,T]``."""
    logp = policy.log_prob_unit(w, x, u, xp=jnp, gammaln=gammaln, policy=kind)
    n = jnp.maximum(mask.sum(), 1.0)
    return (logp * adv * mask).sum() / n


policy_gradient = jax.jit(jax.grad(objective), static_argnames=("kind",))


@partial(jax.jit, static_argnames=("optimizer", "kind"))
def _update(w, m, v, t, x, u, adv, mask, lr, optimizer, kind):
    g = jax.grad(objective)(w, x, u, adv, mask, kind)
    gnorm = jnp.sqrt((g * g).sum())
    if optimizer == "adam":
        t = t + 1.0
        m = ADAM_B1 * m + (1.0 - ADAM_B1) * g
        v = ADAM_B2 * v + (1.0 - ADAM_B2) * g * g
        m_hat = m / (1.0 - ADAM_B1**t)
        v_hat = v / (1.0 - ADAM_B2**t)
        w = w + lr * m_hat / (jnp.sqrt(v_hat) + ADAM_EPS)
    else:
        w = w + lr * g / (gnorm + 1e-12)
        t = t + 1.0
    return w, m, v, t, gnorm


def update(w, opt: OptState, x, u, adv, mask, lr: float, optimizer: str, kind: str = "linear"):
    """One gradient-ascent step on a batch; returns ``(w, opt_state, grad_norm)`` as NumPy."""
    if optimizer not in OPTIMIZERS:
        raise ValueError(f"unknown optimizer {optimizer!r}")
    b, t_len = mask.shape
    if x.shape[:2] != (b, t_len) or u.shape[:2] != (b, t_len) or adv.shape != (b, t_len):
        raise ValueError(f"batch shapes disagree: x {x.shape}, u {u.shape}, adv {adv.shape}, mask {mask.shape}")
    out = _update(w, opt.m, opt.v, opt.t, x, u, adv, mask, float(lr), optimizer, kind)
    w, m, v, t, gnorm = jax.device_get(out)
    return np.asarray(w), OptState(np.asarray(m), np.asarray(v), float(t)), float(gnorm)
