"""Typed method parameters, strict uniforms, and the Renderer that owns every cache."""

import dataclasses
import gc
import weakref

import numpy as np
import pytest

import surfel
from conftest import requires_gl
from models import SPOT
from surfel.camera import frame
from surfel.cloud import PointCloud
from surfel.errors import SurfelError
from surfel.gl.program import declared_uniforms
from surfel.methods import METHODS, get_method
from surfel.options import RenderOptions, SettingError
from surfel.rendering import Renderer


def small_cloud(n: int = 400) -> PointCloud:
    """A jittered plane without normals or radii: rendering it estimates both."""
    rng = np.random.default_rng(3)
    return PointCloud(np.column_stack([rng.uniform(-1, 1, (n, 2)), rng.normal(0, 1e-3, n)]))


def test_every_method_declares_one_frozen_parameter_class():
    for method in METHODS.values():
        params = method.make_params()
        assert isinstance(params, method.params_class())
        with pytest.raises(dataclasses.FrozenInstanceError):
            params.radius_scale = 2.0


def test_the_ewa_filter_default_is_each_method_s_own():
    assert get_method("deferred").make_params().ewa_filter is True
    assert get_method("gaussian").make_params().ewa_filter is False
    assert get_method("phong").make_params().ewa_filter is False
    assert not get_method("points").uses("ewa_filter") and not get_method("ewa").uses("ewa_filter")


@pytest.mark.parametrize("values, message", [
    ({"normalisation": "per-surfel"}, "no setting 'normalisation'; it has: radius_scale, depth_offset"),
    ({"normalization": "per-vertex"}, "normalization: must be one of per-pixel, per-surfel"),
    ({"radius_scale": "big"}, "radius_scale: must be a number"),
    ({"radius_scale": True}, "radius_scale: must be a number"),
    ({"backface_culling": 1}, "backface_culling: must be true or false"),
    ({"depth_offset": float("nan")}, "depth_offset: must be a number >= 0"),
])
def test_parameters_refuse_unknown_names_wrong_types_and_bad_values(values, message):
    with pytest.raises(SettingError, match=message):
        get_method("object-space").make_params(values)


def test_render_options_check_their_values():
    with pytest.raises(SettingError, match="shading"):
        RenderOptions(shading="glossy")
    with pytest.raises(SettingError, match="lod_error"):
        RenderOptions(lod_error=0.0)
    assert RenderOptions(background=(0, 1, 0)).background == (0.0, 1.0, 0.0)


def test_render_takes_options_and_parameters_by_keyword_and_refuses_the_rest():
    cloud = small_cloud()
    with pytest.raises(SurfelError, match="method 'phong' has no option 'normalization'"):
        surfel.render(cloud, method="phong", normalization="per-surfel")
    with pytest.raises(SurfelError, match="does not use lod_error"):
        surfel.render(cloud, method="mls", lod_error=1.0)
    with pytest.raises(SurfelError, match="takes MlsParams"):
        surfel.render(cloud, method="mls", options=RenderOptions(params=get_method("mls-gpu").make_params()))


def test_declared_uniforms_of_a_source():
    source = """
    uniform float u_a;            // a comment naming uniform float u_fake;
    uniform sampler2D u_b, u_c;
    /* uniform int u_hidden; */
    #ifdef PASS_X
    uniform vec4 u_d[2];
    #endif
    """
    assert declared_uniforms(source) == {"u_a", "u_b", "u_c", "u_d"}


@requires_gl
def test_uniforms_the_source_lacks_raise_and_optimised_away_ones_are_skipped(tmp_path):
    from surfel.gl.program import build_program, set_uniforms

    shader = tmp_path / "tiny.glsl"
    shader.write_text("""
    uniform float u_used;
    uniform float u_unused;   // read by no stage: the compiler removes it
    #ifdef VERTEX_SHADER
    void main() { gl_Position = vec4(u_used); }
    #endif
    #ifdef FRAGMENT_SHADER
    out vec4 color;
    void main() { color = vec4(1.0); }
    #endif
    """)
    program = build_program(shader)
    set_uniforms(program, u_used=2.0, u_unused=3.0)
    assert program["u_used"].value == 2.0 and "u_unused" not in program
    with pytest.raises(KeyError, match="u_usde"):
        set_uniforms(program, u_usde=1.0)
    program.release()


def test_a_renderer_keeps_what_it_derives_once_per_cloud_and_lets_go_with_the_cloud():
    cloud = small_cloud()
    renderer = Renderer()
    completed, report = renderer.complete(cloud)
    assert "normals" in str(report) and renderer.complete(cloud)[0] is completed  # estimated once
    assert Renderer().complete(cloud)[0] is not completed  # another renderer, its own caches
    already = completed
    assert renderer.complete(already)[0] is already  # nothing to estimate: nothing kept
    gone = weakref.ref(cloud)
    del cloud, completed, already, report
    gc.collect()
    assert gone() is None  # the renderer held the cloud weakly


def test_a_versioned_entry_keeps_only_the_latest_version():
    """How the Renderer keeps the last LOD subset of a cloud: one per view, the latest only."""
    cloud, renderer, made = small_cloud(), Renderer(), []

    def make():
        made.append(object())
        return made[-1]

    first = renderer.cached(cloud, "subset", make, version="view 1")
    assert renderer.cached(cloud, "subset", make, version="view 1") is first
    second = renderer.cached(cloud, "subset", make, version="view 2")
    assert second is not first and renderer.cached(cloud, "subset", make, version="view 1") is not first
    assert len(made) == 3


@requires_gl
def test_renders_through_a_renderer_match_and_outlive_close():
    cloud = small_cloud()
    camera = frame(np.zeros(3), 1.5, size=(48, 48))
    renderer = Renderer()
    first = renderer.render(cloud, camera, "deferred", shading="lambert")
    again = renderer.render(cloud, camera, "deferred", shading="lambert")
    renderer.close()
    after_close = renderer.render(cloud, camera, "deferred", shading="lambert")
    fresh = Renderer().render(cloud, camera, "deferred", shading="lambert")
    assert first.alpha.mean() > 0.2
    for other in (again, after_close, fresh):
        np.testing.assert_array_equal(first.color, other.color)
    renderer.close()


@requires_gl
def test_the_viewer_renders_gaussian_as_the_command_line_does():
    """The viewer used to force the EWA filter on: gaussian looked different there."""
    from surfel.request import parse_render
    from surfel.viewer import ViewState

    cloud = surfel.load(SPOT)
    state = ViewState(cloud, "gaussian", "lambert")
    viewed, _ = state.render((64, 64))
    request = parse_render({"input": "spot.obj", "output": "x.png", "method": "gaussian", "shading": "lambert"})
    assert request.options.params.ewa_filter is False
    commanded = Renderer().render(cloud, state.camera((64, 64)), "gaussian", options=request.options)
    np.testing.assert_array_equal(viewed.color, commanded.color)
    filtered = Renderer().render(cloud, state.camera((64, 64)), "gaussian", shading="lambert", ewa_filter=True)
    assert not np.array_equal(viewed.color, filtered.color)  # the filter does change the picture
