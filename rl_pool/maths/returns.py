"""Monte Carlo returns and baselines for a batch of episodes (pure NumPy).

Batches are padded to a common length: ``rewards`` and ``mask`` are ``[B, T]``,
``mask[b, t]`` is 1 while episode ``b`` is running and 0 after it ended.
"""

from __future__ import annotations

import numpy as np


def discounted_returns(rewards: np.ndarray, mask: np.ndarray, gamma: float) -> np.ndarray:
    """``G_t = sum_{k >= t} gamma^(k-t) r_k`` within each episode; 0 on padding. ``[B, T]``."""
    rewards = np.asarray(rewards, dtype=np.float64)
    if rewards.ndim != 2 or rewards.shape != np.shape(mask):
        raise ValueError(f"rewards and mask must both be [B, T], got {rewards.shape}, {np.shape(mask)}")
    r = rewards * mask
    out = np.empty_like(r)
    acc = np.zeros(r.shape[0])
    # A loop over time (T ~ 1000) vectorised over the batch; gamma = 1 is allowed.
    for t in range(r.shape[1] - 1, -1, -1):
        acc = r[:, t] + gamma * acc
        out[:, t] = acc
    return out * mask


def time_baseline(returns: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Leave-one-out time-indexed baseline ``[B, T]``.

    ``b[i, t]`` is the mean return-to-go at step ``t`` over the *other*
    episodes of the batch still running at ``t``. Leaving episode ``i`` out
    keeps the baseline independent of its own actions, so the gradient stays
    unbiased (Kool, van Hoof & Welling 2019, "Buy 4 REINFORCE samples"). Where
    no other episode is running the baseline is 0.
    """
    mask = np.asarray(mask, dtype=np.float64)
    total = (returns * mask).sum(axis=0, keepdims=True)
    count = mask.sum(axis=0, keepdims=True)
    others = count - mask
    with np.errstate(invalid="ignore", divide="ignore"):
        b = np.where(others > 0, (total - returns * mask) / np.maximum(others, 1), 0.0)
    return b * mask


def baseline_features(obs: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``[B, T, 2 obs_dim + 4]`` features of each step for :func:`linear_baseline`: the
    (normalised) observation clipped to [-10, 10], its square, t/100, its square and cube, and 1
    (the features of Duan et al. 2016's linear feature baseline)."""
    o = np.clip(np.asarray(obs, dtype=np.float64), -10.0, 10.0)
    B, T = np.shape(mask)
    t = np.broadcast_to((np.arange(T, dtype=np.float64) / 100.0)[None, :, None], (B, T, 1))
    return np.concatenate([o, o * o, t, t * t, t ** 3, np.ones((B, T, 1))], axis=2)


def linear_baseline(returns: np.ndarray, mask: np.ndarray, obs: np.ndarray, reg: float = 1e-5) -> np.ndarray:
    """Cross-fitted linear state baseline ``[B, T]``: a ridge regression of the return-to-go on
    :func:`baseline_features`, fitted on the odd-numbered episodes for the even ones and on the
    even ones for the odd ones.

    Where the return depends on the state more than on time (Reacher's target position), this
    takes out what the time-indexed baseline cannot. Fitting each episode's baseline on the
    *other* half of the batch keeps it independent of that episode's actions, so the gradient
    stays unbiased; with one episode there is nothing to fit on and the baseline is 0.
    """
    mask = np.asarray(mask, dtype=np.float64)
    B = mask.shape[0]
    out = np.zeros_like(mask)
    if B < 2:
        return out
    f = baseline_features(obs, mask)
    k = f.shape[2]
    for fold in (0, 1):
        fit = np.arange(B) % 2 != fold  # the other half
        valid = mask[fit] > 0
        x, y = f[fit][valid], np.asarray(returns, dtype=np.float64)[fit][valid]
        if not len(y):
            continue
        xtx, xty = x.T @ x, x.T @ y
        lam = reg * max(1.0, float(np.trace(xtx)) / k)
        for _ in range(5):  # as rllab: more regularisation until the solve is finite
            try:
                w = np.linalg.solve(xtx + lam * np.eye(k), xty)
            except np.linalg.LinAlgError:
                w = None
            if w is not None and np.all(np.isfinite(w)):
                break
            lam *= 10.0
        else:
            continue
        out[~fit] = f[~fit] @ w
    return out * mask


def _valid_moments(returns: np.ndarray, mask: np.ndarray):
    """Per episode: the number of valid steps, and the sums of their return-to-go and its square."""
    g = np.asarray(returns, dtype=np.float64) * mask
    return mask.sum(axis=1), g.sum(axis=1), (g * g).sum(axis=1)


def value_targets(returns: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """What the value network learns from a batch ``[B, T]``: the return-to-go standardised over the
    batch's valid steps, ``(G - mean) / std`` (0 on padding; no scaling where the std is ~0). The
    network then works in units near 1 whatever the task's reward scale, and follows the batch
    statistics as the policy improves."""
    mask = np.asarray(mask, dtype=np.float64)
    n, s1, s2 = (x.sum() for x in _valid_moments(returns, mask))
    if n <= 0:
        return np.zeros_like(mask)
    mean = s1 / n
    sd = np.sqrt(max(s2 / n - mean * mean, 0.0))
    y = np.asarray(returns, dtype=np.float64) - mean
    return (y / sd if sd > 1e-12 else y) * mask


def value_baseline(returns: np.ndarray, mask: np.ndarray, values: np.ndarray) -> np.ndarray:
    """The learned state baseline ``[B, T]``: the value network's outputs ``values`` (standardised
    units, :func:`value_targets`) put back in return units with the mean and std of the *other*
    episodes' return-to-go. The network was fitted on earlier batches and the scale leaves each
    episode out, so no episode's baseline sees its own actions; with one episode it is 0."""
    mask = np.asarray(mask, dtype=np.float64)
    n, s1, s2 = _valid_moments(returns, mask)
    n_o, s1_o, s2_o = n.sum() - n, s1.sum() - s1, s2.sum() - s2
    has = n_o > 0
    mean = np.where(has, s1_o / np.maximum(n_o, 1), 0.0)
    sd = np.where(has, np.sqrt(np.maximum(s2_o / np.maximum(n_o, 1) - mean * mean, 0.0)), 0.0)
    b = mean[:, None] + sd[:, None] * np.asarray(values, dtype=np.float64)
    return np.where(has[:, None], b, 0.0) * mask


def gae(rewards: np.ndarray, mask: np.ndarray, values: np.ndarray, gamma: float, lam: float) -> np.ndarray:
    """Generalised advantage estimates ``[B, T]`` (Schulman et al. 2016): ``sum_{k >= 0} (gamma
    lam)^k delta_{t+k}`` with ``delta_t = r_t + gamma V_{t+1} - V_t`` and ``V = 0`` after an
    episode's last step.

    ``values`` estimate the (discounted) return-to-go of the same episodes, so the value after the
    last step is 0 whether the episode ended or hit its time limit. With ``lam = 1`` the sum
    telescopes to the return-to-go minus ``values``; below 1 the advantage of a step leans on the
    value of the steps after it instead of their sampled rewards: less variance, some bias.
    """
    mask = np.asarray(mask, dtype=np.float64)
    v = np.asarray(values, dtype=np.float64) * mask
    v_next = np.zeros_like(v)
    v_next[:, :-1] = v[:, 1:]
    delta = np.asarray(rewards, dtype=np.float64) * mask + gamma * v_next - v
    return discounted_returns(delta, mask, gamma * lam)  # the same backward sum, with factor gamma lam


def advantages(rewards: np.ndarray, mask: np.ndarray, gamma: float, baseline: str,
               obs: np.ndarray | None = None, lam: float = 1.0, values: np.ndarray | None = None,
               g: np.ndarray | None = None) -> np.ndarray:
    """Returns minus baseline, scaled to unit standard deviation over the valid steps.
    ``obs``: the batch's (normalised) observations ``[B, T, obs_dim]``, for ``linear``; ``values``:
    the value network's outputs ``[B, T]``, for ``value``; ``g``: the discounted returns, when the
    caller has them already. With ``lam`` below 1 the baseline serves as the value function of
    :func:`gae` instead."""
    if g is None:
        g = discounted_returns(rewards, mask, gamma)
    if baseline == "time":
        b = time_baseline(g, mask)
    elif baseline == "linear":
        if obs is None:
            raise ValueError("the linear baseline needs the observations")
        b = linear_baseline(g, mask, obs)
    elif baseline == "value":
        if values is None:
            raise ValueError("the value baseline needs the value network's outputs")
        b = value_baseline(g, mask, values)
    elif baseline == "none":
        b = np.zeros_like(g)
    else:
        raise ValueError(f"unknown baseline {baseline!r}")
    # lam = 1 keeps the plain difference, bit for bit as pools made before lam existed
    adv = g - b if lam >= 1.0 else gae(rewards, mask, b, gamma, lam)
    valid = mask > 0
    sd = adv[valid].std() if valid.any() else 0.0
    if sd > 1e-12:
        adv = adv / sd
    return adv * mask
