"""`surfel view`: key handling, and a real window under Xvfb."""

import shutil
import subprocess
import sys

import numpy as np
import pytest

from conftest import requires_gl
from models import SPOT
from surfel.io import load
from surfel.viewer import HELP, ViewState


def test_the_help_shows_the_mouse_and_the_keys():
    """The help drawn over the frames is the docstring's key table, not another paragraph."""
    assert HELP[0].startswith("mouse:") and any("h: help" in line for line in HELP)
    assert any(line.startswith("1-9") for line in HELP) and len(HELP) == 6


def test_keys_change_the_view_state():
    state = ViewState(load(SPOT), "deferred", "phong")
    assert state.ewa_filter_on() is True  # deferred's own default, as on the command line
    assert state.key("3") and state.method == state.methods[2] == "gaussian"
    assert state.ewa_filter_on() is False  # gaussian's: the viewer forces nothing
    assert state.key("e") and state.ewa_filter_on() is True
    assert state.key("2") and state.method == "points" and state.ewa_filter_on() is None
    assert state.key("+") and state.lod_error == 1.0
    assert state.key("+") and state.lod_error == 2.0
    assert state.key("-") and state.key("-") and state.lod_error == 0.0
    assert state.key("s") and state.shading != "phong"
    state.azimuth = 40.0
    assert state.key("r") and state.azimuth == 0.0
    assert state.key("q") is False


@requires_gl
@pytest.mark.skipif(shutil.which("xvfb-run") is None, reason="Xvfb is not installed")
def test_screenshot_from_a_real_window_under_xvfb(tmp_path):
    pytest.importorskip("glfw")
    from PIL import Image

    out = tmp_path / "shot.png"
    proc = subprocess.run(["xvfb-run", "-a", "-s", "-screen 0 800x600x24", sys.executable, "-m", "surfel.cli",
                           "view", str(SPOT), "--screenshot", str(out),
                           "--size", "320x240"], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    image = np.asarray(Image.open(out).convert("L")).astype(float)
    assert image.shape == (240, 320)
    middle = image[60:180, 80:240]
    assert (middle > 100).mean() > 0.2  # the lit cow fills the middle of the window
    assert (image[0:16] > 128).any()     # the status line is drawn across the top


@requires_gl
@pytest.mark.skipif(shutil.which("xvfb-run") is None, reason="Xvfb is not installed")
def test_a_tile_opens_obliquely_across_the_window(tmp_path):
    """A geospatial tile: the whole tile seen from above the horizon, filling the window's
    width (not a sliver at ground level), in elevation colours."""
    pytest.importorskip("glfw")
    from pathlib import Path

    from PIL import Image

    tile = Path(__file__).parent / "data" / "autzen_trim.laz"
    out = tmp_path / "shot.png"
    proc = subprocess.run(["xvfb-run", "-a", "-s", "-screen 0 800x600x24", sys.executable, "-m", "surfel.cli",
                           "view", str(tile), "--screenshot", str(out), "--size", "400x300", "--color", "elevation"],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    image = np.asarray(Image.open(out).convert("RGB")).astype(int)
    drawn = image[20:165].max(axis=2) > 30  # between the status line and the help
    columns = np.flatnonzero(drawn.any(axis=0))
    rows = np.flatnonzero(drawn.any(axis=1))
    assert (columns[-1] - columns[0] + 1) / 400 > 0.7 and len(rows) > 30  # across the window, seen from above
    assert len(np.unique(image[20:165][drawn] // 32, axis=0)) > 8  # a colour ramp, not one colour


@requires_gl
def test_a_moving_camera_draws_coarser_until_it_stops():
    """While the camera moves, frames are drawn at half resolution, and coarser while slower
    than the motion budget; the still frame afterwards is whole again."""
    from models import dense_spot

    state = ViewState(dense_spot(), "points", "lambert", motion_frame_ms=1e-3)  # every frame is slow
    still, _ = state.render((160, 120))
    assert state.motion_error == 2.0  # a slow still frame: the next movement starts coarse
    state.moving = True
    first, _ = state.render((160, 120))
    second, _ = state.render((160, 120))
    assert first.alpha.shape == (60, 80)  # half the window's resolution while moving
    assert first.stats["splats"] < still.stats["splats"] / 2
    assert second.stats["splats"] < first.stats["splats"]  # still slow: coarser again
    state.moving = False
    again, _ = state.render((160, 120))
    assert again.stats["splats"] == still.stats["splats"]
    covered = still.alpha[::2, ::2] > 0.5
    assert (first.alpha[covered] > 0.5).mean() > 0.9  # coarser, not full of holes


def test_phong_supersamples_still_frames_only():
    """phong's still frames take its 2x2 samples a pixel; a moving camera's take one, so that
    a dragged frame costs what it did before."""
    from models import dense_spot

    state = ViewState(dense_spot(), "phong", "lambert")
    still, _ = state.render((160, 120))
    state.moving = True
    moving, _ = state.render((160, 120))
    assert (still.stats["supersample"], moving.stats["supersample"]) == (2, 1)
