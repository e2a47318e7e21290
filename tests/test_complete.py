"""Completing a cloud: prepare fills exactly what is missing; complete follows a method's needs."""

from __future__ import annotations

import numpy as np

from models import mesh_cloud, spot
from samples import sphere
from surfel.attributes import FIELD_SLOPES
from surfel.cloud import PointCloud
from surfel.preprocess import complete, completes_with_clip_lines, prepare


def test_prepare_fills_exactly_what_is_missing():
    p = sphere(3_000)
    bare, report = prepare(PointCloud(p))
    assert bare.normals is not None and bare.radii is not None and bare.axes is not None
    assert report["ambiguous_normals"] == 0 and "normals" in report and "radii" in report and "axes" in report
    assert np.allclose(np.cross(bare.axes[:, 0], bare.axes[:, 1]), bare.normals * bare.radii[:, None] ** 2, atol=1e-6)

    given = PointCloud(p, normals=p)
    filled, report = prepare(given)
    assert np.array_equal(filled.normals, given.normals)
    assert "normals" not in report and "ambiguous_normals" not in report and "radii" in report

    complete = filled
    same, report = prepare(complete)
    assert same is complete and report == {}

    ellipses, report = prepare(PointCloud(p, normals=p, radii=np.full(len(p), 0.05)), elliptical=True,
                               normal_field=True)
    assert np.array_equal(ellipses.radii, np.full(len(p), 0.05, np.float32))
    assert report["axes"].startswith("fitted ellipses") and "normal_field" in report and "radii" not in report
    assert ellipses.attributes["phong_alpha"].shape == (len(p),) and (ellipses.attributes["phong_alpha"] > 0).all()

    axes_only, report = prepare(PointCloud(p, axes=bare.axes))
    assert np.allclose(axes_only.normals, bare.normals, atol=1e-5) and np.array_equal(axes_only.axes, bare.axes)


def test_given_normals_are_oriented_where_nothing_says_which_side_was_seen():
    # a mesh wound the other way round gives its vertices inward normals, with which the cells
    # read every convex edge as concave: turned (normals.orient_given)
    model = spot()
    outward, _ = prepare(model, elliptical=True, normal_field=True)
    turned, report = prepare(model.with_(normals=-model.normals), elliptical=True, normal_field=True)
    assert report["normals"] == "given, a closed mesh's, facing inward as a whole: turned to face outward"
    for name in ("normals", "radii", "axes"):
        assert np.array_equal(getattr(turned, name), getattr(outward, name))
    for name in ("clip_lines", *FIELD_SLOPES):
        assert np.array_equal(turned.attributes[name], outward.attributes[name])
    # signs picked point by point, as a PCA never oriented leaves them: propagated, for MLS too,
    # which needs nothing else
    signs = np.where(np.random.default_rng(6).random(len(model)) < 0.5, -1.0, 1.0)[:, None]
    unoriented = model.with_(normals=signs * model.normals)
    for needs_radii in (True, False):
        oriented, report = complete(unoriented, needs_radii=needs_radii)
        assert report["normals"].startswith("given, with signs that disagree between neighbours")
        assert (np.einsum("ij,ij->i", oriented.normals, model.normals) > 0.99).all()
    # a point cloud keeps its sides: a scan made inside a closed room, normals facing the scanner
    p = sphere(3_000)
    inside = PointCloud(p, normals=-p)
    for sensor in (None, np.zeros(3)):
        kept, report = prepare(inside, sensor=sensor)
        assert np.array_equal(kept.normals, inside.normals) and "normals" not in report
    # so does an open mesh: a room without its ceiling, its faces facing in (io.mesh.opening 0.36)
    room = open_room()
    kept, report = prepare(room)
    assert np.array_equal(kept.normals, room.normals) and "normals" not in report
    assert prepare(room.with_(faces=np.concatenate([room.faces, ceiling(room)])))[1]["normals"].startswith(
        "given, a closed mesh's")  # closed, it is taken for an object wound inside out


def open_room() -> PointCloud:
    """An 8 x 6 x 3 room without its ceiling, faces 0.5 across, wound to face in."""
    from trimesh.creation import box

    closed = box(extents=(8.0, 6.0, 3.0)).subdivide_to_size(0.5)
    vertices, faces = np.asarray(closed.vertices), np.asarray(closed.faces)[:, ::-1]
    inward = np.cross(vertices[faces[:, 1]] - vertices[faces[:, 0]], vertices[faces[:, 2]] - vertices[faces[:, 0]])
    walls_and_floor = faces[~((vertices[faces][:, :, 2].min(axis=1) > 1.49) & (inward[:, 2] < 0))]
    used = np.unique(walls_and_floor)
    renumber = np.full(len(vertices), -1)
    renumber[used] = np.arange(len(used))
    return mesh_cloud(vertices[used], renumber[walls_and_floor], "room")


def ceiling(room: PointCloud) -> np.ndarray:
    """Faces that close `room` at its top rim: a fan from one rim vertex, facing in (down)."""
    rim = np.flatnonzero(room.positions[:, 2] > 1.49)
    order = rim[np.argsort(np.arctan2(room.positions[rim, 1], room.positions[rim, 0]))]
    return np.c_[np.full(len(order) - 2, order[0]), order[1:-1], order[2:]][:, ::-1]


def test_prepare_geospatial_faces_up():
    rng = np.random.default_rng(11)
    xy = rng.uniform(0, 100, (5_000, 2))
    cloud = PointCloud(np.c_[xy, 0.1 * xy[:, 0] + 400] + [636_000, 849_000, 0], geospatial=True)
    prepared, report = prepare(cloud, progress=True)
    assert (prepared.normals[:, 2] > 0).all() and "up" in report["normals"]


def test_tiny_clouds():
    for n in (1, 2, 3):
        cloud, report = prepare(PointCloud(np.arange(3 * n, dtype=float).reshape(n, 3) ** 1.5))
        assert (cloud.radii > 0).all() and report["ambiguous_normals"] == n


def test_complete_gives_each_method_what_its_flags_ask():
    p = sphere(2_000, seed=3)
    bare, oriented = PointCloud(p), PointCloud(p, normals=p)
    # every method needs normals: a cloud without them is prepared whole, whatever the method
    for needs_radii in (True, False):
        prepared, report = complete(bare, needs_radii=needs_radii)
        assert prepared.radii is not None and prepared.axes is not None and "normals" in report
    # MLS needs normals only
    same, report = complete(oriented, needs_radii=False)
    assert same is oriented and report == {}
    # splats: circular by default, fitted ellipses for an elliptical method, given normals kept
    circles, report = complete(oriented)
    assert np.array_equal(circles.normals, oriented.normals)
    assert set(report) == {"radii", "axes", "sharp_features", "splat_bound", "thickness"}
    assert report["thickness"].startswith("0.0% ")  # one surface: no layer caps z_t
    assert np.allclose(np.linalg.norm(circles.axes[:, 0], axis=1), circles.radii, rtol=1e-5)
    ellipses, report = complete(oriented, elliptical=True, normal_field=True)
    lengths = np.linalg.norm(ellipses.axes.astype(np.float64), axis=2)
    assert report["axes"].startswith("fitted ellipses") and (lengths[:, 0] > 1.05 * lengths[:, 1]).any()
    assert {"phong_alpha", "phong_beta"} <= set(ellipses.attributes)
    # a complete cloud: given splats are kept (circles stay circles); only a missing field is fitted
    same, report = complete(circles, elliptical=True)
    assert same is circles and report == {}
    fields, report = complete(circles, elliptical=True, normal_field=True)
    assert set(report) == {"normal_field"} and np.array_equal(fields.axes, circles.axes)


def test_renderer_remembers_completions_per_cloud():
    from surfel.methods import METHODS
    from surfel.rendering import Renderer

    renderer = Renderer()
    cloud = PointCloud(sphere(1_500, seed=4))
    for method in METHODS.values():
        flags = {"needs_radii": method.needs_radii, "elliptical": method.elliptical,
                 "normal_field": method.normal_field}
        first, report = renderer.complete(cloud, **flags)
        assert renderer.complete(cloud, **flags)[0] is first  # estimated once
        pure, pure_report = complete(cloud, **flags)
        assert report == pure_report
        for name in ("normals", "radii", "axes"):
            assert np.array_equal(getattr(first, name), getattr(pure, name))
        assert first.attributes.keys() == pure.attributes.keys()


def test_whether_complete_adds_clip_lines_is_known_before_it_runs():
    """`completes_with_clip_lines` (what compile_ahead.py asks before completing) says what
    `complete` then does, for each mix of what a cloud brings and what a method needs."""
    rng = np.random.default_rng(5)
    points = rng.normal(size=(400, 3))
    points /= np.linalg.norm(points, axis=1, keepdims=True)
    radii = np.full(400, 0.15)
    clouds = [PointCloud(points), PointCloud(points, normals=points),
              PointCloud(points, normals=points, radii=radii),
              complete(PointCloud(points))[0]]  # clip lines given
    for cloud in clouds:
        for needs_radii, normal_field, smooth in ((True, False, False), (False, False, False), (True, True, False),
                                                  (True, False, True)):
            flags = dict(needs_radii=needs_radii, normal_field=normal_field, smooth=smooth)
            completed, _ = complete(cloud, **flags)
            assert completes_with_clip_lines(cloud, **flags) == ("clip_lines" in completed.attributes), flags


def seam_copies(cloud: PointCloud, seam: np.ndarray, turn: np.ndarray) -> PointCloud:
    """The cloud with a copy of each point in `seam` appended, its normal turned towards `turn`
    (as a mesh repeats its vertices along a seam, each copy with its own patch's normal)."""
    normals = cloud.normals.astype(np.float64)
    copies = normals[seam] + turn
    copies /= np.linalg.norm(copies, axis=1, keepdims=True)
    return PointCloud(np.concatenate([cloud.positions, cloud.positions[seam]]),
                      normals=np.concatenate([normals, copies]))


def test_coincident_copies_are_estimated_once_per_position():
    """Issue 17 (the Newell teapot's vertices, repeated along its patch seams): a copy filled a
    neighbour slot at distance 0, the cells saw half their neighbours, and the seams' splats
    grew 1.6 to 3 times too large. Copies within 45 degrees of each other now stand for one
    sample: estimated once, with their mean normal, and drawn alike."""
    cloud = spot()
    seam = np.random.default_rng(5).choice(len(cloud), len(cloud) // 2, replace=False)
    doubled = seam_copies(cloud, seam, turn=np.array([0.2, 0.0, 0.0]))
    mean = cloud.normals.astype(np.float64)
    mean[seam] += doubled.normals[len(cloud):]
    once, _ = prepare(PointCloud(cloud.positions, normals=mean / np.linalg.norm(mean, axis=1, keepdims=True)),
                      elliptical=True)
    prepared, report = prepare(doubled, elliptical=True)
    assert report["coincident"].startswith(f"{len(seam)} points repeat another sample's position")
    every = np.concatenate([np.arange(len(cloud)), seam])
    for name in ("radii", "axes", "normals"):
        assert np.allclose(getattr(prepared, name), getattr(once, name)[every], atol=1e-6), name
    assert np.array_equal(prepared.attributes["clip_lines"], once.attributes["clip_lines"][every])


def test_copies_facing_apart_keep_their_own_normals():
    """A vertex split at a crease (flat shading) is one sample per face: copies whose normals
    lie more than 45 degrees apart are not merged, and keep the normals they were given."""
    cloud = spot()
    seam = np.arange(0, len(cloud), 3)
    doubled = seam_copies(cloud, seam, turn=-2.0 * cloud.normals[seam])  # facing the other way
    prepared, report = prepare(doubled, elliptical=True)
    assert "coincident" not in report
    assert np.array_equal(prepared.normals, doubled.normals)
