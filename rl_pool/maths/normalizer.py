"""Running observation statistics (Welford / Chan et al. parallel update).

State: ``count`` (scalar), ``mean`` ``[obs_dim]``, ``m2`` ``[obs_dim]`` (sum of
squared deviations). A batch of observations is merged with the parallel
formula of Chan, Golub & LeVeque (1979), which is exact for any split of the
data into batches, so the result does not depend on how episodes are batched.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

#: Normalised features are clipped to this many standard deviations.
CLIP = 10.0
#: Added to the variance so a constant coordinate does not divide by zero.
VAR_EPS = 1e-8


class NormState(NamedTuple):
    count: float
    mean: np.ndarray
    m2: np.ndarray


def init(obs_dim: int) -> NormState:
    return NormState(0.0, np.zeros(obs_dim), np.zeros(obs_dim))


def update(state: NormState, batch: np.ndarray) -> NormState:
    """Merge ``batch`` ``[n, obs_dim]`` into ``state``; returns a new state."""
    batch = np.asarray(batch, dtype=np.float64)
    if batch.ndim != 2 or batch.shape[1] != state.mean.shape[0]:
        raise ValueError(f"batch must be [n, {state.mean.shape[0]}], got {batch.shape}")
    n = batch.shape[0]
    if n == 0:
        return state
    b_mean = batch.mean(axis=0)
    b_m2 = ((batch - b_mean) ** 2).sum(axis=0)
    total = state.count + n
    delta = b_mean - state.mean
    mean = state.mean + delta * (n / total)
    m2 = state.m2 + b_m2 + delta**2 * (state.count * n / total)
    return NormState(float(total), mean, m2)


def std(state: NormState) -> np.ndarray:
    """Population standard deviation; ones until two observations are seen."""
    if state.count < 2:
        return np.ones_like(state.mean)
    return np.sqrt(state.m2 / state.count + VAR_EPS)


def scale(state: NormState) -> tuple[np.ndarray, np.ndarray]:
    """``(mean, 1/std)`` so that hot loops normalise with one subtract and one multiply."""
    return state.mean, 1.0 / std(state)


def normalize(state: NormState, obs: np.ndarray) -> np.ndarray:
    mean, inv_std = scale(state)
    return np.clip((obs - mean) * inv_std, -CLIP, CLIP)
