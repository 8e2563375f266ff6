"""REINFORCE update (Williams 1992), one jitted JAX call per batch of episodes.

For a batch of episodes padded to ``[B, T]`` the objective is

    J(w) = (1 / n) * sum_{b,t} mask[b,t] * log pi_w(u[b,t] | x[b,t]) * A[b,t]

with ``A`` the scaled advantages (returns minus baseline) and ``n`` the number
of valid steps; its gradient is the REINFORCE estimate of the policy gradient.
A policy with a value network (``--baseline value``) also descends the squared
error of that network against its targets ``y`` (the standardised return-to-go),
``J -= (1 / 2n) * sum_{b,t} mask[b,t] * (V(x[b,t], t / T) - y[b,t])^2``; the
two parts share no parameters, so each network follows its own gradient.
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

from rl_pool.maths import policy

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
    """Adam moments (unused by ``normalized``), named and shaped like the parameters, and the step count."""

    m: dict
    v: dict
    t: float


def init_opt_state(params: dict) -> OptState:
    return OptState({k: np.zeros_like(v) for k, v in params.items()},
                    {k: np.zeros_like(v) for k, v in params.items()}, 0.0)


def time_fraction(x, xp=np, limit: int | None = None):
    """``t / T`` for every step of a batch ``x`` ``[B, T', obs]`` of episodes with limit ``T``
    (``limit``; by default the batch's padded length ``T'``)."""
    return xp.broadcast_to(xp.arange(x.shape[1]) / (limit or x.shape[1]), x.shape[:2])


def values(params, x, spec: policy.PolicySpec, xp=np, limit: int | None = None):
    """The value network's outputs ``[B, T']`` on a padded batch of normalised observations."""
    return policy.value(params, x, time_fraction(x, xp, limit), spec, xp)


def value_loss(params, x, targets, mask, spec: policy.PolicySpec, limit: int | None = None, t_frac=None):
    """``(1 / 2n) * sum mask * (V - y)^2``: the value network's part of ``-J``. ``t_frac``: the steps'
    time inputs, for steps that are not laid out as a padded batch (by default from ``x`` and ``limit``)."""
    v = values(params, x, spec, jnp, limit) if t_frac is None else policy.value(params, x, t_frac, spec, jnp)
    err = v - targets
    return 0.5 * (err * err * mask).sum() / jnp.maximum(mask.sum(), 1.0)


def objective(params, x, u, adv, mask, spec: policy.PolicySpec, targets=None, limit: int | None = None):
    """Surrogate ``J`` above; ``x`` ``[B,T,obs]``, ``u`` ``[B,T,act]``, ``adv``/``mask``/``targets``
    ``[B,T]`` (``targets``: the value network's, needed when ``spec`` has one; ``limit``: the
    episodes' time limit, which the value network's time feature is a fraction of, when the batch
    is cut shorter than it)."""
    logp = policy.log_prob_unit(params, x, u, spec, xp=jnp, gammaln=gammaln)
    n = jnp.maximum(mask.sum(), 1.0)
    j = (logp * adv * mask).sum() / n
    if spec.value:
        j = j - value_loss(params, x, targets, mask, spec, limit)
    return j


policy_gradient = jax.jit(jax.grad(objective), static_argnames=("spec", "limit"))


def _adam_ascent(params, m, v, g, t, lr):
    """One Adam step up the gradient ``g`` (named arrays), bias-corrected for step count ``t``."""
    tmap = jax.tree_util.tree_map
    m = tmap(lambda m_, g_: ADAM_B1 * m_ + (1.0 - ADAM_B1) * g_, m, g)
    v = tmap(lambda v_, g_: ADAM_B2 * v_ + (1.0 - ADAM_B2) * g_ * g_, v, g)
    c1, c2 = 1.0 - ADAM_B1**t, 1.0 - ADAM_B2**t
    params = tmap(lambda p_, m_, v_: p_ + lr * (m_ / c1) / (jnp.sqrt(v_ / c2) + ADAM_EPS), params, m, v)
    return params, m, v


def _as_numpy(tree: dict) -> dict:
    return {k: np.asarray(a) for k, a in tree.items()}


@partial(jax.jit, static_argnames=("optimizer", "spec", "limit"))
def _update(params, m, v, t, x, u, adv, mask, lr, optimizer, spec, targets, limit):
    g = jax.grad(objective)(params, x, u, adv, mask, spec, targets, limit)
    leaves = jax.tree_util.tree_leaves(g)
    gnorm = jnp.sqrt(sum((leaf * leaf).sum() for leaf in leaves))
    if optimizer == "adam":
        t = t + 1.0
        params, m, v = _adam_ascent(params, m, v, g, t, lr)
    else:
        params = jax.tree_util.tree_map(lambda p_, g_: p_ + lr * g_ / (gnorm + 1e-12), params, g)
        t = t + 1.0
    return params, m, v, t, gnorm


#: A batch is cut after its longest episode, rounded up to a multiple of this (a few shapes to
#: compile, and short episodes do not pay for the padding to the limit): by the trainer before any
#: of its arithmetic, and by fit_value and policy_epochs for callers that pass whole batches
FIT_BUCKET = 100


def cut_length(mask) -> int:
    """The padded length a batch can be cut to: past its longest episode, rounded up to a multiple
    of :data:`FIT_BUCKET` (the steps after it are all padding)."""
    longest = int(np.flatnonzero(mask.any(axis=0))[-1]) + 1 if mask.any() else 1
    return min(mask.shape[1], -(-longest // FIT_BUCKET) * FIT_BUCKET)


def _ascend(params, m, v, names, objective, lr, steps, count):
    """``steps`` Adam steps up ``objective(params | q)`` of the arrays ``names`` alone (the others
    held); ``count(i)``: the step count that bias-corrects step ``i``. Inside a jitted function."""
    sub = lambda d: {k: d[k] for k in names}  # noqa: E731

    def step(i, carry):
        g = jax.grad(lambda q: objective(params | q))(carry[0])
        return _adam_ascent(*carry, g, count(i), lr)

    return jax.lax.fori_loop(0, steps, step, (sub(params), sub(m), sub(v)))


@partial(jax.jit, static_argnames=("spec", "steps", "limit"))
def _fit_value(params, m, v, t, x, targets, mask, lr, spec, steps, limit):
    names = [k for k in params if k.startswith(policy.VALUE_PREFIX)]
    # up the gradient of -loss, as the objective's step: the moments keep one sign convention
    return _ascend(params, m, v, names, lambda p: -value_loss(p, x, targets, mask, spec, limit), lr, steps,
                   lambda i: t)


def fit_value(params: dict, opt: OptState, x, targets, mask, lr: float, steps: int,
              spec: policy.PolicySpec, limit: int | None = None):
    """``steps`` more Adam steps on the value network alone, on the batch it has just stepped on
    (more passes over each batch, as PPO's value epochs); the policy's arrays, their moments and
    the step count are left as they are (the bias correction uses the count as it stands).
    ``limit``: the episodes' time limit, when the batch is already cut shorter (by default its length)."""
    if steps < 1 or not spec.value:
        return params, opt
    if opt.t < 1:
        raise ValueError("fit_value follows an update: the step count must be at least 1")
    limit = limit or mask.shape[1]
    cut = cut_length(mask)
    p, m, v = jax.device_get(_fit_value(params, opt.m, opt.v, opt.t, x[:, :cut], targets[:, :cut],
                                        mask[:, :cut], float(lr), spec, int(steps), limit))
    return params | _as_numpy(p), OptState(opt.m | _as_numpy(m), opt.v | _as_numpy(v), opt.t)


def clipped_objective(params, x, u, adv, mask, logp_old, clip, spec: policy.PolicySpec):
    """PPO's clipped surrogate (Schulman et al. 2017) on a batch drawn by the policy whose
    log-probabilities were ``logp_old``: ``(1 / n) * sum mask * min(r A, clip(r, 1 - c, 1 + c) A)``
    with ``r = pi_w(u | x) / pi_old(u | x)``. At ``w = old`` its gradient is the REINFORCE one."""
    logp = policy.log_prob_unit(params, x, u, spec, xp=jnp, gammaln=gammaln)
    ratio = jnp.exp(logp - logp_old)
    s = jnp.minimum(ratio * adv, jnp.clip(ratio, 1.0 - clip, 1.0 + clip) * adv)
    return (s * mask).sum() / jnp.maximum(mask.sum(), 1.0)


@partial(jax.jit, static_argnames=("spec", "steps"))
def _policy_epochs(params, m, v, t, x, u, adv, mask, logp_old, lr, clip, spec, steps):
    names = [k for k in params if not k.startswith(policy.VALUE_PREFIX)]
    return _ascend(params, m, v, names, lambda p: clipped_objective(p, x, u, adv, mask, logp_old, clip, spec),
                   lr, steps, lambda i: t + 1.0 + i)


def minibatch_plan(mask, size: int, passes: int, rng: np.random.Generator):
    """Which steps each minibatch step of :func:`policy_minibatches` takes: ``(order, count)``.

    Every pass draws a fresh permutation of the batch's valid steps (``mask`` ``[B, T]`` > 0, as flat
    indices ``b * T + t``) and cuts it into ``ceil(n / size)`` minibatches; the last one of a pass is
    filled up with ``B * T``, the index of a padding row. ``order`` has room for ``passes`` passes
    over a batch of full episodes (``[passes * ceil(B * T / size), size]``, one shape per batch
    layout and length, so the jitted loop compiles once for each); its first ``count`` rows are the
    steps to take."""
    mask = np.asarray(mask)
    flat = np.flatnonzero(mask.reshape(-1) > 0)
    n, pad = flat.size, mask.size
    per = -(-n // size)
    order = np.full((passes * -(-pad // size), size), pad, dtype=np.int32)
    for p in range(passes):
        block = np.full(per * size, pad, dtype=np.int32)
        block[:n] = flat[rng.permutation(n)]
        order[p * per:(p + 1) * per] = block.reshape(per, size)
    return order, passes * per


@partial(jax.jit, static_argnames=("spec",))
def _policy_minibatches(params, m, v, t, x, u, adv, mask, logp_old, order, count, lr, clip, spec):
    names = [k for k in params if not k.startswith(policy.VALUE_PREFIX)]
    sub = lambda d: {k: d[k] for k in names}  # noqa: E731

    def step(i, carry):
        idx = order[i]
        g = jax.grad(lambda q: clipped_objective(params | q, x[idx], u[idx], adv[idx], mask[idx], logp_old[idx],
                                                 clip, spec))(carry[0])
        return _adam_ascent(*carry, g, t + 1.0 + i, lr)

    return jax.lax.fori_loop(0, count, step, (sub(params), sub(m), sub(v)))


def policy_minibatches(params: dict, opt: OptState, x, u, adv, mask, logp_old, lr: float, clip: float,
                       passes: int, size: int, rng: np.random.Generator, spec: policy.PolicySpec):
    """:func:`policy_epochs` in PPO's minibatches: ``passes`` more passes over a batch the policy has
    just stepped on, each through its valid steps in a fresh random order (drawn from ``rng``),
    ``size`` steps at a time, one Adam step of the policy alone up the clipped surrogate of each
    minibatch. The step count advances by the number of minibatches; the value network's arrays and
    moments are left as they are."""
    if passes < 1:
        return params, opt
    order, count = _checked_plan("policy_minibatches", opt, mask, size, passes, rng)
    if count == 0:
        return params, opt
    flat = partial(_flat_steps, mask=mask)
    p, m, v = jax.device_get(_policy_minibatches(params, opt.m, opt.v, opt.t, flat(x), flat(u), flat(adv),
                                                 flat(mask), flat(logp_old), order, count, float(lr),
                                                 float(clip), spec))
    return (params | _as_numpy(p), OptState(opt.m | _as_numpy(m), opt.v | _as_numpy(v), opt.t + count))


def _checked_plan(caller: str, opt: OptState, mask, size: int, passes: int, rng: np.random.Generator):
    """:func:`minibatch_plan` for ``caller``, which must follow an update and take minibatches of a
    step or more."""
    if opt.t < 1:
        raise ValueError(f"{caller} follows an update: the step count must be at least 1")
    if size < 1:
        raise ValueError(f"a minibatch needs at least one step, got {size}")
    return minibatch_plan(mask, size, passes, rng)


def _flat_steps(a, mask):
    """``[B, T, ...]`` -> ``[B * T + 1, ...]``: a batch's steps in flat index order ``b * T + t``,
    then one padding row (mask 0), the row :func:`minibatch_plan` fills minibatches up with."""
    a = np.asarray(a)
    rest = a.shape[2:]
    return np.concatenate([a.reshape(mask.size, *rest), np.zeros((1, *rest), dtype=a.dtype)])


@partial(jax.jit, static_argnames=("spec",))
def _value_minibatches(params, m, v, t, x, t_frac, targets, mask, order, count, lr, spec):
    names = [k for k in params if k.startswith(policy.VALUE_PREFIX)]
    sub = lambda d: {k: d[k] for k in names}  # noqa: E731

    def step(i, carry):
        idx = order[i]  # up -loss, as :func:`fit_value`
        g = jax.grad(lambda q: -value_loss(params | q, x[idx], targets[idx], mask[idx], spec,
                                           t_frac=t_frac[idx]))(carry[0])
        return _adam_ascent(*carry, g, t, lr)

    return jax.lax.fori_loop(0, count, step, (sub(params), sub(m), sub(v)))


def value_minibatches(params: dict, opt: OptState, x, targets, mask, lr: float, passes: int, size: int,
                      rng: np.random.Generator, spec: policy.PolicySpec, limit: int | None = None):
    """:func:`fit_value` in minibatches: ``passes`` passes of the value network alone over a batch,
    each through its valid steps in a fresh random order (:func:`minibatch_plan`, drawn from
    ``rng``), ``size`` steps at a time, one Adam step down each minibatch's mean squared error
    (PPO's critic epochs). As in :func:`fit_value` the policy's arrays, their moments and the step
    count stay as they are. ``limit``: the episodes' time limit (by default the batch's length),
    which the value network's time feature is a fraction of."""
    if passes < 1 or not spec.value:
        return params, opt
    order, count = _checked_plan("value_minibatches", opt, mask, size, passes, rng)
    if count == 0:
        return params, opt
    t_frac = time_fraction(np.asarray(x), np, limit or mask.shape[1])
    p, m, v = jax.device_get(_value_minibatches(params, opt.m, opt.v, opt.t, _flat_steps(x, mask),
                                                _flat_steps(t_frac, mask), _flat_steps(targets, mask),
                                                _flat_steps(mask, mask), order, count, float(lr), spec))
    return params | _as_numpy(p), OptState(opt.m | _as_numpy(m), opt.v | _as_numpy(v), opt.t)


@partial(jax.jit, static_argnames=("spec",))
def _log_prob(params, x, u, spec):
    return policy.log_prob_unit(params, x, u, spec, xp=jnp, gammaln=gammaln)


def log_prob(params: dict, x, u, spec: policy.PolicySpec) -> np.ndarray:
    """``log pi(u | x)`` ``[B, T]`` of a padded batch (what :func:`policy_epochs` holds as the
    behaviour policy's), computed as the jitted objectives compute it."""
    return np.asarray(jax.device_get(_log_prob(params, x, u, spec)))


def policy_epochs(params: dict, opt: OptState, x, u, adv, mask, logp_old, lr: float, clip: float,
                  steps: int, spec: policy.PolicySpec):
    """``steps`` more Adam steps of the policy alone (not the value network) on a batch it has just
    stepped on, up PPO's clipped surrogate (:func:`clipped_objective`) against the policy that drew
    the batch (``logp_old``): more passes over each batch, with the ratio clipped so that the
    policy does not move far from the one whose episodes they are. The step count advances by
    ``steps``; the value network's arrays and moments are left as they are."""
    if steps < 1:
        return params, opt
    if opt.t < 1:
        raise ValueError("policy_epochs follows an update: the step count must be at least 1")
    cut = cut_length(mask)
    p, m, v = jax.device_get(_policy_epochs(params, opt.m, opt.v, opt.t, x[:, :cut], u[:, :cut],
                                            adv[:, :cut], mask[:, :cut], logp_old[:, :cut],
                                            float(lr), float(clip), spec, int(steps)))
    return (params | _as_numpy(p), OptState(opt.m | _as_numpy(m), opt.v | _as_numpy(v), opt.t + steps))


def update(params: dict, opt: OptState, x, u, adv, mask, lr: float, optimizer: str,
           spec: policy.PolicySpec, targets=None, limit: int | None = None):
    """One gradient-ascent step on a batch; returns ``(params, opt_state, grad_norm)`` as NumPy.
    ``targets``: what the value network learns (:func:`rl_pool.maths.returns.value_targets`),
    when ``spec`` has one; ``limit``: the episodes' time limit, when the batch is cut shorter
    (by default its length)."""
    if optimizer not in OPTIMIZERS:
        raise ValueError(f"unknown optimizer {optimizer!r}")
    b, t_len = mask.shape
    if x.shape[:2] != (b, t_len) or u.shape[:2] != (b, t_len) or adv.shape != (b, t_len):
        raise ValueError(f"batch shapes disagree: x {x.shape}, u {u.shape}, adv {adv.shape}, mask {mask.shape}")
    if spec.value and (targets is None or np.shape(targets) != (b, t_len)):
        raise ValueError("a policy with a value network needs its targets, shaped like the mask")
    out = _update(params, opt.m, opt.v, opt.t, x, u, adv, mask, float(lr), optimizer, spec,
                  targets if spec.value else None, int(limit or t_len))
    params, m, v, t, gnorm = jax.device_get(out)
    return _as_numpy(params), OptState(_as_numpy(m), _as_numpy(v), float(t)), float(gnorm)
