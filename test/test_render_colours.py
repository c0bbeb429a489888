"""`mapf-fleet render` draws each robot in the colour `mapf-fleet view` gives it, with its number
(issue 40, item 8: the two coloured the same robot differently and render had no numbers)."""

from __future__ import annotations

import numpy as np

from mapf_fleet.evaluation.render import draw_frames
from mapf_fleet.view.picture import FleetPicture


def _frame(n=3):
    grid = np.zeros((5, 5), dtype=np.uint8)
    positions = np.array([[[0, 0], [4, 4], [2, 2]][:n]])
    goals = np.array([[0, 4], [4, 0], [3, 1]][:n])
    return next(iter(draw_frames(grid, goals, positions, np.zeros((0, n), bool), "t")))


def test_each_robot_has_the_web_views_colour_and_its_number():
    picture = FleetPicture()
    picture.set_state(1, 0, np.array([[0, 0], [4, 4], [2, 2]]), np.array([[0, 4], [4, 0], [3, 1]]))
    page = picture.snapshot()["colours"]  # what the web page draws with
    frame = _frame().astype(int)
    for i, hexcolour in enumerate(page):
        rgb = [int(hexcolour[k:k + 2], 16) for k in (1, 3, 5)]
        disc = (np.abs(frame - rgb) <= 2).all(axis=2)
        assert disc.sum() > 50, f"robot {i}'s colour {hexcolour} is not in the render"
        rows, cols = np.nonzero(disc)
        inside = frame[rows.min():rows.max() + 1, cols.min():cols.max() + 1]
        assert (inside.max(axis=2) < 90).sum() > 5, f"robot {i} has no number on its disc"
