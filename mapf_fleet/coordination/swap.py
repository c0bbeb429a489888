"""lacam3's swap test (Okumura, "Engineering LaCAM*", AAMAS 2024), shared by the shield's PIBT
(`pibt.PIBTShield`, the `_swap` rules) and LaCAM's successor generator (`lacam.LaCAM(swap=True)`):
which agent, if any, an agent must trade places with this step. Plain Python on flat cell ids
(no numpy): it runs inside both search loops."""

from __future__ import annotations


def _free_degree(cell: int, came_from: int, occupied_now: dict[int, int], neighbors, goal_flat):
    """(number of ways on from `cell` other than back to `came_from`, one of them): a dead end
    holding an agent on its goal counts as a wall, as in lacam3."""
    ways, other = 0, -1
    for u in neighbors[cell]:
        if u == came_from:
            continue
        j = occupied_now.get(u, -1)
        if j >= 0 and len(neighbors[u]) == 1 and goal_flat[j] == u:
            continue
        ways += 1
        other = u
    return ways, other


def _swap_required(d_push, d_pull, v_pusher: int, v_puller: int, occupied_now: dict[int, int],
                   neighbors, goal_flat) -> bool:
    """Must the pusher (at v_pusher, distances d_push) and the puller (at v_puller, d_pull)
    trade places? Walk on from v_puller while it gets the pusher closer: a branch on the way
    lets them pass without a swap; else a swap is required when the puller wants v_pusher and
    the pusher wants on."""
    while d_push[v_puller] < d_push[v_pusher]:
        ways, nxt = _free_degree(v_puller, v_pusher, occupied_now, neighbors, goal_flat)
        if ways >= 2:
            return False  # a branch: they can pass each other there
        if ways <= 0:
            break
        v_pusher, v_puller = v_puller, nxt
    return (d_pull[v_pusher] < d_pull[v_puller]
            and (d_push[v_pusher] == 0 or d_push[v_puller] < d_push[v_pusher]))


def _swap_possible(v_pusher_origin: int, v_puller_origin: int, occupied_now: dict[int, int],
                   neighbors, goal_flat) -> bool:
    """Is there a branch behind v_puller_origin (walking away from v_pusher_origin) where the
    pair can trade places?"""
    v_pusher, v_puller = v_pusher_origin, v_puller_origin
    while v_puller != v_pusher_origin:  # round a ring corridor: no branch
        ways, nxt = _free_degree(v_puller, v_pusher, occupied_now, neighbors, goal_flat)
        if ways >= 2:
            return True
        if ways <= 0:
            return False
        v_pusher, v_puller = v_puller, nxt
    return False


def swap_partner(i: int, target: int, here: int, occupied_now: dict[int, int], decided,
                 neighbors, goal_flat, distances) -> int:
    """The agent that agent i (at flat `here`, first candidate `target`) must swap with this
    step (-1: none): lacam3's `is_swap_required_and_possible`, asked only when `target` takes i
    closer to its goal. decided: next cell per agent (-1 undecided); neighbors: free neighbour
    cells per flat cell; goal_flat: goal cell per agent; distances(agent): its BFS distance per
    flat cell.

    Why only then: swap's test reasons with BFS distances, as a distance-ranked PIBT would act
    (lacam3's). Under a distance ranking an agent off its goal always ranks a closer cell first,
    so plain PIBT's swap is lacam3's unchanged; a ranking whose first choice is a wait or a
    step away (a learned policy's, a kept plan's labels) made that choice itself, and reversing
    it broke plans the rule should let through (docs/results.md, "The expert ceiling")."""
    d_i = distances(i)
    if not d_i[target] < d_i[here]:
        return -1
    j = occupied_now.get(target, -1)
    if j >= 0 and j != i and decided[j] < 0:
        if (_swap_required(distances(i), distances(j), here, target, occupied_now, neighbors,
                           goal_flat)
                and _swap_possible(target, here, occupied_now, neighbors, goal_flat)):
            return j
    if target != here:  # clear: a neighbour that will have to swap with i one step ahead
        for u in neighbors[here]:
            k = occupied_now.get(u, -1)
            if (k >= 0 and u != target  # decided or not, as lacam3 (the pull checks)
                    and _swap_required(distances(k), d_i, here, target, occupied_now, neighbors,
                                       goal_flat)
                    and _swap_possible(target, here, occupied_now, neighbors, goal_flat)):
                return k
    return -1


__all__ = ["swap_partner"]
