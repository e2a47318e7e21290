"""Compiling a CPU render's kernels in a helper process while the cloud is completed
(surfel.compile_ahead): what starts the helper, that it renders, and that it compiles every
kernel the real render then needs."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

import surfel.rendering
from models import DATA, spot
from surfel.compile_ahead import CompileAhead, render_spec
from surfel.methods import get_method
from surfel.rendering import Renderer
from test_compile_notice import fresh_kernel


def phong_spec() -> str:
    return render_spec("phong", get_method("phong").make_params(), clip=True, width=64, height=48,
                       shading="phong", supersample=None)


def test_a_preprocessing_kernel_compiling_starts_one_helper_which_renders():
    with CompileAhead(phong_spec()) as ahead:
        with ahead.watching():
            fresh_kernel("surfel.methods.probe")(1)  # a method's own kernel: this process compiles it
            assert ahead.helper is None
            fresh_kernel("surfel.preprocess.probe")(1)
            helper = ahead.helper
            assert helper is not None
            fresh_kernel("surfel.preprocess.probe")(1)
            assert ahead.helper is helper
        fresh_kernel("surfel.preprocess.probe")(1)  # no longer watched
        ahead.wait()
    assert helper.returncode == 0  # the synthetic render went through


def test_no_helper_without_a_spec_and_none_left_running_after_a_failure():
    with CompileAhead(None) as ahead, ahead.watching():  # the GL backend's
        fresh_kernel("surfel.preprocess.probe")(1)
        assert ahead.helper is None
    with pytest.raises(RuntimeError), CompileAhead(phong_spec()) as ahead:
        with ahead.watching():
            fresh_kernel("surfel.preprocess.probe")(1)
        helper = ahead.helper
        raise RuntimeError("the completion failed")
    assert helper.poll() is not None and ahead.helper is None


@pytest.mark.parametrize("switch, backend, spec", [(True, "cpu", True), (False, "cpu", False), (True, "gl", False)])
def test_the_renderer_compiles_ahead_on_the_cpu_unless_switched_off(monkeypatch, switch, backend, spec):
    specs = []

    class Recorded(CompileAhead):
        def __init__(self, given):
            specs.append(given)
            super().__init__(given)

    monkeypatch.setattr(surfel.rendering, "CompileAhead", Recorded)
    Renderer(compile_ahead=switch).render(spot(), None, "phong", backend=backend, size=(64, 48))
    assert len(specs) == 1 and (specs[0] is not None) == spec
    if spec:
        assert json.loads(specs[0])["method"] == "phong" and json.loads(specs[0])["size"] == [64, 48]


# In a fresh interpreter (no kernel loaded yet): where the render would wait for the helper, the
# helper's synthetic render runs in this process instead; every surfel kernel signature loaded
# after it, by the real render, is one the helper did not compile.
PROBE = """
import json, sys
from numba.core.registry import CPUDispatcher
import surfel.compile_ahead
from surfel.compile_ahead_worker import compile_for
from surfel.io import load
from surfel.rendering import Renderer

def signatures():
    return {f"{name}.{attr}": set(map(str, value.overloads))
            for name, module in list(sys.modules.items()) if name.startswith("surfel.")
            for attr, value in list(vars(module).items()) if isinstance(value, CPUDispatcher)}

before = {}
def wait(ahead):
    if not waited:  # the real render's wait (the synthetic render's own comes within it)
        waited.append(ahead)
        compile_for(json.loads(ahead.spec))
        before.update(signatures())
waited = []
surfel.compile_ahead.CompileAhead.wait = wait

path, method, drop_normals = sys.argv[1], sys.argv[2], sys.argv[3] == "1"
cloud = load(path)
cloud = cloud.take(slice(0, len(cloud)))  # a mesh's vertices
if drop_normals:
    cloud = cloud.with_(normals=None)
Renderer().render(cloud, None, method, backend="cpu", size=(96, 80))
after = signatures()
assert waited
print(json.dumps({name: sorted(found - before.get(name, set())) for name, found in after.items()
                  if found - before.get(name, set())}))
"""


@pytest.mark.parametrize("path, method, drop_normals", [
    ("spot.obj", "phong", True),         # the demo's method, on positions only
    ("spot.obj", "gaussian", False),     # given normals
    ("spot.obj", "ewa", True),
    ("spot.obj", "mls", True),
    ("autzen_trim.laz", "deferred", False),  # a LiDAR tile: eye-dome lighting
])
def test_the_helper_compiles_every_kernel_the_render_needs(path, method, drop_normals):
    run = subprocess.run([sys.executable, "-c", PROBE, str(DATA / path), method, "1" if drop_normals else "0"],
                         capture_output=True, text=True, timeout=900)
    assert run.returncode == 0, run.stderr[-2000:]
    assert json.loads(run.stdout.strip().splitlines()[-1]) == {}
