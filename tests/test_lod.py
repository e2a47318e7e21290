"""Level of detail: point-tree hierarchy and sequential point trees (survey section 2.2)."""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

import surfel.lod as lod
from models import dense_spot
from surfel.camera import Camera, frame
from surfel.cloud import PointCloud
from surfel.lod.build import ROOT_PARENT_ERROR

FLT_MAX = ROOT_PARENT_ERROR


def disk_cloud(positions: np.ndarray, normals: np.ndarray, colors=None) -> PointCloud:
    """Circular splats of 1.2 x the mean distance to the 8 nearest neighbours."""
    distances, _ = cKDTree(positions).query(positions, 9)
    radii = 1.2 * distances[:, 1:].mean(axis=1)
    n = normals / np.linalg.norm(normals, axis=1, keepdims=True)
    t = np.cross(n, [0.3, 0.5, 0.7])
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    b = np.cross(n, t)
    axes = np.stack([t * radii[:, None], b * radii[:, None]], axis=1)
    return PointCloud(positions, normals=n, colors=colors, radii=radii, axes=axes)


@pytest.fixture(scope="module")
def dense() -> PointCloud:
    """Spot refined to 46,850 vertices (tests/models.py), as circular disks."""
    mesh = dense_spot()
    return disk_cloud(mesh.positions, mesh.normals)


@pytest.fixture(scope="module")
def tree(dense) -> lod.LodTree:
    return lod.build_lod(dense, progress=False)


@pytest.fixture(scope="module")
def seq(tree) -> PointCloud:
    return lod.to_sequential_cloud(tree)


def camera_at(cloud: PointCloud, zoom: float, view: str = "front", size=(512, 512)) -> Camera:
    return frame(cloud.center, cloud.bounding_radius, view=view, size=size, zoom=zoom)


# ---- the survey's Fig. 13 ----------------------------------------------------------------

def fig13_list() -> dict[str, np.ndarray]:
    """Fig. 13's sequential point tree, reconstructed from the survey's text.

    A (root, [10, inf)) has children B ([4, 10)), C and D (leaves, [0, 10)); B has the
    leaves E, F, G ([0, 4)). Sorted by r_max decreasing: A B C D E F G = points 0..6.
    With k = 1 the stored errors are the distances themselves.
    """
    emin = np.array([10, 4, 0, 0, 0, 0, 0], np.float32)
    emax = np.array([FLT_MAX, 10, 10, 10, 4, 4, 4], np.float32)
    return {"emin": emin, "emax": emax}


def fig13_draw(r: float) -> tuple[int, np.ndarray]:
    """The CPU prefix and the indices the vertex test keeps, every node at distance r."""
    nodes = fig13_list()
    n = len(nodes["emin"])
    zeros = np.zeros(n, np.float32)
    seq = PointCloud(np.zeros((n, 3)), attributes={"lod_emin": nodes["emin"], "lod_emax": nodes["emax"],
                                               "lod_dparent": zeros, "lod_dsuffix": zeros})
    count = lod.prefix_count(seq, r, 1.0)
    keep = lod.lod_selected(r, nodes["emin"][:count].astype(np.float64),
                            nodes["emax"][:count].astype(np.float64), 0.0, 1.0)
    return count, np.flatnonzero(keep)


def test_fig13_r8_prefix_and_vertex_culling():
    count, drawn = fig13_draw(8.0)
    assert count == 4  # the CPU preselects points 0 to 3
    assert drawn.tolist() == [1, 2, 3]  # the GPU culls point 0: its r_min (10) is above r


def test_fig13_r35_draws_more_and_leaves_parents_out():
    count, drawn = fig13_draw(3.5)
    assert count == 7
    assert drawn.tolist() == [2, 3, 4, 5, 6]  # parents A and B are left out
    assert len(drawn) > len(fig13_draw(8.0)[1])


def test_fig13_one_node_per_path_at_every_distance():
    paths = [[0, 1, 4], [0, 1, 5], [0, 1, 6], [0, 2], [0, 3]]
    for r in np.linspace(0.0, 20.0, 81):
        drawn = set(fig13_draw(float(r))[1].tolist())
        assert all(len(drawn.intersection(path)) == 1 for path in paths), r


# ---- the hierarchy -----------------------------------------------------------------------

def test_tree_structure(dense, tree):
    n = len(dense)
    assert tree.n_leaves == n and sorted(tree.point_index.tolist()) == list(range(n))
    assert np.allclose(tree.positions[:n], dense.positions[tree.point_index])
    assert tree.parent[tree.root] == -1 and (tree.parent[:-1] >= 0).all()
    counts = np.diff(tree.child_start)
    assert (counts[:n] == 0).all() and (counts[n:] >= 2).all()  # no single-child nodes
    assert len(tree.children) == len(tree) - 1
    assert (tree.parent[tree.children] == np.repeat(np.arange(len(tree)), counts)).all()
    assert np.allclose(np.linalg.norm(tree.normals, axis=1), 1, atol=1e-5)
    lengths = np.linalg.norm(tree.axes[n:], axis=2)
    assert np.allclose(lengths, tree.radii[n:, None], rtol=1e-5)


def test_errors_monotone_and_combined(tree):
    n = tree.n_leaves
    assert (tree.e_g[:n] == 0).all() and (tree.e_p[:n] == 0).all() and (tree.e_t[:n] == 0).all()
    assert (tree.e_p >= 0).all() and (tree.e_t >= 0).all()
    combined = np.sqrt(tree.e_p.astype(np.float64) ** 2 + tree.e_t.astype(np.float64) ** 2)
    assert (tree.e_g >= combined * (1 - 1e-6)).all()
    assert (tree.parent_error() >= tree.e_g).all()  # monotone along every path
    assert (tree.e_g[n:] > 0).all()


def test_errors_of_two_flat_disks():
    """Two coplanar disks side by side: e_p = 0, e_t = the overhang across, R encloses."""
    positions = np.array([[-1.0, 0, 0], [1.0, 0, 0]])
    normals = np.array([[0, 0, 1.0], [0, 0, 1.0]])
    cloud = PointCloud(positions, normals=normals, radii=np.array([1.0, 1.0]))
    tree = lod.build_lod(cloud, progress=False)
    assert len(tree) == 3
    assert tree.radii[2] == pytest.approx(2.0)
    assert tree.e_p[2] == pytest.approx(0.0, abs=1e-6)
    assert tree.e_t[2] == pytest.approx(1.0, abs=1e-5)  # across: children reach 1, disk 2
    assert tree.e_g[2] == pytest.approx(1.0, abs=1e-5)


def test_errors_of_a_fold():
    """Two disks tilted towards each other: the slab holds both disks entirely."""
    a = math.radians(30)
    normals = np.array([[-math.sin(a), 0, math.cos(a)], [math.sin(a), 0, math.cos(a)]])
    cloud = PointCloud(np.array([[-1.0, 0, 0], [1.0, 0, 0]]), normals=normals, radii=np.array([0.5, 0.5]))
    tree = lod.build_lod(cloud, progress=False)
    assert tree.e_p[2] == pytest.approx(2 * 0.5 * math.sin(a), rel=1e-5)


def ancestors_selected(tree: lod.LodTree, selected: np.ndarray) -> np.ndarray:
    """For each leaf, its selected ancestor-or-self (-1 if none)."""
    flag = np.zeros(len(tree), bool)
    flag[selected] = True
    node = np.arange(tree.n_leaves)
    found = np.full(tree.n_leaves, -1)
    while (found < 0).any():
        hit = (found < 0) & flag[node]
        found[hit] = node[hit]
        node = np.where(tree.parent[node] >= 0, tree.parent[node], node)
        if not flag[node].any() and (tree.parent[node] < 0).all():
            break
    return found


@pytest.mark.parametrize("zoom", [1, 2, 4, 16, 64])
def test_selected_disks_cover_every_point(tree, seq, dense, zoom):
    """No holes: each input point and its splat rim lies inside a selected disk's cylinder."""
    cam = camera_at(dense, zoom)
    order = lod.sequential_order(tree)
    for selected in (lod.select_recursive(tree, cam, 1.0), order[lod.select_sequential(seq, cam, 1.0)]):
        owner = ancestors_selected(tree, selected)
        assert (owner >= 0).all()
        n = tree.normals[owner].astype(np.float64)
        for rim in ([0, 0], [1, 0], [-1, 0], [0, 1], [0, -1]):
            x = tree.positions[:tree.n_leaves] + np.einsum("k,nkj->nj", rim, tree.axes[:tree.n_leaves])
            d = x - tree.positions[owner]
            dn = np.einsum("ij,ij->i", d, n)
            in_plane = np.linalg.norm(d - dn[:, None] * n, axis=1)
            slack = 1e-5 * tree.radii[owner]  # float32 attributes
            assert (in_plane <= tree.radii[owner] + slack).all()
            assert (np.abs(dn) <= tree.e_p[owner] + slack).all()


# ---- recursive traversal vs sequential list ------------------------------------------------

def test_sequential_order_sorted(tree, seq):
    emax = seq.attributes["lod_emax"]
    buckets = lod.sequential.r_max_bucket(emax).astype(np.int64)
    assert len(seq) == len(tree) and (np.diff(buckets) <= 0).all() and emax[0] == FLT_MAX
    ceiling = np.array([lod.sequential._bucket_ceiling(e) for e in emax[1:1000]])
    assert (ceiling >= emax[1:1000]).all() and (ceiling <= emax[1:1000] * (1 + 2 ** -8)).all()
    order = lod.sequential_order(tree)
    assert sorted(order.tolist()) == list(range(len(tree)))
    assert np.array_equal(seq.attributes["lod_emin"], tree.e_g[order])
    dsuffix = seq.attributes["lod_dsuffix"]
    assert (np.diff(dsuffix) <= 0).all() and (dsuffix >= seq.attributes["lod_dparent"]).all()


@pytest.mark.parametrize("height_factor", [0.5, 2, 8, 32])
def test_orthographic_sequential_equals_recursive(tree, seq, dense, height_factor):
    """One distance for all nodes (orthographic): the two selections are identical."""
    base = camera_at(dense, 1)
    cam = base.with_(ortho_height=2 * dense.bounding_radius * height_factor)
    order = lod.sequential_order(tree)
    recursive = lod.select_recursive(tree, cam, 1.0)
    sequential = np.sort(order[lod.select_sequential(seq, cam, 1.0)])
    assert np.array_equal(recursive, sequential)


@pytest.mark.parametrize("zoom,view", [(1, "front"), (2, "right"), (4, "front"), (8, "iso")])
def test_perspective_sequential_matches_recursive(tree, seq, dense, zoom, view):
    """Per-point distances: the sequential cut contains the recursive one, plus a thin band
    of overlapping parents and children (the view-independent simplification)."""
    cam = camera_at(dense, zoom, view)
    order = lod.sequential_order(tree)
    recursive = lod.select_recursive(tree, cam, 1.0)
    sequential = np.sort(order[lod.select_sequential(seq, cam, 1.0)])
    assert np.isin(recursive, sequential).all()
    extra = len(sequential) - len(recursive)
    print(f"zoom {zoom} {view}: recursive {len(recursive)}, sequential {len(sequential)} "
          f"({len(sequential) / tree.n_leaves:.1%} of the points)")
    assert extra <= 0.02 * len(recursive)


def test_prefix_never_cuts_a_selected_node(seq, dense):
    for zoom in (0.3, 1, 3, 10):
        cam = camera_at(dense, zoom)
        k = lod.lod_scale(cam, 1.0)
        count = lod.prefix_count(seq, lod.near_distance(seq, cam), k)
        r = np.linalg.norm(seq.positions - cam.eye, axis=1)
        everywhere = lod.lod_selected(r, seq.attributes["lod_emin"].astype(np.float64),
                                      seq.attributes["lod_emax"].astype(np.float64),
                                      seq.attributes["lod_dparent"].astype(np.float64), k)
        assert not everywhere[count:].any()
        assert count < len(seq) or zoom < 1


def test_lod_reduces_with_distance_and_subset(seq, dense):
    drawn = [lod.select_sequential(seq, camera_at(dense, z), 1.0).sum() for z in (1, 4, 16)]
    assert drawn[0] > drawn[1] > drawn[2] >= 1
    assert drawn[1] <= 0.3 * len(dense)
    cam = camera_at(dense, 4)
    subset = lod.lod_subset(seq, cam, 1.0)
    assert len(subset) == drawn[1] and subset.attributes == {}


# ---- the shader twin -------------------------------------------------------------------------

def test_glsl_matches_numpy():
    """lod.glsl's lod_selected(), run by transform feedback, agrees with the numpy twin."""
    try:
        from surfel.gl.context import get_context
        from surfel.gl.program import expand_includes

        ctx = get_context()
    except Exception as error:  # no OpenGL here
        pytest.skip(f"no OpenGL: {error}")
    gl = Path(lod.__file__).resolve().parents[1] / "gl"
    shared = [expand_includes(gl / name) for name in ("common.glsl", "lod.glsl")]
    source = "\n".join(["#version 430 core", *shared, """
in vec4 in_lod;  // r, emin, emax, dparent
out float v_selected;
uniform float u_k;
void main() { v_selected = lod_selected(in_lod.x, in_lod.y, in_lod.z, in_lod.w, u_k) ? 1.0 : 0.0; }
"""])
    program = ctx.program(vertex_shader=source, varyings=["v_selected"])
    fbo = ctx.simple_framebuffer((1, 1))  # a headless context has no default framebuffer
    fbo.use()
    rng = np.random.default_rng(3)
    n = 10_000
    emin = rng.uniform(0, 1, n).astype(np.float32)
    emax = (emin + rng.uniform(0, 1, n)).astype(np.float32)
    emax[:20] = FLT_MAX
    dparent = rng.uniform(0, 0.2, n).astype(np.float32)
    r = rng.uniform(0, 3, n).astype(np.float32)
    r[10:20] = emin[10:20] * 2  # exactly on r_min: drawn
    data = np.stack([r, emin, emax, dparent], axis=1).astype(np.float32)
    vbo = ctx.buffer(data.tobytes())
    out = ctx.buffer(reserve=n * 4)
    vao = ctx.vertex_array(program, [(vbo, "4f", "in_lod")])
    program["u_k"].value = 2.0
    vao.transform(out, vertices=n)
    gpu = np.frombuffer(out.read(), np.float32) > 0.5
    for obj in (vao, out, vbo, program, fbo):
        obj.release()
    with np.errstate(over="ignore"):  # FLT_MAX * k overflows to inf, as on the GPU
        cpu = lod.lod_selected(r, emin, emax, dparent, np.float32(2.0))
    assert np.array_equal(gpu, cpu)
    assert cpu[10:20].all()  # r == r_min is drawn


# ---- file format and command -------------------------------------------------------------------

def test_save_load_round_trip(tree, seq, tmp_path):
    from surfel.errors import InputError
    from surfel.io import load

    path = tmp_path / "spot.lod.npz"
    lod.save_lod(tree, path)
    loaded = lod.load_lod(path)
    for name in ("positions", "radii", "axes"):
        assert np.array_equal(getattr(loaded, name), getattr(seq, name)), name
    assert np.allclose(loaded.normals, seq.normals, atol=1e-6)  # renormalised on loading
    for name in lod.sequential.EXTRAS:
        assert np.array_equal(loaded.attributes[name], seq.attributes[name]), name
    generic = load(path)  # any surfel reader of .npz sees the LOD extras
    assert set(lod.sequential.EXTRAS) <= set(generic.attributes)
    assert [p.name for p in tmp_path.iterdir()] == ["spot.lod.npz"]  # no temporaries left
    plain = tmp_path / "plain.npz"
    np.savez(plain, positions=seq.positions)
    with pytest.raises(InputError):
        lod.load_lod(plain)
    bad = tmp_path / "future.npz"
    np.savez(bad, positions=seq.positions, surfel_lod_version=np.int64(99))
    with pytest.raises(InputError, match="version"):
        lod.load_lod(bad)


def test_build_command(dense, tmp_path):
    source = tmp_path / "in.npz"
    rng = np.random.default_rng(0)
    colors = rng.random((len(dense), 3)).astype(np.float32)
    np.savez(source, positions=dense.positions, normals=dense.normals, radii=dense.radii,
             axes=dense.axes, colors=colors)
    stats = lod.build_command(source, tmp_path / "out.lod.npz", tmp_path / "stats.json")
    import json

    assert json.loads((tmp_path / "stats.json").read_text()) == stats
    assert stats["points"] == len(dense) and stats["nodes"] > len(dense) and stats["ms"] > 0
    loaded = lod.load_lod(tmp_path / "out.lod.npz")
    assert loaded.colors is not None and len(loaded) == stats["nodes"]


def test_build_throughput(dense):
    """Printed, not asserted: points per second on the dense replicated with jitter to 1M."""
    rng = np.random.default_rng(1)
    n = 1_000_000
    rep = -(-n // len(dense))
    positions = np.tile(dense.positions, (rep, 1))[:n]
    positions = positions + rng.normal(scale=float(dense.radii.mean()) * 0.3, size=positions.shape)
    big = PointCloud(positions, normals=np.tile(dense.normals, (rep, 1))[:n],
                     radii=np.tile(dense.radii, rep)[:n] * 0.3,
                     axes=np.tile(dense.axes, (rep, 1, 1))[:n] * 0.3)
    lod.build_lod(PointCloud(positions[:1000], normals=big.normals[:1000], radii=big.radii[:1000]),
                  progress=False)  # JIT warm-up, not timed
    start = time.perf_counter()
    tree = lod.build_lod(big, progress=False)
    seq = lod.to_sequential_cloud(tree)
    seconds = time.perf_counter() - start
    print(f"lod build: {n} points -> {len(seq)} nodes in {seconds:.2f} s "
          f"= {n / seconds / 1e6:.2f} M points/s")


def test_clip_lines_of_sharp_features_survive_the_hierarchy(tmp_path, turned_part):
    """A CAD part's leaves keep their clip lines through build, file and cut; crease points
    (cut away whole) are no leaves; the cut at 1 px still meets the full-detail quality bar."""
    from conftest import gl_ok
    from surfel.metrics import compare_results
    from surfel.preprocess import clipped_away, complete
    from surfel.rendering import render

    mesh = turned_part
    cloud = complete(mesh)[0]
    dropped = clipped_away(cloud)
    tree = lod.build_lod(cloud, progress=False)
    assert tree.n_leaves == len(cloud) - dropped.sum() and dropped.sum() > 0
    np.testing.assert_array_equal(tree.clip_lines[:tree.n_leaves], cloud.attributes["clip_lines"][tree.point_index])
    assert (tree.clip_lines[tree.n_leaves:, :, 2] == 1).all()
    lod.save_lod(tree, tmp_path / "part.lod.npz")
    seq = lod.load_lod(tmp_path / "part.lod.npz")
    assert "clip_lines" in seq.attributes
    if gl_ok():
        cam = frame(mesh.center, mesh.bounding_radius, size=(256, 256))
        ref = render(mesh, cam, "mesh", shading="lambert")
        metrics = compare_results(ref, render(seq, cam, "deferred", shading="lambert", lod_error=1.0))
        assert metrics["psnr"] >= 27 and metrics["holes"] <= 0.001, metrics


def test_leaves_compile_once_whatever_the_cloud_holds():
    """A cloud without colours, radii or axes passes read-only stand-ins like the arrays it
    has, so the leaf kernel compiles one signature for all of them (each a compile of about a
    second in every out-of-core worker)."""
    from surfel.lod.build import _leaf_rows

    rng = np.random.default_rng(1)
    positions = rng.random((50, 3))
    normals = np.tile([0.0, 0.0, 1.0], (50, 1))
    axes = np.tile([[[0.01, 0, 0], [0, 0.01, 0]]], (50, 1, 1))
    clouds = [PointCloud(positions, normals=normals, colors=rng.random((50, 3)), axes=axes),
              PointCloud(positions, normals=normals, radii=np.full(50, 0.01)),
              PointCloud(positions, normals=normals, colors=rng.random((50, 3)), radii=np.full(50, 0.01), axes=axes)]
    lod.build_lod(clouds[0], progress=False)
    signatures = set(_leaf_rows.signatures)
    for cloud in clouds[1:]:
        lod.build_lod(cloud, progress=False)
    assert set(_leaf_rows.signatures) == signatures
