"""Beta policy: one Beta distribution per action dimension (pure functions).

Features ``phi = [x, 1]`` for a normalised observation ``x``; parameters are a
matrix ``w`` of shape ``[obs_dim + 1, 2 * act_dim]`` and

    alpha_j = softplus(phi . w[:, j]) + 1,   beta_j = softplus(phi . w[:, A + j]) + 1.

Shapes >= 1 keep every Beta unimodal (no mass piling up at the bounds).

Policy ``linear-exp`` replaces ``softplus`` by ``exp`` (clamped at ``Z_MAX``):
shapes >= 1 still, but a linear step in ``z`` scales the shape multiplicatively,
so a policy can become sharp, or push its mean close to an action bound, in a
few steps instead of hundreds (on Swimmer the softplus link stalls with mean
actions capped near 0.9 of the bound; see results/). A
sample ``u`` in (0, 1) maps to the action ``low + u * (high - low)``; the
policy was introduced for bounded control by Chou, Maturana & Scherer (2017).

Functions take an array module ``xp`` (numpy or jax.numpy) so that the same
maths serves the NumPy rollouts and the JAX gradient.
"""

from __future__ import annotations

import math

import numpy as np

#: Samples are clipped to [EPS, 1 - EPS] before any log: a float Beta draw can be exactly 0 or 1.
EPS = 1e-6

_lgamma = np.vectorize(math.lgamma, otypes=[np.float64])

POLICIES = ("linear", "linear-exp")
#: ``linear-exp`` clamps the pre-activation here: shapes stay below 1 + e^10 ~ 22000.
Z_MAX = 10.0


def n_features(obs_dim: int) -> int:
    return obs_dim + 1


def init_params(obs_dim: int, act_dim: int) -> np.ndarray:
    """Zero weights: alpha = beta = softplus(0) + 1 ~ 1.69, a broad bump centred on the middle."""
    return np.zeros((n_features(obs_dim), 2 * act_dim))


def softplus(z, xp=np):
    return xp.logaddexp(0.0, z)


def shapes(z, policy: str = "linear", xp=np):
    """The link from pre-activations to Beta shapes, both >= 1."""
    if policy == "linear-exp":
        return xp.exp(xp.minimum(z, Z_MAX)) + 1.0
    return softplus(z, xp) + 1.0


def beta_params(w, x, xp=np, policy: str = "linear"):
    """``(alpha, beta)`` for normalised observations ``x`` ``[..., obs_dim]``; each ``[..., act_dim]``."""
    act_dim = w.shape[1] // 2
    ab = shapes(x @ w[:-1] + w[-1], policy, xp)
    return ab[..., :act_dim], ab[..., act_dim:]


def clip_unit(u, xp=np):
    return xp.clip(u, EPS, 1.0 - EPS)


def beta_log_prob(u, alpha, beta, xp=np, gammaln=None):
    """Elementwise ``log Beta(u; alpha, beta)`` with ``u`` clipped into the open interval."""
    if gammaln is None:
        gammaln = _lgamma
    u = clip_unit(u, xp)
    log_norm = gammaln(alpha) + gammaln(beta) - gammaln(alpha + beta)
    return (alpha - 1.0) * xp.log(u) + (beta - 1.0) * xp.log1p(-u) - log_norm


def log_prob_unit(w, x, u, xp=np, gammaln=None, policy: str = "linear"):
    """``sum_j log Beta(u_j; alpha_j, beta_j)`` for samples ``u`` in (0, 1); shape ``[...]``."""
    alpha, beta = beta_params(w, x, xp, policy)
    return beta_log_prob(u, alpha, beta, xp, gammaln).sum(axis=-1)


def sample_unit(rng: np.random.Generator, alpha: np.ndarray, beta: np.ndarray) -> np.ndarray:
    """Draw ``u ~ Beta(alpha, beta)`` and clip it into [EPS, 1 - EPS]."""
    return clip_unit(rng.beta(alpha, beta))


def mean_unit(alpha: np.ndarray, beta: np.ndarray) -> np.ndarray:
    """The Beta mean ``alpha / (alpha + beta)``: the deterministic action."""
    return alpha / (alpha + beta)


def to_action(u, low, high):
    return low + u * (high - low)


def to_unit(action, low, high):
    return (action - low) / (high - low)
