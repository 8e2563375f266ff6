"""Making gymnasium environments and checking that rl-pool can drive them.

The learner steps ``env.unwrapped`` and enforces the episode length itself:
gymnasium's default wrappers (order enforcing, passive checker, time limit)
cost about 40% of a Swimmer step here and do nothing a trusted loop needs.
"""

from __future__ import annotations

import logging
import re
import threading
import warnings
from dataclasses import dataclass

import numpy as np

from rl_pool.errors import EnvError, Stopped


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


log = logging.getLogger("rl_pool")

# MuJoCo reports warnings through one process-wide C callback. Its default writes
# each message to stderr *and* appends it to MUJOCO_LOG.TXT in the working
# directory. Under mujoco 4 every load of HalfCheetah's XML warns that the
# compiler attribute 'settotalmass' is deprecated (gymnasium's model, nothing a
# user can act on): once per env, so a member making 10 envs printed it 10 times.
# We route the callback to logging instead: deprecations of the model format go
# to DEBUG, anything else (e.g. "Nan, Inf or huge value in QACC", a simulation
# going unstable) is logged once per kind at WARNING, in the member's log.
_DEPRECATED = re.compile(r"\bdeprecated\b", re.IGNORECASE)
_seen: set[str] = set()
_seen_lock = threading.Lock()
_installed = False


def _mujoco_warning(message) -> None:
    try:
        text = str(message).strip()
        kind = re.sub(r"[-+]?\d[\d.eE+-]*", "#", text)  # "... at DOF 3 ... Time = 1.2" -> one kind
        with _seen_lock:
            first = kind not in _seen
            _seen.add(kind)
        if _DEPRECATED.search(text):
            log.debug("MuJoCo: %s", text)
        elif first:
            log.warning("MuJoCo: %s (further warnings of this kind are not shown)", text)
        else:
            log.debug("MuJoCo: %s", text)
    except Exception:  # a callback from C must never raise
        pass


def quiet_mujoco_warnings() -> None:
    """Route MuJoCo's warnings to logging (idempotent; :func:`make` calls it)."""
    global _installed
    if _installed:
        return
    try:
        import mujoco
    except ImportError:
        return
    mujoco.set_mju_user_warning(_mujoco_warning)
    _installed = True


def make(env_id: str, env_kwargs: dict | None = None, render_mode: str | None = None):
    """``(env, info)``: the unwrapped env and its checked description."""
    gym = _gym()
    quiet_mujoco_warnings()
    kwargs = dict(env_kwargs or {})
    if render_mode is not None:
        kwargs["render_mode"] = render_mode
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            wrapped = gym.make(env_id, disable_env_checker=True, **kwargs)
    except Exception as exc:  # a user's own module or environment (--env mypkg:MyRobot-v0) may raise anything
        _raise_interrupt(exc)
        if isinstance(exc, gym.error.Error):
            raise EnvError(f"unknown or unusable environment {env_id!r}: {exc}") from None
        if isinstance(exc, (TypeError, ValueError, ImportError, OSError)):
            raise EnvError(f"cannot make environment {env_id!r} with {kwargs}: {exc}") from None
        raise EnvError(f"cannot make environment {env_id!r} with {kwargs}: {type(exc).__name__}: {exc}") from None
    info = check(env_id, wrapped)
    return wrapped.unwrapped, info


def _raise_interrupt(exc: BaseException) -> None:
    """Raise the Ctrl-C or stop signal behind ``exc``, if any: code that a signal cut short (a C
    extension's import) can report it as its own error, which must not read as a bad environment."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, (KeyboardInterrupt, Stopped)):
            raise exc
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__


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
