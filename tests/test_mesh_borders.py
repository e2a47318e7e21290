"""A mesh's boundary edges are its borders (preprocess/borders.py, `mesh_border_outwards`)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import Delaunay

from models import mesh_cloud, unit_sphere
from samples import covered_by
from surfel.cloud import PointCloud
from surfel.preprocess import prepare
from surfel.preprocess.borders import mesh_border_outwards

H = 0.05                       # the sheet's vertex spacing
SLOT = (0.45, 0.55, 0.6)       # x from, x to, y up to: a notch two spacings wide, cut from below


def _in_slot(x, y):
    """Strictly inside the slot: the grid's vertices on its edges (up to rounding) are not."""
    return (x > SLOT[0] + 1e-9) & (x < SLOT[1] - 1e-9) & (y < SLOT[2] - 1e-9)


def slotted_sheet() -> tuple[np.ndarray, np.ndarray]:
    """A flat unit square (z = 0) with a narrow slot cut into it from one side, as a cut-out
    figure's legs fork: vertices on a grid of spacing H, triangulated, the slot's faces dropped."""
    s = np.arange(0, 1 + 1e-9, H)
    x, y = (g.ravel() for g in np.meshgrid(s, s, indexing="ij"))
    keep = ~_in_slot(x, y)
    vertices = np.stack([x[keep], y[keep], np.zeros(keep.sum())], 1)
    faces = Delaunay(vertices[:, :2]).simplices
    centre = vertices[faces].mean(axis=1)
    return vertices, faces[~_in_slot(centre[:, 0], centre[:, 1])].astype(np.int64)


def test_boundary_vertices_face_out_of_the_mesh_through_seams_and_rounding():
    """The vertices on the boundary, and only they, get the outward direction of the sheet's
    edge there; each face given corners of its own (a seam everywhere), moved apart by a CAD
    export's rounding, leaves the same borders."""
    vertices, faces = slotted_sheet()
    normals = np.tile([0.0, 0, 1], (len(vertices), 1))
    outwards = mesh_border_outwards(vertices, faces, normals)
    x, y = vertices[:, 0], vertices[:, 1]
    on_square = (x == 0) | (x == 1) | (y == 0) | (y == 1)
    on_slot = np.isclose(x, SLOT[0]) | np.isclose(x, SLOT[1])
    on_slot &= y <= SLOT[2] + 1e-9
    on_slot |= np.isclose(y, SLOT[2]) & (x >= SLOT[0] - 1e-9) & (x <= SLOT[1] + 1e-9)
    assert np.array_equal(np.any(outwards != 0, axis=1), on_square | on_slot)
    right_side = (x == 1) & (y > 0) & (y < 1)
    assert np.allclose(outwards[right_side], [1, 0, 0])
    slot_left_wall = np.isclose(x, SLOT[0]) & (y > 0) & (y < SLOT[2] - 1e-9)
    assert np.allclose(outwards[slot_left_wall], [1, 0, 0])  # out of the sheet is into the slot
    corners = vertices[faces.ravel()] * (1 + 1e-12 * np.random.default_rng(3).standard_normal((faces.size, 1)))
    split = mesh_border_outwards(corners, np.arange(faces.size).reshape(-1, 3), normals[faces.ravel()])
    assert np.allclose(split, outwards[faces.ravel()], atol=1e-9)


@pytest.mark.parametrize("split", [False, True])
def test_a_narrow_notch_in_a_meshs_outline_stays_open(split):
    """The splats beside a slot two spacings wide end at its edges when the faces say where
    they are; the vertices alone (the same positions and normals, no faces) look like a sheet
    going on across it, and their splats fill it. The sheet around it stays covered, past the
    slot's inner corners too, where the slot's walls end (their border lines cut no splat
    beyond them, cell_kernels.CHORD_SLACK). (The slot's mouth, a spacing deep, is left out of
    the slot: a convex corner of the outline has one border line, half-way between its edges'
    directions, which lets its splat reach past both.) `split`: each face has corners of its
    own, copies that `prepare` estimates once per position."""
    welded, faces = slotted_sheet()
    vertices = welded[faces.ravel()] if split else welded
    faces = np.arange(faces.size).reshape(-1, 3) if split else faces
    rng = np.random.default_rng(17)
    slot = np.stack([rng.uniform(SLOT[0] + 0.1 * H, SLOT[1] - 0.1 * H, 4000),
                     rng.uniform(H, SLOT[2] - 0.2 * H, 4000), np.zeros(4000)], 1)
    sheet = rng.uniform(0, 1, (20000, 3)) * [1, 1, 0]
    sheet = sheet[~_in_slot(sheet[:, 0], sheet[:, 1])]
    mesh, _ = prepare(mesh_cloud(vertices, faces, "slotted.obj"))
    everything = np.arange(len(mesh))
    assert covered_by(mesh, everything, slot).mean() < 0.01
    assert covered_by(mesh, everything, sheet).all()
    points, _ = prepare(PointCloud(welded, normals=np.tile([0.0, 0, 1], (len(welded), 1))))
    assert covered_by(points, np.arange(len(points)), slot).mean() > 0.5


def test_a_crack_between_two_patches_is_no_border():
    """Two halves of a square triangulated apart, the right one's vertices along their common
    edge half as many (T-junctions, as a decimation or a CAD export leaves them): only the
    square's outline is a border. Its edges moved apart by 0.3 spacings, the halves
    lie apart and both sides of the gap are borders."""
    s = np.arange(0, 1 + 1e-9, H)
    x, y = (g.ravel() for g in np.meshgrid(s, s, indexing="ij"))
    left = np.stack([x[x <= 0.5 + 1e-9], y[x <= 0.5 + 1e-9]], 1)
    right = np.stack([x[x >= 0.5 - 1e-9], y[x >= 0.5 - 1e-9]], 1)
    right = right[(right[:, 0] > 0.5 + 1e-9) | np.isclose(np.round(right[:, 1] / H) % 2, 0)]
    for gap, seam_borders in ((0.0, False), (0.3 * H, True)):
        halves = [left, right + [gap, 0.0]]
        faces = [Delaunay(half).simplices + offset for half, offset in zip(halves, (0, len(left)), strict=True)]
        vertices = np.c_[np.concatenate(halves), np.zeros(len(left) + len(right))]
        outwards = mesh_border_outwards(vertices, np.concatenate(faces).astype(np.int64),
                                        np.tile([0.0, 0, 1], (len(vertices), 1)))
        vx, vy = vertices[:, 0], vertices[:, 1]
        outline = np.isclose(vx, 0) | np.isclose(vx, 1 + gap) | np.isclose(vy, 0) | np.isclose(vy, 1)
        seam = ~outline & (np.abs(vx - 0.5 - gap / 2) <= gap / 2 + 1e-9)
        assert np.any(outwards != 0, axis=1)[outline].all()
        assert (np.any(outwards != 0, axis=1)[seam] == seam_borders).all()


def test_a_closed_mesh_has_no_border_and_prepares_as_its_vertices_do():
    """A closed mesh has no boundary edge; its splats and clip lines are those of its vertices
    alone."""
    sphere = unit_sphere()
    assert not mesh_border_outwards(sphere.positions, sphere.faces, sphere.normals).any()
    with_faces, _ = prepare(sphere)
    alone, _ = prepare(PointCloud(sphere.positions, normals=sphere.normals))
    assert np.array_equal(with_faces.attributes["clip_lines"], alone.attributes["clip_lines"])
    assert np.array_equal(with_faces.axes, alone.axes)
