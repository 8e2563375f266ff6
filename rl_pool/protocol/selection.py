"""The selection rule: which agent the pool goes on from after an iteration.

A pure function of the iteration's verified deposit reports (their metrics) and
the previous selection: :func:`decide` touches no file, so every member computes
the same record, and the rule is tested with tables of cases. The store
(:mod:`rl_pool.protocol.pool`) reads and verifies the files, hands the reports over, checks
the agents the decision names, and writes the decision. How the pool works as a
whole is described in ``docs/protocol.md``.

Winners:

* ``branch``: the best valid deposit (ties to the lowest member);
* ``parent``: the agent the iteration started from, re-scored on the same
  evaluation episodes, beat every branch (``--selection parent``);
* ``merge``: with ``--merge mean|sum|adaptive|momentum``, two or more branches beat the parent
  (and the fallback): the next agent is the parent plus a rank-weighted
  combination of their updates (:mod:`rl_pool.maths.merge`); it is scored in the next
  iteration, as the parent, beside the best agent this iteration evaluated
  (its ``fallback``), which takes over if the merge turns out worse;
* ``fallback``: that fallback beat the merged parent and every branch;
* ``revert``: ``--revert-after`` iterations without a new best: back to the best;
* ``carried``: no valid deposit: the parent carries over.
"""

from __future__ import annotations

import math

from rl_pool.config import PoolConfig
from rl_pool.protocol.layout import deposit_rel

#: Members that re-score the parent in an iteration, in turn: enough that a selection lacks the
#: parent's score only if all of them are missing or invalid, few enough that a large pool does not
#: evaluate one agent on the same episodes N times (at N = 16 that was an eighth of the work).
PARENT_SCORERS = 3

#: Larger per-episode returns than this are not believed (no MuJoCo task pays near it); it keeps
#: the paired differences of a garbled report finite.
EPISODE_RETURN_MAX = 1e12


def finite(x) -> bool:
    """A JSON number that is a finite float (an integer too large for a float is not)."""
    if isinstance(x, bool) or not isinstance(x, (int, float)):
        return False
    try:
        return math.isfinite(float(x))
    except OverflowError:
        return False


def score_of(cfg: PoolConfig, doc: dict) -> float:
    """What selection compares for a deposit: its ``eval_score`` when the pool shifts rewards, else
    its ``eval_return``; ValueError if that is not a finite number."""
    score = doc.get("eval_score") if cfg.reward_shift else doc.get("eval_return")
    if not finite(score):
        raise ValueError(f"eval_score is not a finite number ({score!r})")
    return float(score)


def choose(candidates: list[tuple[int, float]]) -> tuple[int, float]:
    """The winner among ``(member, score)``: highest score, ties to the lowest member."""
    if not candidates:
        raise ValueError("no candidates")
    return min(candidates, key=lambda c: (-c[1], c[0]))


def scores_parent(i: int, m: int, pool_size: int) -> bool:
    """Whether member ``m`` re-scores the parent in iteration ``i``: every member in a pool of up
    to :data:`PARENT_SCORERS`, else members ``i``, ``i + N//3`` and ``i + 2N//3`` (mod N).

    Spread over the pool, not consecutive: array jobs place consecutive members on one node, and
    losing a node should not take every scorer of an iteration with it.
    """
    if pool_size <= PARENT_SCORERS:
        return True
    offset = (m - i) % pool_size
    step = pool_size // PARENT_SCORERS
    return offset % step == 0 and offset // step < PARENT_SCORERS


def rescores_parent(cfg: PoolConfig, previous: dict) -> bool:
    """Whether the members of the iteration after ``previous`` re-score its agent (the parent):
    with ``--selection parent`` always (it competes); with ``--best-score mean`` and branches
    only, when the parent is the best so far (just made the best, or reverted to), so its
    re-score counts towards the best's mean without competing."""
    if cfg.selection == "parent":
        return True
    best = previous.get("best")
    return cfg.best_score == "mean" and isinstance(best, dict) and best.get("agent_sha256") == previous["agent_sha256"]


def parent_report(docs: list[dict], parent_sha: str, shifted: bool = False, prefix: str = "parent_") -> dict | None:
    """The deposit whose report of the parent's score counts: the lowest member's that names the
    right parent and gives a finite return (and, when ``shifted``, a finite shifted score).
    ``prefix`` ``"fallback_"``: the report of the fallback's score instead.

    The members :func:`scores_parent` names re-score the agent they started from on
    the iteration's common evaluation seeds, so all honest reports agree.
    """
    for doc in docs:
        ret = doc.get(prefix + "eval_return")
        score = doc.get(prefix + "eval_score") if shifted else ret
        if doc.get(prefix + "sha256") == parent_sha and finite(ret) and finite(score):
            return doc
    return None


def episode_scores(doc: dict, n: int, shift: float, max_steps: int, prefix: str = "") -> list[float] | None:
    """The per-episode scores (return, minus ``shift`` per step) of the ``n`` evaluation episodes
    a deposit reports (``prefix`` ``"parent_"``: of the parent), or None if it does not report
    them whole: ``n`` returns within ±:data:`EPISODE_RETURN_MAX` and, with a shift, ``n``
    lengths of 0 to ``max_steps`` steps."""
    rets, lens = doc.get(prefix + "eval_returns"), doc.get(prefix + "eval_lengths")
    if not (isinstance(rets, list) and len(rets) == n
            and all(finite(r) and abs(r) <= EPISODE_RETURN_MAX for r in rets)):
        return None
    if not shift:
        return [float(r) for r in rets]
    if not (isinstance(lens, list) and len(lens) == n
            and all(isinstance(k, int) and not isinstance(k, bool) and 0 <= k <= max_steps for k in lens)):
        return None
    return [float(r) - shift * k for r, k in zip(rets, lens, strict=True)]


def paired_margin(branch: list[float], parent: list[float]) -> tuple[float, float]:
    """``(mean, standard error)`` of the per-episode differences branch - parent on common episodes."""
    d = [b - p for b, p in zip(branch, parent, strict=True)]
    n = len(d)
    mean = math.fsum(d) / n
    se = math.sqrt(math.fsum((x - mean) ** 2 for x in d) / (n - 1) / n) if n > 1 else 0.0
    return mean, se


def merge_weights(k: int) -> list[float]:
    """Rank weights of ``k`` merged branches, best first: ``k - r`` for rank ``r``, summing to 1
    (the linear fitness shaping of evolution strategies, without negative weights: a REINFORCE
    update is not a symmetric perturbation, and going against one is not an improvement)."""
    total = k * (k + 1) // 2
    return [(k - r) / total for r in range(k)]


def merge_scale(kind: str, k: int, adaptive: float = 1.0) -> float:
    """How far a merge of ``k`` branches steps, in units of their weighted mean update: ``mean`` and
    ``momentum`` 1 (a data-parallel batch: less noise, the same step; ``momentum`` adds its term
    apart, :func:`merge_momentum`), ``sum`` ``k`` (the linear scaling rule:
    k branches' worth of progress in one step), ``adaptive`` the pool's current scale
    (:func:`next_scale`) capped at ``k``."""
    if kind == "sum":
        return float(k)
    if kind == "adaptive":
        return float(min(max(adaptive, 1.0), k))
    return 1.0


#: The rules that merge only from three or more branches at the bar, so that a merge is always
#: judged in the next iteration; with 2 members they decide as ``none`` (:func:`min_merged`).
RULES_OF_THREE = ("adaptive", "momentum")


def min_merged(kind: str) -> int:
    """The fewest branches a merge is made of; with fewer at the bar, the best one wins alone.
    ``adaptive`` and ``momentum`` need 3: the rank-weighted mean of two branches is mostly the better one shrunk
    towards the other (in the default launch, the guard member's small steps), which loses the
    step size and gains little averaging; a pool of 2 members then goes on exactly as ``none``
    does (measured in docs/scaling.md)."""
    return 3 if kind in RULES_OF_THREE else 2


#: The adaptive merge's scale is multiplied by this after a merge that held its ground and divided
#: by it after one that did not: a trust region, as the 1/5 success rule of evolution strategies.
SCALE_STEP = 2.0


def carried_scale(previous: dict, pool_size: int) -> float:
    """The adaptive scale the previous selection carries (1 for a pool's first selections)."""
    c = previous.get("merge_scale")
    return float(min(max(c, 1.0), pool_size)) if finite(c) else 1.0


def next_scale(previous: dict, parent: float | None, fallback: float | None, pool_size: int) -> float:
    """The adaptive scale after the verdict on the previous iteration's merge: that merge (re-scored
    now as the ``parent``) against its ``fallback`` (the best branch of its iteration, re-scored on
    the same episodes). At least as good: the scale doubles; worse: it halves; no merge or no
    verdict: it stays. It stays within 1 (the mean update) and the pool size."""
    c = carried_scale(previous, pool_size)
    if previous.get("winner") == "merge" and parent is not None and fallback is not None:
        c = c * SCALE_STEP if parent >= fallback else c / SCALE_STEP
    return float(min(max(c, 1.0), pool_size))


def decide(cfg: PoolConfig, i: int, previous: dict, reports: list[dict], skipped: list[dict],
           reason: str) -> tuple[dict, list[int]]:
    """The selection record of iteration ``i`` and the members whose agents it uses.

    ``reports``: the valid deposits' metrics (signature, iteration, member and a finite score
    checked by the store), in member order; ``skipped``: ``{"member", "reason"}`` of the rest;
    ``previous``: the selection of ``i - 1``. The store verifies the agents of the returned
    members; one that fails is moved to ``skipped`` and the rule is applied again, so the result
    stays a pure function of the files.

    Candidates are compared on their *score*: the mean evaluation return of the objective the
    members train on (with ``reward_shift`` taken off every step when the pool shifts rewards);
    ``eval_return`` always records the env's own return. A branch that ties with the parent wins:
    it has not lost ground.

    ``cfg.selection_margin`` K > 0 asks more of a branch: its per-episode scores minus the
    parent's on the same episodes must average at least K standard errors of those differences
    (:func:`paired_margin`); the best branch that clears it wins, else the parent. Each
    considered branch then records ``diff`` and ``se``.
    """
    shifted = bool(cfg.reward_shift)
    docs = list(reports)
    considered = [{"member": d["member"], "eval_return": float(d["eval_return"]), "score": score_of(cfg, d),
                   "agent_sha256": d["agent_sha256"], "doc": d} for d in docs]
    skipped = sorted(skipped, key=lambda s: s["member"])
    sha = previous["agent_sha256"]
    report = parent_report(docs, sha, shifted) if rescores_parent(cfg, previous) else None
    competes = report is not None and cfg.selection == "parent"
    streak = parent_streak(previous)
    patience_out = bool(cfg.parent_patience) and streak >= cfg.parent_patience and competes
    if patience_out:  # the parent has kept the pool long enough: this time the branches compete alone
        competes = False
    parent_eps = None
    if competes and cfg.selection_margin:
        def parent_episodes(doc):
            return episode_scores(doc, cfg.eval_episodes, cfg.reward_shift, cfg.max_episode_steps, "parent_")

        # the lowest report of the parent with its episodes whole (all honest ones agree)
        report = parent_report([d for d in docs if parent_episodes(d)], sha, shifted) or report
        parent_eps = parent_episodes(report)
    for c in considered:
        eps = parent_eps and episode_scores(c["doc"], cfg.eval_episodes, cfg.reward_shift,
                                            cfg.max_episode_steps)
        c["diff"], c["se"] = paired_margin(eps, parent_eps) if eps else (None, None)
    eligible = [c for c in considered if parent_eps is None
                or (c["diff"] is not None and c["diff"] >= cfg.selection_margin * c["se"])]

    keys = ("member", "eval_return", "score") + (("diff", "se") if parent_eps is not None else ())
    out = {"iteration": i, "considered": [{k: c[k] for k in keys} for c in considered],
           "skipped": skipped, "quorum_reason": reason,
           "parent": {"iteration": previous["iteration"], "member": previous.get("member"),
                      "agent_sha256": sha}}
    if cfg.merge == "momentum":  # the next merge's momentum starts from this agent's file
        out["parent"]["agent"] = previous["agent"]
    parent = None if report is None else (
        float(report["parent_eval_return"]), float(report["parent_eval_score" if shifted else "parent_eval_return"]))
    out["parent"] |= {"eval_return": parent and parent[0], "score": parent and parent[1]}
    if parent_eps is not None:
        out["margin"] = cfg.selection_margin
    keep_parent = {"member": None, "agent": previous["agent"], "agent_sha256": sha,
                   "eval_return": parent and parent[0], "score": parent and parent[1]}

    def branch(c) -> dict:
        return {"winner": "branch", "member": c["member"], "eval_return": c["eval_return"], "score": c["score"],
                "agent": deposit_rel(i, c["member"]), "agent_sha256": c["agent_sha256"]}

    needs: list[int] = []
    if cfg.merge == "adaptive":
        out["merge_scale"] = carried_scale(previous, cfg.pool_size)
    if not considered:
        out |= keep_parent | {"winner": "carried", "carried_from": previous["iteration"]}
    elif cfg.merge != "none" and parent_eps is None:
        needs = _merge_or_pick(cfg, out, previous, considered, docs, competes and parent, keep_parent, branch)
    else:
        if eligible:
            top, _ = choose([(c["member"], c["score"]) for c in eligible])
        else:  # with a margin, no branch cleared it: the parent stays
            top, _ = choose([(c["member"], c["score"]) for c in considered])
        best = next(c for c in considered if c["member"] == top)
        if competes and (not eligible or (parent_eps is None and parent[1] > best["score"])):
            out |= keep_parent | {"winner": "parent", "best_branch": {k: best[k] for k in keys}}
        else:
            out |= branch(best)
            needs = [top]
    if patience_out:
        out["patience"] = streak
    out = track_best(out, previous, cfg.revert_after, cfg.best_score == "mean")
    if cfg.rate_patience:
        out["rate"] = next_rate(previous, out, cfg.rate_patience, cfg.rate_decay)
    if cfg.parent_patience:  # after track_best: a parent kept and then reverted is no longer a parent kept
        kept, nothing = out["winner"] in ("parent", "fallback"), out["winner"] == "carried"
        out["parent_streak"] = streak + 1 if kept else streak if nothing else 0
    return out, needs


#: The smallest share of its given learning rate a member is taken down to by ``--rate-patience``.
MIN_RATE_SCALE = 0.01


def rate_scale(previous: dict) -> float:
    """The share of its given learning rate every member trains with after ``previous`` (1 when the
    record carries no valid scale: a pool without ``--rate-patience``, or its first iteration)."""
    rate = previous.get("rate")
    c = rate.get("scale") if isinstance(rate, dict) else None
    return float(min(max(c, MIN_RATE_SCALE), 1.0)) if finite(c) else 1.0


def anneal_scale(cfg, iteration: int) -> float:
    """The share of its learning rate every member trains with in ``iteration`` under
    ``--rate-anneal K``: 1 in iteration 1, falling linearly to :data:`MIN_RATE_SCALE` by
    iteration K + 1 and staying there (1 without the option). A function of the iteration alone,
    so a restarted member trains as an uninterrupted one would."""
    if not cfg.rate_anneal:
        return 1.0
    return max(MIN_RATE_SCALE, 1.0 - (iteration - 1) / cfg.rate_anneal)


def recorded_rate_scale(sel: dict) -> float | None:
    """The rate scale a selection record carries, for reports (status, TensorBoard): None when it
    has no ``rate`` (a pool without ``--rate-patience``), else :func:`rate_scale`."""
    return rate_scale(sel) if isinstance(sel.get("rate"), dict) else None


def next_rate(previous: dict, out: dict, patience: int, decay: float) -> dict:
    """``{"scale", "since"}`` after selection ``out``: the pool-wide share of the learning rates
    (``--rate-patience``) and the iterations since it last changed or the pool last found a new
    best. A new best divides the scale by ``decay`` (up to 1: the pool is climbing at this step
    size, and may again at a larger one); ``patience`` iterations without one multiply it by
    ``decay`` (down to :data:`MIN_RATE_SCALE`): a plateau asks for smaller steps, as a learning
    rate reduced on a plateau does in supervised training."""
    scale = rate_scale(previous)
    rate = previous.get("rate")
    since = count(rate.get("since")) if isinstance(rate, dict) else 0
    best = out.get("best")
    if isinstance(best, dict) and best.get("iteration") == out["iteration"]:
        return {"scale": min(scale / decay, 1.0), "since": 0}
    since += 1
    if since >= patience:
        return {"scale": max(scale * decay, MIN_RATE_SCALE), "since": 0}
    return {"scale": scale, "since": since}


def parent_streak(previous: dict) -> int:
    """How many iterations in a row, up to ``previous``, the parent or a merge's fallback kept the pool
    (``--parent-patience``; an iteration without a valid deposit, ``carried``, neither counts nor
    ends the run; a revert ends it; 0 when the record has no valid count)."""
    return count(previous.get("parent_streak"))


def count(n) -> int:
    """A JSON count: ``n`` if it is an integer >= 0 (not a bool), else 0."""
    return n if isinstance(n, int) and not isinstance(n, bool) and n >= 0 else 0


def _merge_or_pick(cfg: PoolConfig, out: dict, previous: dict, considered: list[dict], docs: list[dict],
                   parent, keep_parent: dict, branch) -> list[int]:
    """``decide`` with ``--merge``: fill ``out``; the members whose agents it uses.

    The bar a branch must reach is the best score of the agents that did not train this
    iteration: the parent (re-scored) and, after a merge, the fallback (the best agent the
    merge's iteration evaluated, re-scored beside it). Branches at or above the bar are merged
    (fewer than :func:`min_merged`: the best of them simply wins); with none, the better of
    parent and fallback stays. With ``--selection branches``, or with no report of the parent's
    score, there is no bar: ``mean`` and ``sum`` merge the better half of the branches, and
    ``adaptive``, which merges only what the next iteration can judge, takes the best branch.
    """
    shifted = bool(cfg.reward_shift)
    ranked = sorted(considered, key=lambda c: (-c["score"], c["member"]))
    olds = []  # (score, eval_return, record) of the parent and the fallback, the parent first
    if parent:
        olds.append((parent[1], parent[0], keep_parent | {"winner": "parent"}))
    fb = previous.get("next_fallback")
    if parent and isinstance(fb, dict):
        rep = parent_report(docs, fb.get("agent_sha256"), shifted, prefix="fallback_")
        if rep is not None:
            ret = float(rep["fallback_eval_return"])
            score = float(rep["fallback_eval_score" if shifted else "fallback_eval_return"])
            out["fallback"] = {"eval_return": ret, "score": score, "agent_sha256": fb["agent_sha256"]}
            olds.append((score, ret, {"winner": "fallback", "member": None, "agent": fb["agent"],
                                      "agent_sha256": fb["agent_sha256"], "eval_return": ret, "score": score}))
    if cfg.merge == "adaptive":
        out["merge_scale"] = next_scale(previous, parent[1] if parent else None, out.get("fallback", {}).get("score"),
                                        cfg.pool_size)
    if olds:
        bar = max(s for s, _, _ in olds)
        chosen = [c for c in ranked if c["score"] >= bar]
    elif cfg.merge in RULES_OF_THREE:
        # nothing to merge against: no verdict could ever judge the merge, so the best branch wins
        chosen = ranked[:1]
    else:
        chosen = ranked[:(len(ranked) + 1) // 2]
    best = ranked[0]
    if not chosen:
        _, _, rec = max(olds, key=lambda o: o[0])  # ties: the parent (listed first) stays
        out |= rec | {"best_branch": {k: best[k] for k in ("member", "eval_return", "score")}}
        return []
    if len(chosen) < min_merged(cfg.merge):
        out |= branch(chosen[0])
        return [chosen[0]["member"]]
    weights = merge_weights(len(chosen))
    evaluated = branch(best)
    del evaluated["winner"]
    out |= {"winner": "merge", "member": None, "eval_return": best["eval_return"], "score": best["score"],
            "agent": None, "agent_sha256": None,
            "merge": {"kind": cfg.merge, "members": [c["member"] for c in chosen], "weights": weights,
                      "scale": merge_scale(cfg.merge, len(chosen), out.get("merge_scale", 1.0)),
                      "statistics_from": [c["member"] for c in considered]},
            "evaluated": evaluated}
    if any(sharpening(cfg, previous, m) != 1.0 for m in range(cfg.pool_size)):
        out["merge"]["sharpened_starts"] = True  # its step holds the sharpening: no momentum from it
    momentum = merge_momentum(cfg, previous)
    if momentum is not None:
        out["merge"]["momentum"] = momentum
    return [c["member"] for c in considered]


def sharpening(cfg: PoolConfig, previous: dict, member: int) -> float:
    """By how much member ``member`` sharpens the agent it starts from after ``previous``
    (``--sharpen`` F): ``F ** (member / (N - 1))`` when ``previous`` kept the parent or a merge's
    fallback (a lock: every branch scored below it), else 1. A ladder from the agent as it is
    (member 0) to F times sharper, so the pool tries several noise levels at once and selection
    keeps the one whose branch scored best. After a revert, ``--revert-sharpen`` F for every member:
    the pool goes back to its best agent with less action noise."""
    if previous.get("winner") == "revert":
        return float(cfg.revert_sharpen)
    if cfg.sharpen == 1.0 or cfg.pool_size < 2 or previous.get("winner") not in ("parent", "fallback"):
        return 1.0
    return float(cfg.sharpen ** (member / (cfg.pool_size - 1)))


def merge_momentum(cfg: PoolConfig, previous: dict) -> dict | None:
    """The momentum term of a ``--merge momentum`` merge made after ``previous``: ``{"beta",
    "from"}``, where ``from`` names the agent the previous iteration started from, so the merge adds
    ``beta`` times the step from that agent to the parent (:func:`rl_pool.maths.merge.merge_agents`).
    Only when ``previous`` was itself a merge of branches that started from its parent as it was: a
    step that was a pick, a revert or the parent kept is not a direction the pool's branches agreed
    on, and one from sharpened starts (``--sharpen``, ``--revert-sharpen``) holds the sharpening,
    which momentum would apply again. None for other rules, with beta 0, or when
    the previous selection does not name its parent's file."""
    if cfg.merge != "momentum" or not cfg.merge_momentum or previous.get("winner") != "merge":
        return None
    if isinstance(previous.get("merge"), dict) and previous["merge"].get("sharpened_starts"):
        return None  # its branches started sharpened (--sharpen, --revert-sharpen): not a step to repeat
    grand = previous.get("parent")
    if not (isinstance(grand, dict) and isinstance(grand.get("agent"), str)
            and isinstance(grand.get("agent_sha256"), str)):
        return None
    return {"beta": cfg.merge_momentum,
            "from": {"iteration": grand.get("iteration"), "agent": grand["agent"],
                     "agent_sha256": grand["agent_sha256"]}}


def track_best(out: dict, previous: dict, revert_after: int, mean: bool = False) -> dict:
    """Carry the best selection so far (``best``, by score) and the iterations since it
    (``since_best``) from ``previous`` to ``out``; revert to the best after ``revert_after`` of them.

    The candidate is the selected agent, or, when the selection is a merge (scored only in the
    next iteration), the best agent the iteration evaluated (``evaluated``); after a merge that
    agent is also the ``fallback`` the next iteration re-scores.

    With ``mean`` (``--best-score mean``) the best ranks by ``mean_score``: the mean of its first
    score and of every later re-score of it as the parent (``scores`` of them in all). A best
    whose first score was the luck of its iteration's episodes sinks towards what it is worth, so
    a later agent can take its place and a revert goes back to an agent that earned its rank.
    ``score`` and ``eval_return`` stay the first ones. A new agent enters with one score; the
    agent the pool keeps or reverts to is not a new one (its re-score is already counted).
    """
    best = previous.get("best")
    if not isinstance(best, dict):
        best = None
    parent = out.get("parent") or {}
    if mean and best is not None and parent.get("agent_sha256") == best["agent_sha256"] \
            and parent.get("score") is not None:
        n = int(best.get("scores") or 1)
        total = best.get("score_sum", best["score"]) + parent["score"]
        if math.isfinite(total):  # two huge finite scores can sum to inf, which JSON cannot hold
            best = best | {"scores": n + 1, "score_sum": total, "mean_score": total / (n + 1)}
    cand = out.get("evaluated") or out
    score = cand.get("score")
    rank = None if best is None else best.get("mean_score", best["score"]) if mean else best["score"]
    if score is not None and (best is None or (score > rank and not (
            mean and cand.get("agent_sha256") == best["agent_sha256"]))):
        out["best"] = {"iteration": out["iteration"], "eval_return": cand["eval_return"], "score": score,
                       "agent": cand["agent"], "agent_sha256": cand["agent_sha256"]}
        if mean:
            out["best"] |= {"scores": 1, "score_sum": score, "mean_score": score}
        out["since_best"] = 0
        return _with_fallback(out)
    out["best"] = best
    out["since_best"] = int(previous.get("since_best") or 0) + 1
    if revert_after and out["best"] is not None and out["since_best"] >= revert_after \
            and out["agent_sha256"] != best["agent_sha256"]:
        out["instead"] = {k: out.get(k) for k in ("winner", "member", "eval_return", "score")}
        out |= {"winner": "revert", "member": None, "eval_return": best["eval_return"], "score": best["score"],
                "agent": best["agent"], "agent_sha256": best["agent_sha256"],
                "reverted_to": best["iteration"], "since_best": 0}
        out.pop("merge", None)
        out.pop("evaluated", None)
    return _with_fallback(out)


def _with_fallback(out: dict) -> dict:
    """After a merge, the agent the next iteration re-scores beside it: the best one evaluated."""
    if out.get("winner") == "merge":
        ev = out["evaluated"]
        out["next_fallback"] = {"agent": ev["agent"], "agent_sha256": ev["agent_sha256"],
                                "member": ev["member"], "iteration": out["iteration"]}
    return out
