"""Agent files: a Beta policy, its observation normaliser and optimiser state.

An agent is a ``.npz`` loaded with ``allow_pickle=False`` (no object arrays, so
no code can ride along) holding the weights, the normaliser, the optimiser
moments and a JSON ``meta`` string with everything needed to run it alone:
env id and kwargs, episode length, action bounds, policy shape, format version.
"""

from __future__ import annotations

import io
import json
import math
import os
from dataclasses import dataclass, field, replace

import numpy as np

from . import normalizer, policy
from .errors import AgentFileError
from .normalizer import NormState

FORMAT = "rl-pool-agent"
FORMAT_VERSION = 1
ARRAYS = ("meta", "w", "obs_count", "obs_mean", "obs_m2", "opt_m", "opt_v", "opt_t")
META_MAX_BYTES = 1 << 20
NPY_HEADER_MAX = 4096


def _parse_meta(meta_arr, source: str) -> AgentMeta:
    if meta_arr.dtype.kind != "U" or meta_arr.shape != ():
        raise AgentFileError(f"{source}: agent meta is not a JSON string")
    try:
        return AgentMeta.from_json(json.loads(str(meta_arr)))
    except json.JSONDecodeError as exc:
        raise AgentFileError(f"{source}: agent meta is not valid JSON ({exc})") from None
    except AgentFileError as exc:
        raise AgentFileError(f"{source}: {exc}") from None


def _shapes(meta) -> dict:
    """The shape of every numeric array of an agent with this meta."""
    f, a = meta.obs_dim + 1, meta.act_dim
    return {"w": (f, 2 * a), "obs_count": (), "obs_mean": (meta.obs_dim,), "obs_m2": (meta.obs_dim,),
            "opt_m": (f, 2 * a), "opt_v": (f, 2 * a), "opt_t": ()}


@dataclass(frozen=True)
class AgentMeta:
    """Everything about an agent except its numbers."""

    env: str
    env_kwargs: dict
    max_episode_steps: int
    obs_dim: int
    act_dim: int
    action_low: tuple
    action_high: tuple
    policy: str = "linear"

    def to_json(self) -> dict:
        return {
            "format": FORMAT,
            "version": FORMAT_VERSION,
            "env": self.env,
            "env_kwargs": self.env_kwargs,
            "max_episode_steps": self.max_episode_steps,
            "obs_dim": self.obs_dim,
            "act_dim": self.act_dim,
            "action_low": list(self.action_low),
            "action_high": list(self.action_high),
            "policy": self.policy,
        }

    @classmethod
    def from_json(cls, d) -> AgentMeta:
        if not isinstance(d, dict) or d.get("format") != FORMAT:
            raise AgentFileError("not an rl-pool agent (meta has no rl-pool format tag)")
        if d.get("version") != FORMAT_VERSION:
            raise AgentFileError(f"agent format version {d.get('version')!r}, this rl-pool reads {FORMAT_VERSION}")
        try:
            meta = cls(
                env=str(d["env"]),
                env_kwargs=dict(d["env_kwargs"]),
                max_episode_steps=int(d["max_episode_steps"]),
                obs_dim=int(d["obs_dim"]),
                act_dim=int(d["act_dim"]),
                action_low=tuple(float(x) for x in d["action_low"]),
                action_high=tuple(float(x) for x in d["action_high"]),
                policy=str(d["policy"]),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise AgentFileError(f"agent meta is incomplete: {exc}") from None
        if meta.policy not in policy.POLICIES:
            raise AgentFileError(f"unknown policy kind {meta.policy!r}")
        if len(meta.action_low) != meta.act_dim or len(meta.action_high) != meta.act_dim:
            raise AgentFileError("agent action bounds do not match its action dimension")
        if not all(math.isfinite(lo) and math.isfinite(hi) and hi > lo
                   for lo, hi in zip(meta.action_low, meta.action_high, strict=True)):
            raise AgentFileError("agent action bounds are not finite low < high")
        if meta.obs_dim <= 0 or meta.act_dim <= 0 or meta.max_episode_steps <= 0:
            raise AgentFileError("agent dimensions must be positive")
        return meta


@dataclass(frozen=True)
class Agent:
    """A Beta policy with its normaliser. ``w`` is ``[obs_dim + 1, 2 * act_dim]``."""

    meta: AgentMeta
    w: np.ndarray
    norm: NormState
    opt_m: np.ndarray = field(repr=False, default=None)
    opt_v: np.ndarray = field(repr=False, default=None)
    opt_t: float = 0.0

    # ----- construction -------------------------------------------------
    @classmethod
    def initial(cls, meta: AgentMeta) -> Agent:
        w = policy.init_params(meta.obs_dim, meta.act_dim)
        return cls(meta, w, normalizer.init(meta.obs_dim), np.zeros_like(w), np.zeros_like(w), 0.0)

    def evolve(self, **changes) -> Agent:
        return replace(self, **changes)

    @property
    def low(self) -> np.ndarray:
        return np.asarray(self.meta.action_low)

    @property
    def high(self) -> np.ndarray:
        return np.asarray(self.meta.action_high)

    # ----- the API --------------------------------------------------------
    def normalize(self, obs) -> np.ndarray:
        return normalizer.normalize(self.norm, np.asarray(obs, dtype=np.float64))

    def beta_params(self, obs):
        """``(alpha, beta)`` for an observation; each ``[act_dim]`` (or ``[n, act_dim]`` for a batch)."""
        return policy.beta_params(self.w, self.normalize(obs), policy=self.meta.policy)

    def act(self, obs, rng: np.random.Generator | None = None, deterministic: bool = True) -> np.ndarray:
        """An action in env units: the Beta mean if ``deterministic``, else a sample drawn from ``rng``."""
        alpha, beta = self.beta_params(obs)
        if deterministic:
            u = policy.mean_unit(alpha, beta)
        else:
            u = policy.sample_unit(rng if rng is not None else np.random.default_rng(), alpha, beta)
        return policy.to_action(u, self.low, self.high)

    def log_prob(self, obs, action) -> np.ndarray:
        """``sum_j [log Beta(u_j; a_j, b_j) - log(high_j - low_j)]`` with ``u`` the action in (0, 1)."""
        u = policy.to_unit(np.asarray(action, dtype=np.float64), self.low, self.high)
        logp = policy.log_prob_unit(self.w, self.normalize(obs), u, policy=self.meta.policy)
        return logp - np.log(self.high - self.low).sum()

    # ----- files ----------------------------------------------------------
    def to_bytes(self) -> bytes:
        buf = io.BytesIO()
        np.savez(
            buf,
            meta=np.array(json.dumps(self.meta.to_json(), sort_keys=True)),
            w=np.asarray(self.w, dtype=np.float64),
            obs_count=np.array(self.norm.count, dtype=np.float64),
            obs_mean=np.asarray(self.norm.mean, dtype=np.float64),
            obs_m2=np.asarray(self.norm.m2, dtype=np.float64),
            opt_m=np.asarray(self.opt_m, dtype=np.float64),
            opt_v=np.asarray(self.opt_v, dtype=np.float64),
            opt_t=np.array(self.opt_t, dtype=np.float64),
        )
        return buf.getvalue()

    def save(self, path: str | os.PathLike) -> None:
        """Write atomically (temp file, fsync, rename)."""
        from .fsutil import atomic_write

        atomic_write(path, self.to_bytes())

    @classmethod
    def from_bytes(cls, data: bytes, source: str = "agent") -> Agent:
        """Parse and check an agent file; :class:`AgentFileError` says why it is refused.

        Nothing is unpickled, and no array is read before its size in the zip
        directory fits the shape the meta implies, so a small hostile file
        cannot make the reader allocate gigabytes.
        """
        try:
            with np.load(io.BytesIO(data), allow_pickle=False) as z:
                missing = [k for k in ARRAYS if k not in z.files]
                if missing:
                    raise AgentFileError(f"{source}: not an rl-pool agent (missing {', '.join(missing)})")
                sizes = {k: z.zip.getinfo(k + ".npy").file_size for k in ARRAYS}
                if sizes["meta"] > META_MAX_BYTES:
                    raise AgentFileError(f"{source}: agent meta is implausibly large ({sizes['meta']} bytes)")
                meta = _parse_meta(z["meta"], source)
                expect = _shapes(meta)
                for key, shape in expect.items():
                    if sizes[key] > 8 * int(np.prod(shape)) + NPY_HEADER_MAX:
                        raise AgentFileError(f"{source}: array {key!r} is larger than its shape {shape} allows")
                arrays = {k: z[k] for k in expect}
        except AgentFileError:
            raise
        except Exception as exc:  # zip errors, object arrays refused, truncation, ...
            raise AgentFileError(f"{source}: unreadable agent file ({type(exc).__name__}: {exc})") from None
        for key, shape in expect.items():
            arr = arrays[key]
            if arr.dtype.kind != "f":
                raise AgentFileError(f"{source}: array {key!r} has dtype {arr.dtype}, expected float")
            if arr.shape != shape:
                raise AgentFileError(f"{source}: array {key!r} has shape {arr.shape}, expected {shape}")
            if not np.all(np.isfinite(arr)):
                raise AgentFileError(f"{source}: array {key!r} holds non-finite numbers")
        if arrays["obs_count"] < 0 or np.any(arrays["obs_m2"] < 0) or np.any(arrays["opt_v"] < 0):
            raise AgentFileError(f"{source}: negative count or variance")
        f64 = {k: arrays[k].astype(np.float64) for k in expect}
        norm = NormState(float(f64["obs_count"]), f64["obs_mean"], f64["obs_m2"])
        return cls(meta, f64["w"], norm, f64["opt_m"], f64["opt_v"], float(f64["opt_t"]))

    @classmethod
    def load(cls, path: str | os.PathLike) -> Agent:
        try:
            with open(path, "rb") as fh:
                data = fh.read()
        except OSError as exc:
            raise AgentFileError(f"cannot read agent {os.fspath(path)!r}: {exc.strerror or exc}") from None
        return cls.from_bytes(data, source=os.fspath(path))
