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
