"""The command line as a user meets it: demo, compare, bench, and bad input."""

import json
import struct
import subprocess
import sys

import numpy as np

from conftest import requires_gl
from models import DATA, SPOT


def run(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "surfel.cli", *map(str, args)], capture_output=True,
                          text=True, cwd=cwd, timeout=600)


@requires_gl
def test_demo_render_writes_a_picture_of_spot(tmp_path):
    from PIL import Image

    out = tmp_path / "demo.png"
    proc = run("render", "--demo", "-o", out, "--size", "256x256", "--stats", tmp_path / "s.json")
    assert proc.returncode == 0, proc.stderr
    rgba = np.asarray(Image.open(out))
    assert rgba.shape == (256, 256, 4)
    covered = rgba[..., 3] > 127
    assert 0.1 < covered.mean() < 0.7  # the cow fills the frame but not all of it
    assert rgba[covered][:, 0].mean() > rgba[covered][:, 2].mean()  # Spot's warm colour
    stats = json.loads((tmp_path / "s.json").read_text())
    assert {"method", "backend", "renderer", "points", "splats", "width", "height", "ms"} <= set(stats)


@requires_gl
def test_compare_reports_metrics_and_writes_side_by_side(tmp_path):
    proc = run("compare", SPOT, "--method", "deferred", "--size", "128x128", "--shading", "lambert", "--json",
               "-o", tmp_path / "cmp.png")
    assert proc.returncode == 0, proc.stderr
    metrics = json.loads(proc.stdout)
    assert metrics["psnr"] > 22 and metrics["holes"] < 0.01
    from PIL import Image

    assert Image.open(tmp_path / "cmp.png").size == (384, 128)

    sparse = run("compare", SPOT, "--method", "deferred", "--size", "128x128", "--shading", "lambert", "--json",
                 "--every", "4", "-o", tmp_path / "sparse.png")
    assert sparse.returncode == 0, sparse.stderr
    sparse_metrics = json.loads(sparse.stdout)
    assert sparse_metrics["splats"] == (metrics["splats"] + 3) // 4  # every 4th vertex, the mesh's camera
    assert sparse_metrics["psnr"] < metrics["psnr"]


@requires_gl
def test_bench_json_rows(tmp_path):
    proc = run("bench", "--methods", "points,deferred@gl", "--points", "20000", "--size", "64x64", "--frames", "2",
               "--json")
    assert proc.returncode == 0, proc.stderr
    rows = json.loads(proc.stdout)
    assert [r["method"] for r in rows] == ["points", "deferred"]
    assert rows[0]["backend_choice"].startswith("auto") and rows[1]["backend_choice"] == "asked"
    for r in rows:
        assert {"method", "backend", "points", "width", "height", "ms", "msplats_per_s"} <= set(r)
        assert r["points"] == 20000 and r["ms"] > 0
        assert " cores of " in r["machine"]
    table = run("bench", "--methods", "points@gl", "--points", "2000", "--size", "32x32", "--frames", "1")
    machine, sizes = table.stdout.splitlines()[:2]
    assert machine == f"machine: {rows[0]['machine']}" and "OpenGL renderer: " in sizes


def _bad_inputs(tmp_path):
    """Eight malformed or empty inputs of different kinds."""
    files = {}
    files["missing.ply"] = tmp_path / "missing.ply"
    (tmp_path / "empty.ply").write_bytes(b"")
    files["empty.ply"] = tmp_path / "empty.ply"
    (tmp_path / "model.stl3").write_text("solid")
    files["model.stl3"] = tmp_path / "model.stl3"
    (tmp_path / "truncated.ply").write_bytes(
        b"ply\nformat binary_little_endian 1.0\nelement vertex 1000\nproperty float x\nproperty float y\n"
        b"property float z\nend_header\n" + b"\0" * 100)
    files["truncated.ply"] = tmp_path / "truncated.ply"
    (tmp_path / "nan.xyz").write_text("0 0 0\n1 nan 0\n0 1 0\n")
    files["nan.xyz"] = tmp_path / "nan.xyz"
    (tmp_path / "zero.ply").write_text("ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\n"
                                       "property float y\nproperty float z\nend_header\n")
    files["zero.ply"] = tmp_path / "zero.ply"
    (tmp_path / "garbage.obj").write_text("v 1 2\nf 1 2 3\n")
    files["garbage.obj"] = tmp_path / "garbage.obj"
    # a LAS 1.2 header that claims millions of VLRs in a 14 KB file
    header = bytearray(227)
    header[0:4] = b"LASF"
    header[24], header[25] = 1, 2
    struct.pack_into("<H", header, 94, 227)
    struct.pack_into("<I", header, 96, 227)
    struct.pack_into("<I", header, 100, 5_000_000)
    header[104] = 0
    struct.pack_into("<H", header, 105, 20)
    struct.pack_into("<I", header, 107, 10)
    (tmp_path / "liar.las").write_bytes(bytes(header) + b"\0" * 14000)
    files["liar.las"] = tmp_path / "liar.las"
    return files


def test_bad_inputs_give_one_line_and_exit_2(tmp_path):
    files = _bad_inputs(tmp_path)
    assert len(files) == 8
    for name, path in files.items():
        out = tmp_path / f"out-{name}.png"
        proc = run("render", path, "-o", out, "--size", "32x32")
        lines = proc.stderr.strip().splitlines()
        assert proc.returncode == 2, (name, proc.stderr)
        assert len(lines) == 1 and name in lines[0], (name, proc.stderr)
        assert "Traceback" not in proc.stderr
        assert not out.exists()


def test_info_reports_attributes_and_estimates():
    proc = run("info", DATA / "autzen_trim.laz", "--json")
    assert proc.returncode == 0, proc.stderr
    info = json.loads(proc.stdout)
    assert info["points"] == 110000 and info["geospatial"]
    assert "colors" in info["attributes"] and "normals" in info["would_estimate"]
    # a file without scanner positions says so, not what to do when OpenGL is missing
    lines = run("info", DATA / "autzen_trim.laz").stdout.splitlines()
    assert info["sensors"] is None
    assert [line.split(None, 1)[1] for line in lines if line.startswith("sensors ")] == [
        "none (the file holds no scanner positions)"]


def test_an_output_named_for_another_format_is_refused(tmp_path):
    """prepare writes a PLY and compare a PNG: under another extension the file would not read
    back as what its name says (load takes a .npz for an archive), so the name is refused
    before any work, in one line, and nothing is written."""
    cloud = DATA / "autzen_trim.laz"
    for command, output, wanted in (("prepare", "prepared.npz", ".ply"), ("compare", "side.jpg", ".png")):
        target = tmp_path / output
        args = (cloud, "-o", target) + (("--size", "32x32") if command == "compare" else ())
        proc = run(command, *args)
        lines = proc.stderr.strip().splitlines()
        assert proc.returncode == 2 and len(lines) == 1, (command, proc.stderr)
        assert output in lines[0] and wanted in lines[0], lines
        assert not target.exists()


def test_compare_refuses_the_mesh_method_in_one_line(tmp_path):
    """compare draws the method on the mesh's vertices: 'mesh', which draws faces, is refused
    naming --method, not by saying that a mesh with faces has none."""
    proc = run("compare", SPOT, "--method", "mesh", "-o", tmp_path / "side.png")
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1 and lines[0].startswith("surfel: error: --method:"), proc.stderr
    assert "vertices" in lines[0] and not (tmp_path / "side.png").exists()


def test_unknown_method_is_a_clear_error(tmp_path):
    proc = run("render", "--demo", "-o", tmp_path / "x.png", "--method", "nope")
    assert proc.returncode == 2 and "unknown method" in proc.stderr
