"""Beta policies: a small family of networks feeding one Beta distribution per action dimension.

A policy is described by a :class:`PolicySpec` (kind, hidden sizes, link) and
its parameters are a dict of named arrays (a JAX pytree), so rollouts, the
learner and agent files treat every kind alike. Each kind maps normalised
observations ``x`` ``[..., obs_dim]`` to pre-activations ``z`` ``[..., 2A]``:

* ``linear``: ``z = [x, 1] W`` with ``W`` (named ``w``) ``[obs_dim + 1, 2A]``
  (the last row is the bias, as in agent files of format 1);
* ``mlp``: ``h_0 = x``, ``h_{k+1} = tanh(h_k W_k + b_k)`` for each hidden
  layer, then ``z = h_L W_L + b_L``; arrays ``w0, b0, ..., wL, bL``.

A spec with ``value`` hidden sizes also carries a state-value network (the learned baseline of
``--baseline value``): the same tanh MLP on ``[x, t / T]`` (``t`` the step, ``T`` the episode
limit) with one output, arrays ``v_w0, v_b0, ..., v_wL, v_bL``. It never touches the actions.

The link turns ``z`` into shapes ``alpha_j = link(z_j) + 1`` and ``beta_j =
link(z_{A+j}) + 1``, both >= 1 so every Beta is unimodal (no mass piling up
at the bounds). ``exp`` (clamped at ``Z_MAX``) is the default: a linear step
in ``z`` scales the shape, so a policy can become sharp, or push its mean
close to an action bound, in a few steps instead of hundreds (on Swimmer the
``softplus`` link stalls with mean actions capped near 0.9 of the bound; see
results/). A sample ``u`` in (0, 1) maps to the action ``low + u (high - low)``;
the Beta policy for bounded control is Chou, Maturana & Scherer (2017).

The forward pass is written once and takes an array module ``xp`` (numpy or
jax.numpy): the same maths serves the NumPy rollouts and the JAX gradient.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: Samples are clipped to [EPS, 1 - EPS] before any log: a float Beta draw can be exactly 0 or 1.
EPS = 1e-6
#: The ``exp`` link clamps the pre-activation here: shapes stay below 1 + e^10 ~ 22000.
Z_MAX = 10.0

KINDS = ("linear", "mlp")
#: Names of the value network's arrays start with this.
VALUE_PREFIX = "v_"
LINKS = ("exp", "softplus")
#: Seed-stream tag for initial weights, apart from every training and evaluation stream.
_INIT_TAG = 7

_lgamma = np.vectorize(math.lgamma, otypes=[np.float64])


@dataclass(frozen=True)
class PolicySpec:
    """What a policy is, apart from its numbers (hashable: a static argument to jitted code)."""

    kind: str = "linear"
    hidden: tuple[int, ...] = ()
    link: str = "exp"
    #: hidden sizes of the state-value network (empty: none)
    value: tuple[int, ...] = ()

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ValueError(f"unknown policy kind {self.kind!r} (have {', '.join(KINDS)})")
        if self.link not in LINKS:
            raise ValueError(f"unknown link {self.link!r} (have {', '.join(LINKS)})")
        hidden = tuple(int(h) for h in self.hidden)
        if self.kind == "linear" and hidden:
            raise ValueError("a linear policy has no hidden layers")
        if self.kind == "mlp" and (not hidden or any(h < 1 or h > 4096 for h in hidden) or len(hidden) > 8):
            raise ValueError(f"mlp hidden sizes must be 1 to 8 layers of 1..4096 units, got {hidden}")
        value = tuple(int(h) for h in self.value)
        if value and (any(h < 1 or h > 4096 for h in value) or len(value) > 8):
            raise ValueError(f"value hidden sizes must be 1 to 8 layers of 1..4096 units, got {value}")
        object.__setattr__(self, "hidden", hidden)
        object.__setattr__(self, "value", value)

    def to_json(self) -> dict:
        out = {"kind": self.kind, "hidden": list(self.hidden), "link": self.link}
        if self.value:  # written only when there is one: agents without it keep their bytes
            out["value"] = list(self.value)
        return out

    @classmethod
    def from_json(cls, d) -> PolicySpec:
        """From an agent file: format 2's object, or format 1's names ``linear`` / ``linear-exp``."""
        if d == "linear":
            return cls("linear", (), "softplus")
        if d == "linear-exp":
            return cls("linear", (), "exp")
        if not isinstance(d, dict):
            raise ValueError(f"policy must be an object, got {d!r}")
        return cls(str(d["kind"]), tuple(d.get("hidden", ())), str(d.get("link", "exp")),
                   tuple(d.get("value", ())))

    def describe(self) -> str:
        body = "linear" if self.kind == "linear" else "mlp " + ",".join(map(str, self.hidden))
        value = f", value mlp {','.join(map(str, self.value))}" if self.value else ""
        return f"{body} ({self.link} link{value})"


def param_shapes(spec: PolicySpec, obs_dim: int, act_dim: int) -> dict[str, tuple[int, ...]]:
    """Every parameter's name and shape, in a fixed order (the policy's, then the value network's)."""
    out = 2 * act_dim
    if spec.kind == "linear":
        shapes = {"w": (obs_dim + 1, out)}
    else:
        shapes = _mlp_shapes("", [obs_dim, *spec.hidden, out])
    if spec.value:
        shapes |= _mlp_shapes(VALUE_PREFIX, [obs_dim + 1, *spec.value, 1])
    return shapes


def _mlp_shapes(prefix: str, sizes: list[int]) -> dict[str, tuple[int, ...]]:
    shapes = {}
    for k in range(len(sizes) - 1):
        shapes[f"{prefix}w{k}"] = (sizes[k], sizes[k + 1])
        shapes[f"{prefix}b{k}"] = (sizes[k + 1],)
    return shapes


def init_bias(link: str, shape: float) -> float:
    """The output bias that makes ``alpha = beta = shape`` (> 1): the link's inverse at ``shape - 1``."""
    if not (math.isfinite(shape) and 1.0 < shape <= 1.0 + math.exp(Z_MAX)):
        raise ValueError(f"an initial Beta shape must be > 1 and <= 1 + e^{Z_MAX:g}, got {shape}")
    if link == "exp":
        return math.log(shape - 1.0)
    return math.log(math.expm1(shape - 1.0)) if shape - 1.0 < 30 else shape - 1.0  # softplus^-1 (~identity)


def init_params(spec: PolicySpec, obs_dim: int, act_dim: int, seed: int = 0,
                shape: float | None = None) -> dict[str, np.ndarray]:
    """Initial parameters, a deterministic function of ``seed``.

    The output layer's weights start at zero, so every kind starts from the same
    policy: ``alpha = beta = link(0) + 1`` (2 for ``exp``), a broad bump centred
    on the middle of each action range; ``shape`` sets its bias so that
    ``alpha = beta = shape`` instead (a larger shape explores less: the action's
    variance is ``(high - low)^2 / (4 (2 shape + 1))``, which matters where
    the reward charges for large actions, as Ant's control cost does).
    Hidden layers draw ``N(0, 1/fan_in)`` weights (LeCun's scaling, which keeps
    ``tanh`` units out of saturation) and zero biases. A value network starts the same way,
    its output layer at zero (drawn after the policy's, which stay as without it).
    """
    shapes = param_shapes(spec, obs_dim, act_dim)
    rng = np.random.Generator(np.random.PCG64(np.random.SeedSequence([int(seed), _INIT_TAG])))
    params = {}
    n_layers = len(spec.hidden) + 1
    v_out = len(spec.value)
    for name, dims in shapes.items():
        last = name in ("w", f"w{n_layers - 1}", f"b{n_layers - 1}",
                        f"{VALUE_PREFIX}w{v_out}", f"{VALUE_PREFIX}b{v_out}")
        if last or name.removeprefix(VALUE_PREFIX).startswith("b"):
            params[name] = np.zeros(dims)
        else:
            params[name] = rng.normal(0.0, 1.0 / math.sqrt(dims[0]), size=dims)
    if shape is not None:
        name, rows = shape_bias(spec)
        params[name][rows] = init_bias(spec.link, shape)
    return params


def shape_bias(spec: PolicySpec) -> tuple[str, int | slice]:
    """Where the output bias of the Beta shapes' pre-activations lives: ``(parameter name, index)``
    (the last row of a linear policy's weights; an MLP's last bias vector)."""
    if spec.kind == "linear":
        return "w", -1
    return f"b{len(spec.hidden)}", slice(None)


def sharpened(params: dict, spec: PolicySpec, factor: float) -> dict:
    """``params`` with every Beta shape's excess over 1 multiplied by ``factor`` (``exp`` link:
    ``log(factor)`` added to the output bias of every shape): the same policy with its action noise
    narrowed, its mean action moved a little towards its mode (exactly ``factor`` times while the
    pre-activation stays below the link's cap, ``Z_MAX``). The value network's parameters stay."""
    if spec.link != "exp":
        raise ValueError("sharpening needs the exp link")
    name, rows = shape_bias(spec)
    bias = np.array(params[name], dtype=np.float64)
    bias[rows] += math.log(factor)
    return dict(params, **{name: bias})


def preactivations(params: dict, x, spec: PolicySpec, xp=np):
    """``z`` ``[..., 2A]`` for normalised observations ``x`` ``[..., obs_dim]``."""
    if spec.kind == "linear":
        w = params["w"]
        return x @ w[:-1] + w[-1]
    h = x
    n_layers = len(spec.hidden) + 1
    for k in range(n_layers - 1):
        h = xp.tanh(h @ params[f"w{k}"] + params[f"b{k}"])
    return h @ params[f"w{n_layers - 1}"] + params[f"b{n_layers - 1}"]


def value(params: dict, x, t_frac, spec: PolicySpec, xp=np):
    """The value network's output ``[...]`` for normalised observations ``x`` ``[..., obs_dim]`` at
    steps ``t_frac`` ``[...]`` (the step over the episode limit)."""
    h = xp.concatenate([x, t_frac[..., None]], axis=-1)
    n_layers = len(spec.value) + 1
    for k in range(n_layers - 1):
        h = xp.tanh(h @ params[f"{VALUE_PREFIX}w{k}"] + params[f"{VALUE_PREFIX}b{k}"])
    return (h @ params[f"{VALUE_PREFIX}w{n_layers - 1}"] + params[f"{VALUE_PREFIX}b{n_layers - 1}"])[..., 0]


def softplus(z, xp=np):
    return xp.logaddexp(0.0, z)


def shapes(z, link: str = "exp", xp=np):
    """The link from pre-activations to Beta shapes, both >= 1."""
    if link == "exp":
        return xp.exp(xp.minimum(z, Z_MAX)) + 1.0
    return softplus(z, xp) + 1.0


def beta_params(params: dict, x, spec: PolicySpec, xp=np):
    """``(alpha, beta)`` for normalised observations ``x`` ``[..., obs_dim]``; each ``[..., act_dim]``."""
    ab = shapes(preactivations(params, x, spec, xp), spec.link, xp)
    act_dim = ab.shape[-1] // 2
    return ab[..., :act_dim], ab[..., act_dim:]


def clip_unit(u, xp=np, out=None):
    """``u`` clipped into ``[EPS, 1 - EPS]``, in place into ``out`` (NumPy only) when given.

    ``minimum(maximum(...))`` gives clip's numbers; NumPy's ``clip`` wrapper costs as much as
    the arithmetic on the small arrays of a rollout step.
    """
    if out is not None:
        return np.minimum(np.maximum(u, EPS, out=out), 1.0 - EPS, out=out)
    return xp.minimum(xp.maximum(u, EPS), 1.0 - EPS)


def beta_log_prob(u, alpha, beta, xp=np, gammaln=None):
    """Elementwise ``log Beta(u; alpha, beta)`` with ``u`` clipped into the open interval."""
    if gammaln is None:
        gammaln = _lgamma
    u = clip_unit(u, xp)
    log_norm = gammaln(alpha) + gammaln(beta) - gammaln(alpha + beta)
    return (alpha - 1.0) * xp.log(u) + (beta - 1.0) * xp.log1p(-u) - log_norm


def log_prob_unit(params: dict, x, u, spec: PolicySpec, xp=np, gammaln=None):
    """``sum_j log Beta(u_j; alpha_j, beta_j)`` for samples ``u`` in (0, 1); shape ``[...]``."""
    alpha, beta = beta_params(params, x, spec, xp)
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
