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


def advantages(rewards: np.ndarray, mask: np.ndarray, gamma: float, baseline: str) -> np.ndarray:
    """Returns minus baseline, scaled to unit standard deviation over the valid steps."""
    g = discounted_returns(rewards, mask, gamma)
    if baseline == "time":
        adv = g - time_baseline(g, mask)
    elif baseline == "none":
        adv = g
    else:
        raise ValueError(f"unknown baseline {baseline!r}")
    valid = mask > 0
    sd = adv[valid].std() if valid.any() else 0.0
    if sd > 1e-12:
        adv = adv / sd
    return adv * mask
