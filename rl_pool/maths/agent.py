"""Agent files: a Beta policy, its observation normaliser and optimiser state.

An agent is a ``.npz`` loaded with ``allow_pickle=False`` (no object arrays, so
no code can ride along) holding the weights, the normaliser, the optimiser
moments and a JSON ``meta`` string with everything needed to run it alone:
env id and kwargs, episode length, action bounds, policy shape, format version.
"""

from __future__ import annotations

import functools
import io
import json
import math
import os
import zipfile
from dataclasses import dataclass, field, replace

import numpy as np

from rl_pool.errors import AgentFileError
from rl_pool.maths import normalizer, policy
from rl_pool.maths.normalizer import NormState

FORMAT = "rl-pool-agent"
#: Format 2: named parameter arrays (``param.NAME``, ``adam_m.NAME``, ``adam_v.NAME``) and a policy spec
#: object; format 1 (one matrix ``w``, policy ``linear`` / ``linear-exp``) is still read.
FORMAT_VERSION = 2
READS_VERSIONS = (1, 2)
NORM_ARRAYS = ("obs_count", "obs_mean", "obs_m2")
META_MAX_BYTES = 1 << 16
NPY_HEADER_MAX = 4096
#: Every .npz starts with a zip local-file header.
ZIP_MAGIC = b"PK\x03\x04"
#: Zip bookkeeping per array (local header + central directory entry, names included), generously.
ZIP_ENTRY_MAX = 512


def array_shapes(meta: AgentMeta, version: int = FORMAT_VERSION) -> dict[str, tuple[int, ...]]:
    """The name and shape of every numeric array in an agent file with this meta."""
    pshapes = policy.param_shapes(meta.spec, meta.obs_dim, meta.act_dim)
    out: dict[str, tuple[int, ...]] = {"obs_count": (), "obs_mean": (meta.obs_dim,),
                                       "obs_m2": (meta.obs_dim,), "opt_t": ()}
    if version == 1:
        return out | {"w": pshapes["w"], "opt_m": pshapes["w"], "opt_v": pshapes["w"]}
    for prefix in ("param", "adam_m", "adam_v"):
        out |= {f"{prefix}.{k}": v for k, v in pshapes.items()}
    return out


def max_file_bytes(meta: AgentMeta) -> int:
    """An upper bound on the size of a well-formed agent file with this meta (a cap for readers)."""
    shapes = array_shapes(meta)
    arrays = sum(8 * int(np.prod(s)) + NPY_HEADER_MAX + ZIP_ENTRY_MAX for s in shapes.values())
    return arrays + META_MAX_BYTES + NPY_HEADER_MAX + ZIP_ENTRY_MAX + 4096


@functools.lru_cache(maxsize=256)
def _float64_header(shape: tuple[int, ...]) -> bytes:
    """The ``.npy`` header this numpy writes for a C-ordered little-endian float64 array of
    ``shape`` (built from the shape alone: no array of that size is made)."""
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, {"descr": "<f8", "fortran_order": False, "shape": shape})
    return buf.getvalue()


def _read_float64(z, key: str, shape: tuple[int, ...]) -> np.ndarray:
    """Array ``key`` of an open ``.npz``. What ``to_bytes`` writes (a stored, uncompressed member:
    a header equal, byte for byte, to this numpy's for a float64 array of ``shape``, then exactly
    its data) is read straight from the bytes; anything else (compressed, another dtype, byte order
    or header) goes through numpy's reader, whose header parser costs several times more. Either
    way the caller checks dtype, shape and values."""
    info = z.zip.getinfo(key + ".npy")
    head = _float64_header(shape)
    # Stored members only: their bytes are the file's own, so reading one allocates no more than
    # the file holds (a compressed member would be inflated before its size is cut to the directory's).
    if info.compress_type == zipfile.ZIP_STORED and info.file_size == len(head) + 8 * math.prod(shape):
        raw = z.zip.read(info)
        if raw.startswith(head):
            return np.frombuffer(raw, dtype="<f8", offset=len(head)).reshape(shape)
    arr = z[key]
    if not isinstance(arr, np.ndarray):  # numpy hands back the bytes of a member that is not .npy
        raise ValueError(f"{key}.npy is not a .npy array")
    return arr


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
    spec: policy.PolicySpec = field(default_factory=policy.PolicySpec)

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
            "policy": self.spec.to_json(),
        }

    @classmethod
    def from_json(cls, d) -> AgentMeta:
        return cls.from_json_versioned(d)[0]

    @classmethod
    def from_json_versioned(cls, d) -> tuple[AgentMeta, int]:
        if not isinstance(d, dict) or d.get("format") != FORMAT:
            raise AgentFileError("not an rl-pool agent (meta has no rl-pool format tag)")
        version = d.get("version")
        if version not in READS_VERSIONS:
            raise AgentFileError(f"agent format version {version!r}, this rl-pool reads "
                                 + " and ".join(map(str, READS_VERSIONS)))
        try:
            spec = policy.PolicySpec.from_json(d["policy"])
        except (KeyError, TypeError, ValueError) as exc:
            raise AgentFileError(f"agent policy is not one rl-pool knows: {exc}") from None
        if version == 1 and spec.kind != "linear":
            raise AgentFileError("agent format 1 holds linear policies only")
        try:
            meta = cls(
                env=str(d["env"]),
                env_kwargs=dict(d["env_kwargs"]),
                max_episode_steps=int(d["max_episode_steps"]),
                obs_dim=int(d["obs_dim"]),
                act_dim=int(d["act_dim"]),
                action_low=tuple(float(x) for x in d["action_low"]),
                action_high=tuple(float(x) for x in d["action_high"]),
                spec=spec,
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise AgentFileError(f"agent meta is incomplete: {exc}") from None
        if len(meta.action_low) != meta.act_dim or len(meta.action_high) != meta.act_dim:
            raise AgentFileError("agent action bounds do not match its action dimension")
        if not all(math.isfinite(lo) and math.isfinite(hi) and hi > lo
                   for lo, hi in zip(meta.action_low, meta.action_high, strict=True)):
            raise AgentFileError("agent action bounds are not finite low < high")
        if not (0 < meta.obs_dim <= 100_000 and 0 < meta.act_dim <= 10_000 and meta.max_episode_steps > 0):
            raise AgentFileError("agent dimensions must be positive (and plausible)")
        return meta, version


@dataclass(frozen=True)
class Agent:
    """A Beta policy (``params``: named arrays, see :mod:`rl_pool.maths.policy`) with its normaliser
    and optimiser state (Adam moments named like ``params``)."""

    meta: AgentMeta
    params: dict
    norm: NormState
    opt_m: dict = field(repr=False, default=None)
    opt_v: dict = field(repr=False, default=None)
    opt_t: float = 0.0

    # ----- construction -------------------------------------------------
    @classmethod
    def initial(cls, meta: AgentMeta, seed: int = 0, shape: float | None = None) -> Agent:
        """The iteration-0 agent: initial parameters from ``seed`` (Beta shapes ``shape`` at the start,
        see :func:`rl_pool.maths.policy.init_params`), empty normaliser and moments."""
        params = policy.init_params(meta.spec, meta.obs_dim, meta.act_dim, seed, shape)
        zeros = {k: np.zeros_like(v) for k, v in params.items()}
        return cls(meta, params, normalizer.init(meta.obs_dim), zeros, dict(zeros), 0.0)

    def evolve(self, **changes) -> Agent:
        return replace(self, **changes)

    @property
    def spec(self) -> policy.PolicySpec:
        return self.meta.spec

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
        return policy.beta_params(self.params, self.normalize(obs), self.spec)

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
        logp = policy.log_prob_unit(self.params, self.normalize(obs), u, self.spec)
        return logp - np.log(self.high - self.low).sum()

    # ----- files ----------------------------------------------------------
    def to_bytes(self) -> bytes:
        f64 = lambda a: np.asarray(a, dtype=np.float64)  # noqa: E731
        arrays = {"meta": np.array(json.dumps(self.meta.to_json(), sort_keys=True)),
                  "obs_count": np.array(self.norm.count, dtype=np.float64),
                  "obs_mean": f64(self.norm.mean), "obs_m2": f64(self.norm.m2),
                  "opt_t": np.array(self.opt_t, dtype=np.float64)}
        for prefix, tree in (("param", self.params), ("adam_m", self.opt_m), ("adam_v", self.opt_v)):
            arrays |= {f"{prefix}.{k}": f64(tree[k]) for k in sorted(self.params)}
        buf = io.BytesIO()
        np.savez(buf, **arrays)
        return buf.getvalue()

    def save(self, path: str | os.PathLike) -> None:
        """Write atomically (temp file, fsync, rename)."""
        from rl_pool.fsutil import atomic_write

        atomic_write(path, self.to_bytes())

    @classmethod
    def from_bytes(cls, data: bytes, source: str = "agent") -> Agent:
        """Parse and check an agent file (format 1 or 2); :class:`AgentFileError` says why it is refused.

        Nothing is unpickled, and no array is read before its size in the zip
        directory fits the shape the meta implies, so a small hostile file
        cannot make the reader allocate gigabytes.
        """
        if bytes(data[:4]) != ZIP_MAGIC:
            # Checked first so that numpy's reply to a non-zip file (a pickle, with advice on
            # loading it unsafely) never reaches the user, and np.load only ever sees a zip.
            raise AgentFileError(f"{source}: not an rl-pool agent file (an .npz is a zip archive; "
                                 f"this starts with {bytes(data[:8])!r})")
        try:
            with np.load(io.BytesIO(data), allow_pickle=False) as z:
                if "meta" not in z.files:
                    raise AgentFileError(f"{source}: not an rl-pool agent (missing meta)")
                if z.zip.getinfo("meta.npy").file_size > META_MAX_BYTES:
                    raise AgentFileError(f"{source}: agent meta is implausibly large")
                meta_arr = z["meta"]
                if meta_arr.dtype.kind != "U" or meta_arr.shape != ():
                    raise AgentFileError(f"{source}: agent meta is not a JSON string")
                try:
                    meta, version = AgentMeta.from_json_versioned(json.loads(str(meta_arr)))
                except json.JSONDecodeError as exc:
                    raise AgentFileError(f"{source}: agent meta is not valid JSON ({exc})") from None
                except AgentFileError as exc:
                    raise AgentFileError(f"{source}: {exc}") from None
                expect = array_shapes(meta, version)
                missing = [k for k in expect if k not in z.files]
                if missing:
                    raise AgentFileError(f"{source}: not an rl-pool agent (missing {', '.join(missing)})")
                for key, shape in expect.items():
                    size = z.zip.getinfo(key + ".npy").file_size
                    if size > 8 * int(np.prod(shape)) + NPY_HEADER_MAX:
                        raise AgentFileError(f"{source}: array {key!r} is larger than its shape {shape} allows")
                arrays = {k: _read_float64(z, k, shape) for k, shape in expect.items()}
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
        f64 = {k: arrays[k].astype(np.float64) for k in expect}
        if version == 1:
            params, m, v = {"w": f64["w"]}, {"w": f64["opt_m"]}, {"w": f64["opt_v"]}
        else:
            names = policy.param_shapes(meta.spec, meta.obs_dim, meta.act_dim)
            params = {k: f64[f"param.{k}"] for k in names}
            m = {k: f64[f"adam_m.{k}"] for k in names}
            v = {k: f64[f"adam_v.{k}"] for k in names}
        if f64["obs_count"] < 0 or np.any(f64["obs_m2"] < 0) or any(np.any(a < 0) for a in v.values()):
            raise AgentFileError(f"{source}: negative count or variance")
        norm = NormState(float(f64["obs_count"]), f64["obs_mean"], f64["obs_m2"])
        return cls(meta, params, norm, m, v, float(f64["opt_t"]))

    @classmethod
    def load(cls, path: str | os.PathLike) -> Agent:
        from rl_pool import fsutil

        try:  # bounded and non-blocking: a FIFO or /dev/zero named as an agent is refused, not read
            data = fsutil.read_bytes(path, fsutil.AGENT_MAX_BYTES, follow=True)
        except OSError as exc:
            raise AgentFileError(f"cannot read agent {os.fspath(path)!r}: {exc.strerror or exc}") from None
        return cls.from_bytes(data, source=os.fspath(path))
