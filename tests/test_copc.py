"""COPC: the writer's files open in laspy's COPC reader and round-trip every attribute; the
reader selects through the hierarchy, reading a fraction of the file for far views, and its cuts
render like the original cloud; bad files give one-line errors."""

from __future__ import annotations

from pathlib import Path

import laspy
import numpy as np
import pytest
from scipy.spatial import cKDTree

from conftest import requires_gl
from models import DATA, SPOT
from surfel.camera import frame
from surfel.cloud import PointCloud
from surfel.errors import InputError
from surfel.lod.copc import CopcSource
from surfel.lod.copc_write import write_copc
from surfel.lod.source import open_source
from surfel.metrics import compare_results
from surfel.rendering import Renderer, render

REAL_COPC = DATA / "simple_with_page.copc.laz"  # laspy's, BSD licence
SIZE = (256, 256)


def _lidar_cloud() -> PointCloud:
    """Real aerial LiDAR (autzen_trim, 110,000 points) with cheap attributes: normals up, radii
    1.5 x the mean distance to the 6 nearest neighbours (enough to cover, fast to compute)."""
    las = laspy.read(DATA / "autzen_trim.laz")
    positions = np.column_stack([las.x, las.y, las.z])
    distances, _ = cKDTree(positions).query(positions, k=7)
    rgb = np.column_stack([las.red, las.green, las.blue]).astype(np.float64)
    return PointCloud(positions, normals=np.tile([0.0, 0.0, 1.0], (len(positions), 1)),
                      colors=rgb / (255.0 if rgb.max() <= 255 else 65535.0),
                      radii=1.5 * distances[:, 1:].mean(axis=1), geospatial=True)


@pytest.fixture(scope="module")
def lidar():
    return _lidar_cloud()


@pytest.fixture(scope="module")
def lidar_copc(lidar, tmp_path_factory):
    path = tmp_path_factory.mktemp("copc") / "autzen.copc.laz"
    summary = write_copc(lidar, path)
    assert summary["points"] == len(lidar) and summary["depth"] >= 2
    return path


def _camera(source, zoom: float, view: str = "top"):
    return frame(source.center, source.bounding_radius, geospatial=True, size=SIZE, view=view, zoom=zoom)


def test_round_trip_through_laspy(lidar, lidar_copc):
    with laspy.CopcReader.open(lidar_copc) as reader:
        points = reader.query()
        assert len(points) == len(lidar) == reader.header.point_count
    plain = laspy.read(lidar_copc)  # also a valid plain LAZ (chunk table and all)
    assert len(plain.points) == len(lidar)
    # the same points in another order: match them up by position
    stored = np.column_stack([plain.x, plain.y, plain.z])
    distance, index = cKDTree(stored).query(lidar.positions)
    assert distance.max() <= plain.header.scales.max()
    assert np.array_equal(np.column_stack([plain.normal_x, plain.normal_y, plain.normal_z])[index],
                          lidar.normals)
    assert np.array_equal(np.asarray(plain.radius)[index], lidar.radii)
    rgb = np.column_stack([plain.red, plain.green, plain.blue])[index] / 65535.0
    assert np.abs(rgb - lidar.colors).max() <= 0.5 / 65535 + 1e-6


def test_far_view_reads_a_fraction_and_covers(lidar, lidar_copc):
    source = open_source(lidar_copc)
    assert isinstance(source, CopcSource) and source.total_points == len(lidar)
    camera = _camera(source, zoom=4.0)
    cut, stats = source.select(camera, 1.0)
    assert stats["bytes_read"] < source.size / 3
    assert stats["points_selected"] == len(cut) < len(lidar) / 3
    assert cut.normals is not None and cut.radii is not None and cut.axes is not None
    assert len(np.unique(cut.positions, axis=0)) == len(cut)  # additive: no point loaded twice


@requires_gl
def test_far_and_near_views_render_like_the_cloud(lidar, lidar_copc):
    source = CopcSource(lidar_copc)
    for zoom, min_psnr in [(4.0, 30.0), (0.5, 45.0)]:
        camera = _camera(source, zoom)
        reference = render(lidar, camera, method="deferred", shading="lambert")
        result = render(source, camera, method="deferred", shading="lambert", lod_error=1.0)
        scores = compare_results(reference, result)
        assert scores["holes"] < 0.002, (zoom, scores)
        assert scores["psnr"] > min_psnr, (zoom, scores)
    assert result.stats["points"] == len(lidar) and result.stats["bytes_read"] > 0


def test_point_budget_raises_the_error(lidar_copc):
    source = CopcSource(lidar_copc)
    camera = _camera(source, zoom=0.5, view="front")
    full, full_stats = source.select(camera, 0.5)
    cut, stats = source.select(camera, 0.5, point_budget=len(full) // 3)
    assert len(cut) <= len(full) // 3 and stats["epsilon_used"] > 0.5
    assert stats["bytes_read"] < full_stats["bytes_read"]


def test_reader_skips_nodes_outside_the_view(lidar_copc):
    source = CopcSource(lidar_copc)
    camera = _camera(source, zoom=0.15)  # looking down at the middle only, at full detail
    cut, stats = source.select(camera, 1.0)
    nodes = sum(entry.point_count > 0 for entry in source._entries.values())
    # the coarse levels (ancestors of the view) are read whole; the fine nodes outside are not
    assert stats["nodes_loaded"] < nodes / 2 and stats["bytes_read"] < 0.8 * source.size
    lo, hi = source.bounds
    middle = (np.abs(cut.positions[:, :2] - source.center[:2]) < (hi - lo)[:2] / 3).all(axis=1)
    assert middle.mean() > 0.5


def test_real_copc_with_a_child_page():
    """laspy's Autzen sample, written by PDAL: a foreign file without normals or radii."""
    source = CopcSource(REAL_COPC)
    with laspy.CopcReader.open(REAL_COPC) as reader:
        everything = reader.query()
    camera = _camera(source, zoom=1.0)
    _, far_stats = source.select(camera.with_(fy=camera.fy / 64, fx=camera.fx / 64), 1.0)
    full, full_stats = source.select(camera, 1e-3)
    assert far_stats["nodes_loaded"] < full_stats["nodes_loaded"] == 65  # the nodes of every page
    assert far_stats["bytes_read"] < source.size / 3
    assert len(full) == len(everything) == source.total_points
    assert np.allclose(np.sort(full.positions[:, 0]), np.sort(np.asarray(everything.x)))
    assert full.normals is not None and (full.normals[:, 2] >= 0).all()  # estimated, facing up
    assert full.colors is not None and "estimated" in full_stats


def test_bad_files_give_one_line_errors(lidar_copc, tmp_path):
    data = Path(lidar_copc).read_bytes()
    truncated = tmp_path / "truncated.copc.laz"
    truncated.write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError, match="truncated.copc.laz") as error:
        CopcSource(truncated)
    assert "\n" not in str(error.value)

    source = CopcSource(lidar_copc)
    root = source._entries[0]  # the root node's chunk: scribble over it
    corrupt = tmp_path / "corrupt.copc.laz"
    scribbled = bytearray(data)
    scribbled[root.offset:root.offset + root.byte_size] = bytes(range(256)) * (root.byte_size // 256) \
        + bytes(root.byte_size % 256)
    corrupt.write_bytes(bytes(scribbled))
    with pytest.raises(InputError, match="corrupt.copc.laz: cannot decompress") as error:
        CopcSource(corrupt).select(_camera(source, zoom=4.0), 1.0)
    assert "\n" not in str(error.value)

    plain = tmp_path / "plain.laz"
    plain.write_bytes((DATA / "autzen_trim.laz").read_bytes())
    with pytest.raises(InputError, match="not a COPC file"):
        CopcSource(plain)


@requires_gl
def test_build_command_and_cli_render(tmp_path):
    from click.testing import CliRunner

    from surfel.cli import main
    from surfel.lod.copc_write import build_command

    out = tmp_path / "spot.copc.laz"
    stats = build_command(SPOT, out)
    assert stats["points"] == CopcSource(out).total_points and stats["bytes"] == out.stat().st_size
    result = CliRunner().invoke(main, ["render", str(out), "-o", str(tmp_path / "spot.png"),
                                       "--size", "64x64"])
    assert result.exit_code == 0, result.output
    broken = tmp_path / "broken.copc.laz"
    broken.write_bytes(out.read_bytes()[:-100])
    result = CliRunner().invoke(main, ["render", str(broken), "-o", str(tmp_path / "broken.png")])
    assert result.exit_code == 2 and "broken.copc.laz" in result.output
    assert len(result.output.strip().splitlines()) == 1


def test_a_tile_without_rgb_looks_the_same_as_laz_and_as_copc(tmp_path):
    """Converting a LAZ tile without RGB to COPC must not change its default picture: both
    default to the elevation ramp, and intensity stays an attribute to colour by."""
    from surfel.lod.copc_write import build_command
    from surfel.request import parse_render

    tile = DATA / "classified.laz"
    copc = tmp_path / "classified.copc.laz"
    build_command(tile, copc)
    modes = {}
    for path in (tile, copc):
        for color in (None, "intensity"):
            request = parse_render({"input": str(path), "output": str(tmp_path / "unused.png"), "size": "64x64",
                                    **({} if color is None else {"color": color})})
            result = request.render(Renderer())
            modes[path.name, color] = result.stats["color"]
    assert modes == {("classified.laz", None): "elevation", ("classified.copc.laz", None): "elevation",
                     ("classified.laz", "intensity"): "intensity", ("classified.copc.laz", "intensity"): "intensity"}
