"""surfel.show's widget: frames rendered by the kernel, in JupyterLab under headless Chromium."""

import json
import os
import secrets
import socket
import subprocess
import sys
import time
import urllib.request

import numpy as np
import pytest

from browser import png_rgb
from conftest import requires_gl

pytest.importorskip("jupyter_rfb", reason="the notebook extra (jupyter_rfb) is not installed")
pytest.importorskip("ipywidgets", reason="the notebook extra (ipywidgets) is not installed")


def mean_change(a, b):
    return float(np.abs(a.astype(int) - b.astype(int)).mean())


@requires_gl
def test_widget_frames_follow_the_mouse_and_the_controls():
    """Without a frontend: events in, frames out, coarse while moving, full when settled."""
    from surfel.data import demo_cloud
    from surfel.widget import make_view

    widget = make_view(demo_cloud(), size=(320, 240))
    frames = widget.frames
    first = frames.get_frame()
    assert first.shape == (240, 320, 3) and first.max() > 0
    frames.handle_event({"type": "pointer_down", "x": 100, "y": 100, "button": 1, "modifiers": ()})
    frames.handle_event({"type": "pointer_move", "x": 160, "y": 110, "button": 1, "modifiers": ()})
    moving = frames.get_frame()
    assert moving.shape == (120, 160, 3) and frames.last_stats["moving"]
    frames.handle_event({"type": "pointer_up", "x": 160, "y": 110, "button": 1, "modifiers": ()})
    frames.settle()
    turned = frames.get_frame()
    assert turned.shape == first.shape and mean_change(turned, first) > 2
    method, color = widget.children[0].children[:2]
    color.value = "elevation"
    recolored = frames.get_frame()
    assert mean_change(recolored, turned) > 2 and "splats" in widget.children[2].value
    method.value = "points"
    assert mean_change(frames.get_frame(), recolored) > 0.5 and frames.last_stats["method"] == "points"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def jupyter_lab(tmp_path):
    pytest.importorskip("jupyterlab", reason="the test extra installs jupyterlab")
    port, token = free_port(), secrets.token_hex(16)
    notebook = {"cells": [{"cell_type": "code", "execution_count": None, "id": "show", "metadata": {}, "outputs": [],
                           "source": ["import surfel\n", "from surfel.data import demo_cloud\n",
                                      "view = surfel.show(demo_cloud(), size=(320, 240))\n", "view"]}],
                "metadata": {"kernelspec": {"display_name": "Python 3", "language": "python", "name": "python3"}},
                "nbformat": 4, "nbformat_minor": 5}
    (tmp_path / "view.ipynb").write_text(json.dumps(notebook))
    env = {**os.environ, "JUPYTER_CONFIG_DIR": str(tmp_path / "config"), "JUPYTER_DATA_DIR": str(tmp_path / "data"),
           "JUPYTER_RUNTIME_DIR": str(tmp_path / "runtime")}
    server = subprocess.Popen(
        [sys.executable, "-m", "jupyterlab", "--no-browser", "--allow-root", "--ip=127.0.0.1", f"--port={port}",
         f"--IdentityProvider.token={token}", f"--ServerApp.root_dir={tmp_path}", "--LabApp.news_url=",
         "--LabApp.check_for_updates_class=jupyterlab.NeverCheckForUpdate", "--LabApp.extension_manager=readonly"],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env)
    url = f"http://127.0.0.1:{port}"
    try:
        for _ in range(120):
            try:
                urllib.request.urlopen(f"{url}/api/status?token={token}", timeout=2)
                break
            except OSError:
                if server.poll() is not None:
                    pytest.fail(f"jupyter lab exited: {server.stderr.read().decode()[-2000:]}")
                time.sleep(0.5)
        yield f"{url}/lab/tree/view.ipynb?token={token}"
    finally:
        server.terminate()
        try:
            server.wait(timeout=20)
        except subprocess.TimeoutExpired:
            server.kill()
            server.wait()


@requires_gl
def test_surfel_show_in_jupyterlab_is_an_interactive_view(browser, jupyter_lab):
    """A notebook calls surfel.show; dragging on the view it displays changes its frames."""
    page = browser.new_page()
    page.set_viewport_size({"width": 1000, "height": 800})
    page.goto(jupyter_lab)
    cell = page.locator(".jp-Cell .jp-InputArea-editor").first
    cell.wait_for(timeout=120_000)
    page.wait_for_function("() => document.body.innerText.includes('| Idle')", timeout=120_000)  # kernel ready
    cell.click()
    page.keyboard.press("Shift+Enter")
    view = page.locator("img.renderview-view").first
    view.wait_for(timeout=180_000)
    page.wait_for_function("() => { const v = document.querySelector('img.renderview-view');"
                           " return v && v.naturalWidth > 0; }", timeout=180_000)
    page.wait_for_timeout(1500)  # the lossless frame after the first one
    before = png_rgb(view.screenshot())
    assert before.max() > 0
    source = view.get_attribute("src")
    box = view.bounding_box()
    x, y = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
    page.mouse.move(x, y)
    page.mouse.down()
    for step in range(1, 8):
        page.mouse.move(x + 12 * step, y + 3 * step)
        page.wait_for_timeout(50)
    page.mouse.up()
    page.wait_for_function(f"() => document.querySelector('img.renderview-view').src !== {json.dumps(source)}",
                           timeout=120_000)
    page.wait_for_timeout(2000)  # settled: the full frame
    after = png_rgb(view.screenshot())
    assert mean_change(after, before) > 2
    assert "splats" in page.locator(".widget-label").last.inner_text()
    page.close()


@requires_gl
def test_widget_streams_a_copc_file_coarser_while_moving():
    from pathlib import Path

    from surfel.lod import open_source
    from surfel.widget import make_view

    source = open_source(Path(__file__).parent / "data" / "simple_with_page.copc.laz")
    widget = make_view(source, size=(200, 160))
    frames = widget.frames
    still = frames.get_frame()
    assert still.shape == (160, 200, 3) and still.max() > 0
    splats = frames.last_stats["splats"]
    frames.handle_event({"type": "wheel", "x": 100, "y": 80, "dx": 0, "dy": 0, "modifiers": ()})
    frames.get_frame()
    assert frames.last_stats["moving"] and frames.last_stats["splats"] < splats
    assert frames.last_stats["lod"] > 1.0  # the coarser error of moving frames
