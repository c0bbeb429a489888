"""The one PIBT push (Okumura et al., AIJ 2022), shared by the shield's tick (`pibt.PIBTShield`)
and LaCAM's successor generator (`lacam.LaCAM`). Plain Python on flat cell ids: it is the inner
loop of both.

`Push(now, occ_now, occ_next, nxt, candidates, partner_of).funnel(i, caller)` decides agent i's
next cell and returns True, or undoes everything it decided on the way and returns False:
- i takes the first of `candidates(i)` (flat cells, best first) that is free for the next step,
  is not its pusher's (`caller`'s) cell and is not the cell of an agent already moving into i's
  cell (both would be a swap);
- when that cell holds an undecided agent, the occupant inherits the priority and must move
  first (`funnel(occupant, i)`); when it cannot, the sub-chain is undone and the next candidate
  is tried (backtracking);
- swap (lacam3): when `partner_of(i, first candidate)` names an agent i must trade places with,
  i reverses its candidate order and, when it gets the first cell of the reversed order, pulls
  the partner into the cell it leaves (`swap.swap_partner`).

State (shared with the caller, mutated in place): `now[i]` agent i's cell; `occ_now` {cell:
agent} now; `occ_next` {cell: agent} next step (-2: a cell kept free); `nxt[i]` agent i's next
cell, -1 while undecided. The callers own what happens when an unpushed agent gets nothing (the
shield keeps it in place; LaCAM has no successor)."""

from __future__ import annotations

from collections.abc import Callable, Sequence


class Push:
    __slots__ = ("now", "occ_now", "occ_next", "nxt", "candidates", "partner_of", "journal")

    def __init__(self, now: Sequence[int], occ_now: dict[int, int], occ_next: dict[int, int],
                 nxt: list[int], candidates: Callable[[int], list[int]],
                 partner_of: Callable[[int, int], int] | None = None):
        self.now = now
        self.occ_now = occ_now
        self.occ_next = occ_next
        self.nxt = nxt
        self.candidates = candidates
        self.partner_of = partner_of
        self.journal: list[int] = []

    def assign(self, i: int, cell: int) -> None:
        self.occ_next[cell] = i
        self.nxt[i] = cell
        self.journal.append(i)

    def rollback(self, mark: int) -> None:
        journal, nxt, occ_next = self.journal, self.nxt, self.occ_next
        while len(journal) > mark:
            i = journal.pop()
            cell = nxt[i]
            nxt[i] = -1
            if occ_next.get(cell) == i:
                del occ_next[cell]

    def funnel(self, i: int, caller: int) -> bool:
        now, occ_now, occ_next, nxt = self.now, self.occ_now, self.occ_next, self.nxt
        here = now[i]
        ranked = self.candidates(i)
        partner = -1
        if self.partner_of is not None and ranked:
            partner = self.partner_of(i, ranked[0])
            if partner >= 0:
                ranked = ranked[::-1]  # back away, pulling the partner behind
        for k, cell in enumerate(ranked):
            if cell in occ_next:
                continue
            if caller >= 0 and cell == now[caller]:
                continue  # the caller's cell: that would be a swap with it
            other = occ_now.get(cell, -1)
            if other >= 0 and other != i and nxt[other] == here:
                continue  # the occupant already moves into our cell: a swap
            mark = len(self.journal)
            self.assign(i, cell)
            if other >= 0 and other != i and nxt[other] < 0:
                if not self.funnel(other, i):  # the occupant must make room first
                    self.rollback(mark)
                    continue
            if (k == 0 and partner >= 0 and nxt[partner] < 0 and cell != here
                    and here not in occ_next):
                # the pull: the partner (undecided, so neither held nor on a kept-free cell)
                # takes the cell we leave; we did not take its cell (it would be decided
                # then), so nobody trades cells
                self.assign(partner, here)
            return True
        return False


__all__ = ["Push"]
