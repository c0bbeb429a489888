"""`mapf-fleet render`: the GIF's frame timing follows --fps; bad --fps is refused."""

import pytest
from PIL import Image

from mapf_fleet.cli import main as mapf_fleet


def _render(out, *extra):
    return mapf_fleet(["render", "--checkpoint", "heuristic", "--size", "10", "--agents", "2",
                       "--seed", "1", "--max-steps", "6", "--out", str(out), *extra])


@pytest.mark.parametrize("fps", [2.0, 4.0, 10.0])
def test_gif_frame_duration_follows_fps(tmp_path, fps):
    out = tmp_path / "ep.gif"
    assert _render(out, "--fps", str(fps)) == 0
    with Image.open(out) as gif:
        durations = []
        for k in range(gif.n_frames):
            gif.seek(k)
            durations.append(gif.info.get("duration", 0))  # absent when 0
    assert len(durations) >= 2
    # GIF stores centiseconds: 1000 / fps ms, to the nearest 10 ms
    assert all(abs(d - 1000.0 / fps) <= 10 for d in durations), durations


@pytest.mark.parametrize("fps", ["0", "-3", "nan"])
def test_bad_fps_is_refused(tmp_path, fps, capsys):
    assert _render(tmp_path / "ep.gif", "--fps", fps) == 2
    assert capsys.readouterr().err == f"mapf-fleet render: --fps must be > 0, got {float(fps):g}\n"
    assert not (tmp_path / "ep.gif").exists()


def test_row_0_is_drawn_at_the_bottom_as_in_the_map_frame():
    """The map frame (and RViz, Foxglove, the web view) puts row 0 at the bottom (y grows with
    the row): a building map appears as its image. A map whose row 0 is all obstacles is dark
    at the bottom of the frame, light at the top; the robot on row 3 is in the upper half."""
    import numpy as np

    from mapf_fleet.evaluation.render import draw_frames

    grid = np.zeros((4, 6), dtype=np.uint8)
    grid[0] = 1
    frame = next(draw_frames(grid, np.array([[3, 5]]), np.array([[[3, 0]]]), np.zeros((0, 1)),
                             "t"))
    grey = frame.mean(axis=2)
    dark = grey < 120
    rows = np.flatnonzero(dark.sum(axis=1) > 0.5 * dark.sum(axis=1).max())
    assert np.median(rows) > frame.shape[0] / 2, rows  # the obstacle row: the lower half
    colour = np.abs(frame.astype(int) - frame.mean(axis=2, keepdims=True)).sum(axis=2) > 60
    ys = np.flatnonzero(colour.any(axis=1))
    assert ys.size and np.median(ys) < frame.shape[0] / 2  # robot and goal on row 3: upper half
