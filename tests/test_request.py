"""The request layer: every option of every command parsed and checked in one place, before
anything is loaded, rendered or written; each refusal one line on stderr and exit status 2."""

import json
from pathlib import Path

import numpy as np
import pytest

from conftest import assert_refused, invoke, requires_gl
from surfel.errors import SurfelError

COPC = Path(__file__).parent / "data" / "simple_with_page.copc.laz"


def opencv_file(tmp_path, K, R=None):
    path = tmp_path / "camera.json"
    R = np.eye(3) if R is None else R
    path.write_text(json.dumps({"K": np.asarray(K, float).tolist(), "R": np.asarray(R, float).tolist(),
                                "t": [0, 0, 3]}))
    return path


# Issue 15.4: option values that ended in a traceback; checked before the input is even opened,
# so a missing .lod directory or .lod.npz file is never reached.
@pytest.mark.parametrize("source", ["--demo", COPC, "missing.lod", "missing.lod.npz"])
@pytest.mark.parametrize("value", ["0", "-1", "nan"])
def test_lod_error_must_be_positive_on_every_input(tmp_path, source, value):
    source = [source] if source == "--demo" else [tmp_path / source if "missing" in str(source) else source]
    result = invoke("render", *source, "-o", tmp_path / "x.png", "--lod-error", value)
    assert_refused(result, "--lod-error")
    assert not (tmp_path / "x.png").exists()


@pytest.mark.parametrize("flags, named", [
    (["--fov", "0"], "--fov"), (["--fov", "180"], "--fov"), (["--ortho", "0"], "--ortho"),
    (["--azimuth", "inf"], "--azimuth"), (["--elevation", "nan"], "--elevation"), (["--zoom", "0"], "--zoom"),
    (["--size", "0x10"], "--size"), (["--eye", "1,2"], "--eye"), (["--up", "0,0,0"], "--up"),
    (["--eye", "1,1,1", "--target", "1,1,1"], "--eye"),  # a camera on its target looks nowhere
    (["--eye", "0,0,3", "--target", "0,0,0", "--up", "0,0,-1"], "--up"),  # up along the line of sight
])
def test_camera_values_that_cannot_be_honoured(tmp_path, flags, named):
    assert_refused(invoke("render", "--demo", "-o", tmp_path / "x.png", *flags), named)
    assert not (tmp_path / "x.png").exists()


@pytest.mark.parametrize("K, R, problem", [
    (np.eye(2), np.eye(3), "K must be 3x3"),
    ([[0, 0, 16], [0, 100, 16], [0, 0, 1]], np.eye(3), "focal lengths"),           # singular
    ([[np.nan, 0, 16], [0, 100, 16], [0, 0, 1]], np.eye(3), "not finite"),
    ([[100, 0, 16], [0, 100, 16], [0, 0, 1]], np.zeros((3, 3)), "rotation"),
    ([[100, 0, 16], [0, 100, 16], [0, 0, 1]], 2 * np.eye(3), "rotation"),
    ([[100, 0, 16], [0, 100, 16], [0, 0, 1]], np.diag([1.0, 1.0, -1.0]), "rotation"),  # a mirror
])
def test_opencv_cameras_that_are_no_pinhole_camera(tmp_path, K, R, problem):
    path = opencv_file(tmp_path, K, R)
    assert_refused(invoke("render", "--demo", "-o", tmp_path / "x.png", "--opencv", path), "camera.json", problem)
    assert not (tmp_path / "x.png").exists()


@pytest.mark.parametrize("fps", ["0", "nan", "-2"])
def test_turntable_fps_must_be_positive(tmp_path, fps):
    assert_refused(invoke("turntable", "missing.ply", "-o", tmp_path / "t.gif", "--fps", fps), "--fps")


# Issue 15.7: values that rendered a blank or garbage image with exit status 0.
@pytest.mark.parametrize("flags, named", [
    (["--radius-scale", "0"], "--radius-scale"), (["--radius-scale", "-1"], "--radius-scale"),
    (["--radius-scale", "nan"], "--radius-scale"), (["--lowpass-radius", "nan"], "--lowpass-radius"),
    (["--lowpass-radius", "0"], "--lowpass-radius"), (["--depth-offset", "-1"], "--depth-offset"),
    (["--ortho", "-1"], "--ortho"), (["--background", "0,0,2"], "--background"),
    (["--supersample", "0"], "--supersample"), (["--point-budget", "0"], "--point-budget"),
])
def test_values_that_render_nothing_are_refused(tmp_path, flags, named):
    assert_refused(invoke("render", "--demo", "-o", tmp_path / "x.png", *flags), named)
    assert not (tmp_path / "x.png").exists()


# Issue 16.4: an option the chosen method does not use, set explicitly, is refused.
@pytest.mark.parametrize("flags, named, users", [
    (["--shadows"], "--shadows", "mls"),
    (["--method", "mls-gpu", "--reflect"], "--reflect", "mls"),
    (["--method", "phong", "--per-surfel-normalization"], "--per-surfel-normalization", "object-space"),
    (["--method", "mls", "--lod-error", "1"], "--lod-error", "points"),
    (["--method", "points", "--no-ewa-filter"], "--no-ewa-filter", "deferred"),
    (["--method", "mesh", "--radius-scale", "2"], "--radius-scale", "gaussian"),
    (["--method", "ewa", "--backend", "cpu", "--dump-passes", "passes"], "--dump-passes", "cpu"),
])
def test_an_option_the_method_does_not_use_is_refused(tmp_path, flags, named, users):
    assert_refused(invoke("render", "--demo", "-o", tmp_path / "x.png", *flags), named, users)


def test_a_batch_job_with_an_option_its_method_does_not_use_is_refused(tmp_path):
    jobs = tmp_path / "jobs.json"
    jobs.write_text(json.dumps([{"demo": True, "output": str(tmp_path / "a.png"), "method": "phong",
                                 "shadows": True}]))
    assert_refused(invoke("batch", jobs), "jobs.json: job 0", "--shadows", "phong")


def test_camera_options_that_contradict_each_other(tmp_path):
    path = opencv_file(tmp_path, [[100, 0, 16], [0, 100, 16], [0, 0, 1]])
    out = tmp_path / "x.png"
    assert_refused(invoke("render", "--demo", "-o", out, "--opencv", path, "--fov", "40"), "--opencv", "--fov")
    assert_refused(invoke("render", "--demo", "-o", out, "--eye", "0,0,3", "--view", "top"), "--eye", "--view")
    assert_refused(invoke("render", "--demo", "-o", out, "--view", "top", "--azimuth", "10"), "--view", "--azimuth")


# Issue 15.6: every output location is checked first; a render writes all its files or none.
def test_outputs_are_checked_before_anything_is_written(tmp_path):
    png = tmp_path / "a.png"
    result = invoke("render", "--demo", "-o", png, "--depth", tmp_path / "missing" / "d.npy")
    assert_refused(result, "d.npy", "no such directory")
    assert not png.exists()
    (tmp_path / "folder.png").mkdir()
    assert_refused(invoke("render", "--demo", "-o", tmp_path / "folder.png"), "folder.png", "directory")
    assert_refused(invoke("render", "--demo", "-o", png, "--stats", png), "same file")
    assert_refused(invoke("render", "--demo", "-o", tmp_path / "a.jpg"), "a.jpg", ".png")
    assert not png.exists()


# Issue 15.12: one line for click's usage errors; outputs checked before the work.
@pytest.mark.parametrize("args, words", [
    (["render", "--demo", "-o", "x.png", "--colour", "red"], ["--colour"]),
    (["render", "--demo", "-o"], ["-o"]),
    (["turntable", "in.ply"], ["--output"]),
    (["view", "--demo", "--shading", "glossy"], ["--shading", "lambert, phong, none, normals, depth"]),
    (["nonsense"], ["nonsense"]),
])
def test_usage_errors_are_one_line(args, words):
    assert_refused(invoke(*args), *words)


def test_turntable_checks_its_output_before_loading_the_input(tmp_path):
    # the input does not exist: the output's extension is what must be reported
    assert_refused(invoke("turntable", tmp_path / "missing.ply", "-o", tmp_path / "t.avi"), "t.avi", ".gif")
    assert_refused(invoke("turntable", tmp_path / "missing.ply", "-o", tmp_path / "no" / "t.gif"),
                   "no such directory")


def test_lod_build_does_not_create_missing_folders(tmp_path):
    source = tmp_path / "in.xyz"
    source.write_text("0 0 0\n1 0 0\n0 1 0\n")
    for name in ("x.lod", "x.lod.npz", "x.copc.laz"):
        assert_refused(invoke("lod", "build", source, "-o", tmp_path / "missing" / name), "no such directory")
    assert not (tmp_path / "missing").exists()


# Issues 15.13 and 15.5: batch output names, patterns and jobs files.
def test_turntable_frames_in_a_folder_or_by_pattern(tmp_path):
    from surfel.batch import frame_names

    (tmp_path / "frames").mkdir()
    assert frame_names(str(tmp_path / "frames"), 3) == [str(tmp_path / "frames" / f"{i:03d}.png") for i in range(3)]
    assert frame_names(str(tmp_path / "frames"), 2, "depth")[1] == str(tmp_path / "frames" / "001.npy")
    assert frame_names("new/", 2) == ["new/000.png", "new/001.png"]
    assert frame_names("f-{frame:02d}.png", 2) == ["f-00.png", "f-01.png"]
    assert frame_names("spot.png", 1001)[1000] == "spot-1000.png"
    with pytest.raises(SurfelError, match="no such folder"):
        frame_names(str(tmp_path / "absent"), 3)


@pytest.mark.parametrize("pattern", ["f-{frame.real}.png", "f-{frame[0]}.png", "f-{index}.png", "f-{}.png",
                                     "f-{frame.png", "f-{frame:q}.png"])
def test_bad_frame_patterns_are_one_line(tmp_path, pattern):
    assert_refused(invoke("batch", "--demo", "--turntable", 2, "-o", tmp_path / pattern), "--output")


def test_a_jobs_file_that_is_not_utf8(tmp_path):
    jobs = tmp_path / "jobs.json"
    jobs.write_bytes(b'[{"demo": true, "output": "\xff.png"}]')
    assert_refused(invoke("batch", jobs), "jobs.json", "UTF-8")


@requires_gl
def test_a_job_that_cannot_write_fails_alone_and_frames_go_into_a_folder(tmp_path):
    pytest.importorskip("distributed")
    jobs = tmp_path / "jobs.json"
    jobs.write_text(json.dumps([{"demo": True, "output": str(tmp_path / "missing" / "a.png"), "size": "32x32"},
                                {"demo": True, "output": str(tmp_path / "b.png"), "size": "32x32"}]))
    result = invoke("batch", jobs, "--workers", 1, "--json")
    assert result.exit_code == 1, result.output
    summary = json.loads(result.output)
    assert summary["done"] == 1 and [f["job"] for f in summary["failed"]] == [0]
    assert "no such directory" in summary["failed"][0]["error"]
    assert (tmp_path / "b.png").exists() and not (tmp_path / "missing").exists()

    (tmp_path / "frames").mkdir()
    result = invoke("batch", "--demo", "--turntable", 3, "-o", tmp_path / "frames", "--size", "32x32",
                    "--workers", 1)
    assert result.exit_code == 0, result.output
    assert sorted(p.name for p in (tmp_path / "frames").iterdir()) == ["000.png", "001.png", "002.png"]


# Issue 17.6: one default method for every interface that names none, the exported page's too.
def test_the_default_method_where_none_is_named(tmp_path):
    from surfel.methods import DEFAULT_METHOD
    from surfel.request import parse_render
    from surfel.web.export import page_request

    assert DEFAULT_METHOD == "phong"
    assert parse_render({"demo": True, "output": str(tmp_path / "x.png")}).method == DEFAULT_METHOD
    assert page_request({"demo": True, "output": str(tmp_path / "x.html")}).method == DEFAULT_METHOD
    listed = invoke("methods").output.splitlines()
    assert [line.split()[0] for line in listed if line.endswith("(the default)")] == [DEFAULT_METHOD]


def test_a_folder_of_tiles_is_sent_to_lod_build(tmp_path):
    """A folder that is no .lod hierarchy is one cloud only to `lod build`: render, info and
    export-html say so in one line naming it."""
    folder = tmp_path / "tiles"
    folder.mkdir()
    for command in (["render", folder, "-o", tmp_path / "x.png"], ["info", folder],
                    ["export-html", folder, "-o", tmp_path / "x.html"]):
        assert_refused(invoke(*command), "tiles: a folder", "surfel lod build")
    assert not (tmp_path / "x.png").exists() and not (tmp_path / "x.html").exists()
