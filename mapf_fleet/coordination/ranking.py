"""Rankings (each agent's five actions ranked, best first) from any decentralized policy.

Everything here reads only what a robot has on board: its 9x9 observation (channel 1 obstacles,
channels 2..5 the heuristic bits "this move gets strictly closer to my goal", DHC order up, down,
left, right) and, for a learned policy, its five Q-values. On a 4-connected grid a move changes
the BFS distance to the goal by exactly one, so the heuristic bits at the centre cell give the
whole distance order: closer moves, then staying, then moves away, then blocked moves (an
obstacle or off the map). An agent with no closer move stands on its goal.

A robot publishes its whole ranking, moves into occupied cells included: PIBT decides who
yields, and an agent that ranks "stay" first whenever its closer cell is occupied never pushes
(the non-learned heuristic's failure under the shield).

Rankings (`RANKINGS`; `Q_RANKINGS` those that read Q-values):
  q               the actions by descending Q (ties: action order) — CS-PIBT as published
  q_demote_stay   the Q order, but an agent off its goal ranks "stay" below every move that
                  gets closer
  q_then_distance the argmax of Q first, then the rest in the distance order (ties broken by
                  `ties` when given, else by Q)
  confidence      the argmax of Q first only where it leads the runner-up by more than
                  `margin` (`CONFIDENCE_MARGIN` unless given), then the distance order; an agent
                  whose Q-values are that close ranks by the distance order alone (ties by `ties`,
                  then Q): the network overrides plain PIBT only where it is sure
  distance_q      the distance order, its ties broken by Q (then `ties`): a learned tie-breaker
                  inside plain PIBT; the network only chooses among equally close moves (which
                  of two closer cells, which way to step aside), never a wait over a closer move
  distance        the distance order, ties by action order: plain PIBT (no learning); also the
                  non-learned heuristic's ranking (it follows a closer move, else stays)
`default_ranking(rule, recorded)` is the ranking a learned policy uses under each rule when none
is asked for, in the evaluator and the fleet's policy nodes alike: the ranking its checkpoint
records for the rule (metadata `rankings`, e.g. what a DAgger round was trained under), else the
rule's own (`rules.Rule.default_ranking`: `confidence` under an anchor, `q` otherwise).
"""

from __future__ import annotations

from typing import Mapping

import numpy as np

from mapf_fleet.grid.actions import ACTION_DELTAS, NUM_ACTIONS, STAY

from .rules import PIBT_RULES, UNANCHORED_RANKING, Rule

RANKINGS = ("q", "q_demote_stay", "q_then_distance", "confidence", "distance_q", "distance")
Q_RANKINGS = ("q", "q_demote_stay", "q_then_distance", "confidence", "distance_q")
DEFAULT_RANKING = UNANCHORED_RANKING
# The ranking each PIBT rule uses by default, derived from the rule (`Rule.default_ranking`; the
# planning arbiter takes its fallback rule's)
DEFAULT_RANKING_BY_RULE = {name: Rule.parse(name).default_ranking for name in PIBT_RULES}
# `confidence`: the Q lead of the argmax over the runner-up above which the network's choice goes
# first (Q units: one step costs 0.075); chosen on generated maps, never the published sets
# (docs/results.md, "Which ranking under which rule").
CONFIDENCE_MARGIN = 0.3


def default_ranking(rule: "Rule | str", recorded: Mapping[str, str] | None = None) -> str:
    """The ranking a learned policy uses under `rule` when none is asked for: the one its
    checkpoint records for the rule (`recorded`, the metadata's `rankings` {rule: mode}; see
    `recorded_ranking`), else the rule's own (`Rule.default_ranking`). A checkpoint trained on the
    states one ranking visits does best under that ranking (docs/results.md, "Which ranking
    under which rule")."""
    found = recorded_ranking(rule, recorded)
    return found if found is not None else Rule.parse(rule).default_ranking


def recorded_ranking(rule: "Rule | str", recorded: Mapping[str, str] | None) -> str | None:
    """The ranking a checkpoint records for exactly `rule`, else None. A ranking recorded for
    one rule is not carried to its variants (swap, hindrance, the planning arbiter): a ranking
    that a policy was trained under for `pibt_anchor` can lose to the variant's own default
    under `pibt_anchor_swap` (docs/results.md, "Which ranking under which rule"), so a variant
    takes `Rule.default_ranking` unless its own ranking was recorded."""
    if not recorded:
        return None
    return recorded.get(Rule.parse(rule).name)


def validate_rankings(rankings, num_agents: int) -> np.ndarray:
    """(N, 5) int64 where each row is a ranking (permutation) of the actions 0..4."""
    prefs = np.asarray(rankings)
    if prefs.shape != (num_agents, NUM_ACTIONS):
        raise ValueError(f"rankings must have shape ({num_agents}, {NUM_ACTIONS}), "
                         f"got {prefs.shape}")
    if prefs.size and not np.issubdtype(prefs.dtype, np.integer):
        raise ValueError(f"rankings must be integer actions, got dtype {prefs.dtype}")
    prefs = prefs.astype(np.int64, copy=False)
    bad = (np.sort(prefs, axis=1) != np.arange(NUM_ACTIONS)).any(axis=1)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise ValueError(f"agent {i}: ranking {prefs[i].tolist()} is not a ranking of the "
                         f"actions 0..{NUM_ACTIONS - 1}")
    return prefs

# distance classes of a move, lower is better
_CLOSER, _STAY, _AWAY, _BLOCKED = 0, 1, 2, 3


def distance_classes(obs) -> np.ndarray:
    """(..., 5) int: per action 0 closer to the goal, 1 stay, 2 away, 3 blocked, from
    observations (..., 6, S, S) (the agent at the centre)."""
    obs = np.asarray(obs)
    if obs.ndim < 3 or obs.shape[-3] < 6 or obs.shape[-1] != obs.shape[-2] or obs.shape[-1] % 2 != 1:
        raise ValueError(f"observations must have shape (..., 6, S, S) with S odd, got {obs.shape}")
    r = obs.shape[-1] // 2
    rows = r + ACTION_DELTAS[:, 0]
    cols = r + ACTION_DELTAS[:, 1]
    blocked = obs[..., 1, rows, cols] > 0  # (..., 5); the centre (stay) is free
    closer = np.zeros(blocked.shape, dtype=bool)
    closer[..., 1:] = obs[..., 2:6, r, r] > 0
    classes = np.where(closer, _CLOSER, _AWAY)
    classes = np.where(blocked, _BLOCKED, classes)
    classes[..., STAY] = _STAY
    return classes.astype(np.int64)


def _rank(keys: list[np.ndarray]) -> np.ndarray:
    """Actions ordered by the keys (lexicographic, first key most significant; the action index
    breaks the remaining ties), per row. keys: arrays of shape (..., 5)."""
    shape = keys[0].shape
    flat = [np.broadcast_to(k, shape).reshape(-1, NUM_ACTIONS) for k in keys]
    action = np.broadcast_to(np.arange(NUM_ACTIONS), flat[0].shape)
    # np.lexsort sorts by the last key first
    order = np.lexsort([action, *reversed(flat)], axis=-1)
    return order.reshape(shape).astype(np.int64)


def tie_breakers(agent_ids, tick: int, seed: int = 0) -> np.ndarray:
    """(..., 5) float64 in [0, 1): a hash of (seed, tick, agent id, action), the same on every
    machine. Breaks ties between equally good moves differently per agent and per tick: with a
    fixed order (always "up" before "right") PIBT livelocks on random maps: ties broken the
    same way at every tick can repeat the same moves forever (docs/results.md, "Tie-breaks
    between equally good moves"; pymapf shuffles its candidates for the same reason)."""
    ids = np.asarray(agent_ids, dtype=np.uint64)[..., None]
    x = (ids * np.uint64(0x9E3779B97F4A7C15)) ^ np.uint64((int(tick) * 0xBF58476D1CE4E5B9 + int(seed)) % 2**64)
    x = x + np.arange(NUM_ACTIONS, dtype=np.uint64) * np.uint64(0x94D049BB133111EB)
    # splitmix64 finaliser
    x = (x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    x = (x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    x = x ^ (x >> np.uint64(31))
    return (x >> np.uint64(11)).astype(np.float64) / float(2**53)


def rank_actions(obs, q=None, mode: str = DEFAULT_RANKING, ties=None,
                 margin: float | None = None) -> np.ndarray:
    """(..., 5) int64 rankings. obs (..., 6, S, S); q (..., 5) for the Q modes;
    `ties` (..., 5) breaks the remaining ties (`tie_breakers`; default: the action order);
    `margin`: the `confidence` mode's threshold (default `CONFIDENCE_MARGIN`)."""
    if mode not in RANKINGS:
        raise ValueError(f"ranking must be one of {RANKINGS}, got {mode!r}")
    classes = distance_classes(obs)
    tail = [] if ties is None else [np.asarray(ties, dtype=np.float64)]
    if mode == "distance":
        return _rank([classes, *tail])
    if q is None:
        raise ValueError(f"ranking {mode!r} needs Q-values")
    q = np.asarray(q, dtype=np.float64)
    if q.shape != classes.shape:
        raise ValueError(f"Q-values must have shape {classes.shape}, got {q.shape}")
    if mode == "q":
        return _rank([-q, *tail])
    if mode == "distance_q":
        return _rank([classes, -q, *tail])
    if mode in ("q_then_distance", "confidence"):
        best = np.argmax(q, axis=-1)[..., None] == np.arange(NUM_ACTIONS)
        if mode == "confidence":
            top2 = np.sort(q, axis=-1)[..., -2:]
            lead = top2[..., 1] - top2[..., 0]
            best &= (lead > (CONFIDENCE_MARGIN if margin is None else float(margin)))[..., None]
        return _rank([~best, classes, *tail, -q])
    # q_demote_stay: stay's Q lowered just below the lowest Q of a closer move (off goal only)
    closer = classes == _CLOSER
    off_goal = closer.any(axis=-1)
    lowest_closer = np.where(closer, q, np.inf).min(axis=-1)
    stay_q = q[..., STAY]
    demoted = off_goal & (stay_q >= lowest_closer)
    q = q.copy()
    q[..., STAY] = np.where(demoted, np.nextafter(lowest_closer, -np.inf), stay_q)
    # a tie with the lowest closer move is won by the move (it comes first in the key order)
    return _rank([-q, (np.arange(NUM_ACTIONS) == STAY), *tail])

