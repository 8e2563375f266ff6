"""Making gymnasium environments and checking that rl-pool can drive them.

The learner steps ``env.unwrapped`` and enforces the episode length itself:
gymnasium's default wrappers (order enforcing, passive checker, time limit)
cost about 40% of a Swimmer step here and do nothing a trusted loop needs.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np

from .errors import EnvError


@dataclass(frozen=True)
class EnvInfo:
    """What the learner needs to know of an environment."""

    env_id: str
    obs_dim: int
    act_dim: int
    low: np.ndarray
    high: np.ndarray
    max_episode_steps: int


def _gym():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        import gymnasium

    return gymnasium


def make(env_id: str, env_kwargs: dict | None = None, render_mode: str | None = None):
    """``(env, info)``: the unwrapped env and its checked description."""
    gym = _gym()
    kwargs = dict(env_kwargs or {})
    if render_mode is not None:
        kwargs["render_mode"] = render_mode
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            wrapped = gym.make(env_id, disable_env_checker=True, **kwargs)
    except gym.error.Error as exc:
        raise EnvError(f"unknown or unusable environment {env_id!r}: {exc}") from None
    except (TypeError, ValueError, ImportError, OSError) as exc:
        raise EnvError(f"cannot make environment {env_id!r} with {kwargs}: {exc}") from None
    info = check(env_id, wrapped)
    return wrapped.unwrapped, info


def check(env_id: str, env) -> EnvInfo:
    """Refuse what a Beta policy cannot drive: non-Box or unbounded actions, non-flat observations."""
    gym = _gym()
    act = env.action_space
    if not isinstance(act, gym.spaces.Box):
        raise EnvError(
            f"environment {env_id!r} has a {type(act).__name__} action space; "
            "rl-pool needs a bounded continuous (Box) action space"
        )
    low = np.asarray(act.low, dtype=np.float64).ravel()
    high = np.asarray(act.high, dtype=np.float64).ravel()
    if not (np.all(np.isfinite(low)) and np.all(np.isfinite(high)) and np.all(high > low)):
        raise EnvError(
            f"environment {env_id!r} has an unbounded action space; a Beta policy needs finite low < high"
        )
    obs = env.observation_space
    if not isinstance(obs, gym.spaces.Box) or len(obs.shape) != 1:
        raise EnvError(f"environment {env_id!r} needs a flat Box observation space, has {obs}")
    steps = env.spec.max_episode_steps if env.spec is not None else None
    if not steps:
        raise EnvError(f"environment {env_id!r} has no episode limit; pass --max-episode-steps")
    return EnvInfo(env_id, int(obs.shape[0]), int(low.shape[0]), low, high, int(steps))
