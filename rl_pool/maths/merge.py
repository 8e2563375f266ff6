"""The merge: one agent made from several branches of the same parent (pure maths).

Every branch of an iteration starts from the same parent ``P`` and returns an agent
``B_m`` after its own training episodes. With the branches the selection rule chose
(:func:`rl_pool.protocol.selection.decide`), rank weights ``w_m`` (summing to 1) and a scale
``c``, the merged agent is

* parameters ``P + c * sum_m w_m (B_m - P)``: the weighted mean update times ``c``
  (``--merge mean``: c = 1, a data-parallel batch; ``sum``: c = k, the k
  branches' progress in one step, as a batch k times larger with a rate k times
  larger would take it);
* with ``--merge-momentum`` beta, after a merge, plus ``beta (P - P')``, ``P'`` the agent the
  previous merge started from: heavy-ball momentum across iterations (:func:`with_momentum`);
* Adam moments ``sum_m w_m M_m`` (the same weights: they describe the merged update);
  its step count is the branches' (they all made the same number of steps);
* observation statistics of every valid branch, not only the merged ones: each
  branch's own observations are recovered from its statistics and the parent's
  (Chan et al.'s parallel update run backwards) and added to the parent's, so the
  normaliser counts every episode the pool ran (ARS does the same).

Sums run in a fixed order over members, element by element in float64, so every
member that computes a merge from the same deposits gets the same bytes.
"""

from __future__ import annotations

import numpy as np

from rl_pool.maths.agent import Agent
from rl_pool.maths.normalizer import NormState


def weighted_update(parent: dict, branches: list[dict], weights: list[float], scale: float) -> dict:
    """``parent + scale * sum_m weights[m] * (branches[m] - parent)`` for each named array."""
    if len(branches) != len(weights) or not branches:
        raise ValueError("one weight per branch, at least one branch")
    out = {}
    for name, p in parent.items():
        p = np.asarray(p, dtype=np.float64)
        step = np.zeros_like(p)
        for b, w in zip(branches, weights, strict=True):
            step = step + w * (np.asarray(b[name], dtype=np.float64) - p)
        out[name] = p + scale * step
    return out


def weighted_mean(arrays: list[dict], weights: list[float]) -> dict:
    """``sum_m weights[m] * arrays[m]`` for each named array (weights summing to 1)."""
    out = {}
    for name in arrays[0]:
        acc = np.zeros_like(np.asarray(arrays[0][name], dtype=np.float64))
        for a, w in zip(arrays, weights, strict=True):
            acc = acc + w * np.asarray(a[name], dtype=np.float64)
        out[name] = acc
    return out


def own_statistics(parent: NormState, branch: NormState) -> NormState:
    """The statistics of the observations a branch added to its parent's: Chan's parallel update
    ``branch = parent (+) own`` solved for ``own``. A branch that added nothing gives count 0."""
    n = branch.count - parent.count
    if n <= 0:
        return NormState(0.0, np.zeros_like(parent.mean), np.zeros_like(parent.m2))
    mean = (branch.count * branch.mean - parent.count * parent.mean) / n
    delta = mean - parent.mean
    m2 = branch.m2 - parent.m2 - delta * delta * (parent.count * n / branch.count)
    return NormState(float(n), mean, np.maximum(m2, 0.0))


def combine(a: NormState, b: NormState) -> NormState:
    """Chan, Golub & LeVeque (1979): the statistics of two disjoint sets of observations together."""
    if b.count <= 0:
        return a
    if a.count <= 0:
        return b
    total = a.count + b.count
    delta = b.mean - a.mean
    mean = a.mean + delta * (b.count / total)
    m2 = a.m2 + b.m2 + delta * delta * (a.count * b.count / total)
    return NormState(float(total), mean, m2)


def pooled_statistics(parent: NormState, branches: list[NormState]) -> NormState:
    """The parent's statistics with every branch's own observations added, in member order."""
    out = parent
    for b in branches:
        out = combine(out, own_statistics(parent, b))
    return out


def with_momentum(merged: dict, parent: dict, before: dict, beta: float) -> dict:
    """``merged + beta * (parent - before)`` for each named array: heavy-ball momentum (Polyak
    1964) across iterations, ``before`` being the agent the previous merge started from. Applied
    to merges, as SlowMo (Wang et al. 2020) applies it to the averaged updates of local SGD: the
    part of the step that persists from one iteration to the next grows up to ``1 / (1 - beta)``
    times, the part that changes direction does not."""
    out = {}
    for name, m in merged.items():
        p = np.asarray(parent[name], dtype=np.float64)
        out[name] = m + beta * (p - np.asarray(before[name], dtype=np.float64))
    return out


def merge_agents(parent: Agent, chosen: list[Agent], weights: list[float], scale: float,
                 every: list[Agent], momentum: tuple[float, Agent] | None = None) -> Agent:
    """The merged agent: ``chosen`` branches (best first) with ``weights`` and ``scale``;
    observation statistics from ``every`` valid branch (in member order); with ``momentum``
    ``(beta, before)``, plus ``beta`` times the step from ``before`` to ``parent``."""
    params = weighted_update(parent.params, [b.params for b in chosen], weights, scale)
    if momentum is not None:
        params = with_momentum(params, parent.params, momentum[1].params, momentum[0])
    opt_m = weighted_mean([b.opt_m for b in chosen], weights)
    opt_v = weighted_mean([b.opt_v for b in chosen], weights)
    norm = pooled_statistics(parent.norm, [b.norm for b in every])
    return parent.evolve(params=params, norm=norm, opt_m=opt_m, opt_v=opt_v, opt_t=chosen[0].opt_t)
