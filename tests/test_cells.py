"""Tangent-plane cells: hole-free radii and ellipses, tangent frames, clip lines at creases and borders."""

from __future__ import annotations

import numpy as np
import pytest

from models import turned_part
from samples import (
    capped_cylinder,
    coverage,
    covered_by,
    dense_samples,
    edge_wedge,
    nn_spacing,
    scan_lines,
    sphere,
    unit,
)
from scenes import sheet_on_body, sheet_over_body
from surfel.cloud import PointCloud
from surfel.preprocess import (
    INACTIVE_CLIP,
    clipped_away,
    estimate_normals,
    estimate_radii,
    fit_ellipses,
    fit_normal_field,
    prepare,
    tangent_frames,
)

# --- radii and ellipses: hole-free coverage of the true surface ---------------------------------


@pytest.mark.parametrize("step", [1, 4])
def test_radii_and_ellipses_cover_a_dense_mesh(step):
    vertices, _, surface = dense_samples()
    points = vertices[::step]
    normals, _ = estimate_normals(points)
    radii = estimate_radii(points, normals=normals)
    assert radii.dtype == np.float32 and (radii > 0).all()
    assert coverage(surface, points, normals, tangent_frames(normals, radii)) >= 0.999
    ellipses = fit_ellipses(points, normals)
    assert coverage(surface, points, normals, ellipses) >= 0.999
    # not needlessly large: about the nearest-neighbour spacing, ellipses smaller than the disks
    assert radii.mean() < 2.0 * nn_spacing(points)
    area = np.prod(np.linalg.norm(ellipses, axis=2), axis=1)
    assert area.mean() <= (radii.astype(np.float64) ** 2).mean()


def test_radii_are_the_voronoi_cells_covering_radii():
    """On a plane, a point's radius is RADIUS_MARGIN times the distance to the farthest vertex
    of its Voronoi cell (scipy's), wherever its RADIUS_NEIGHBOURS nearest hold all the cell's
    neighbours and the cell lies inside the cap's octagon: every bisector that cuts the cell
    cuts it, whatever the kernel skips."""
    from scipy.spatial import Voronoi, cKDTree

    from surfel.preprocess.cell_kernels import CAP_SIDES
    from surfel.preprocess.cells import RADIUS_MARGIN, RADIUS_NEIGHBOURS

    rng = np.random.default_rng(11)
    xy = rng.uniform(-1, 1, (3000, 2))
    radii = estimate_radii(np.c_[xy, np.zeros(len(xy))], normals=np.tile([0.0, 0.0, 1.0], (len(xy), 1)))
    voronoi = Voronoi(xy)
    distance, nearest = cKDTree(xy).query(xy, RADIUS_NEIGHBOURS)
    neighbours = [set() for _ in xy]
    for a, b in voronoi.ridge_points:
        neighbours[a].add(b)
        neighbours[b].add(a)
    checked = []
    for i in np.flatnonzero(np.abs(xy).max(axis=1) < 0.8):
        farthest = np.linalg.norm(voronoi.vertices[voronoi.regions[voronoi.point_region[i]]] - xy[i], axis=1).max()
        if neighbours[i] <= set(nearest[i]) and farthest < distance[i, -1] * np.cos(np.pi / CAP_SIDES):
            checked.append((radii[i], RADIUS_MARGIN * farthest))
    assert len(checked) > 1000
    assert np.allclose(*np.array(checked).T, rtol=1e-6)


def test_radii_and_ellipses_cover_lidar_scan_lines():
    rng = np.random.default_rng(6)
    strip = scan_lines(rng, 0.0, line=1.0, along=0.3)
    overlap = scan_lines(rng, 0.5, line=1.3, along=0.25)  # a second flight line over half the tile
    xy = np.concatenate([strip, overlap[overlap[:, 0] > 0]])

    def height(xy):
        return 0.5 * np.sin(xy[:, 0] / 7)

    points = np.c_[xy, height(xy) + rng.normal(0, 0.02, len(xy))]
    normals, _ = estimate_normals(points)
    radii = estimate_radii(points, normals=normals)
    sample = rng.uniform(-22, 22, (200_000, 2))
    surface = np.c_[sample, height(sample)]
    assert coverage(surface, points, normals, tangent_frames(normals, radii)) >= 0.999
    assert coverage(surface, points, normals, fit_ellipses(points, normals)) >= 0.999


def test_isolated_point_gets_no_blob():
    rng = np.random.default_rng(7)
    points = np.c_[rng.uniform(-1, 1, (5_000, 2)), np.zeros(5_000)]
    points = np.concatenate([points, [[0.0, 0.0, 0.5]]])  # a stray return above the surface
    radii = estimate_radii(points)
    assert radii[-1] <= 3 * np.median(radii)  # its cell alone would be 0.5 across, 15 x the median


def test_a_sheet_lying_on_a_body_leaves_no_holes_beside_its_rim():
    # the rim's small cells must not cap the body's splats beside it: the outlier cap compares a
    # point with the neighbours on its own surface
    rng = np.random.default_rng(11)
    points, normals, body = sheet_on_body(rng)
    beside = np.c_[rng.uniform(-10, 10, 50_000), rng.uniform(0.5, 3.0, 50_000), np.zeros(50_000)]
    radii = estimate_radii(points, normals=normals)
    # capped by the median over all neighbours: 0.84 and 0.83
    assert coverage(beside, points[body], normals[body], tangent_frames(normals[body], radii[body])) >= 0.995
    ellipses = fit_ellipses(points, normals)
    assert coverage(beside, points[body], normals[body], ellipses[body]) >= 0.995


def test_tangent_frames_orthonormal():
    rng = np.random.default_rng(8)
    poles = [[0, 0, 1], [0, 0, -1], [1e-9, 0, -1], [1, 0, 0], [1, 0, -0.0]]  # where naive frames break
    normals = unit(np.concatenate([rng.normal(size=(1_000, 3)), poles]))
    radii = rng.uniform(0.5, 2, len(normals))
    axes = tangent_frames(normals, radii)
    assert axes.shape == (len(normals), 2, 3) and axes.dtype == np.float32
    u, v = axes[:, 0] / radii[:, None], axes[:, 1] / radii[:, None]
    assert np.allclose(np.linalg.norm(u, axis=1), 1, atol=1e-5) and np.allclose(np.linalg.norm(v, axis=1), 1, atol=1e-5)
    assert np.abs(np.einsum("ij,ij->i", u, v)).max() < 1e-5
    assert np.abs(np.einsum("ij,ij->i", u, normals)).max() < 1e-5
    assert np.allclose(np.cross(u, v), normals, atol=1e-5)  # right-handed (u, v, n)


def test_compiled_frames_match_the_formula():
    """frames.py's kernels give exactly the numpy evaluation of Duff et al.'s listing 3, and
    unit leaves zero rows zero."""
    from surfel.preprocess.frames import orthonormal_basis
    from surfel.preprocess.frames import unit as unit_rows

    rng = np.random.default_rng(3)
    v = np.concatenate([rng.normal(size=(5_000, 3)), [[0, 0, 0], [0, 0, -1], [1e-9, 0, -1]]])
    reference = v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-300)
    n = unit_rows(v.astype(np.float32))
    assert n.dtype == np.float64 and np.array_equal(unit_rows(v), reference) and not n[5_000].any()
    x, y, z = reference[:, 0], reference[:, 1], reference[:, 2]
    sign = np.copysign(1.0, z)
    a = -1.0 / (sign + z)
    b = x * y * a
    t = np.stack([1.0 + sign * x * x * a, sign * b, -sign * x], axis=1)
    s = np.stack([b, sign + y * y * a, -y], axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        assert np.array_equal(orthonormal_basis(reference), np.stack([t, s], axis=1), equal_nan=True)
    # the unit rows it made come back as they are (read-only); equal values made elsewhere are divided again
    assert unit_rows(n) is n and not n.flags.writeable and unit_rows(n.copy()) is not n
    assert np.array_equal(unit_rows(n.copy()), n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-300))


def test_tangent_frames_are_the_scaled_basis_rounded_once():
    """tangent_frames' one kernel gives the bits of its steps: unit normals, their basis, times
    the radii in float64, rounded to float32 (zero and -0 rows, float32 inputs included)."""
    from surfel.preprocess.frames import orthonormal_basis
    from surfel.preprocess.frames import unit as unit_rows

    rng = np.random.default_rng(5)
    v = np.concatenate([rng.normal(size=(5_000, 3)) * 3, [[0, 0, 0], [0, 0, -1], [1e-9, 0, -1], [1, 0, -0.0]]])
    radii = np.concatenate([rng.uniform(0, 2, 5_000), [1.0, 0.0, 2.5, 1e-30]])
    for normals, r in ((v, radii), (v.astype(np.float32), radii.astype(np.float32))):
        steps = orthonormal_basis(unit_rows(normals)) * np.asarray(r, np.float64)[:, None, None]
        assert np.array_equal(tangent_frames(normals, r).view(np.uint32), steps.astype(np.float32).view(np.uint32))


def test_cloud_bounds_are_the_corners():
    rng = np.random.default_rng(4)
    positions = rng.normal(size=(10_000, 3)) * [1, 100, 1e-3] + [5e5, -3, 0]
    lo, hi = PointCloud(positions).bounds
    assert np.array_equal(lo, positions.min(axis=0)) and np.array_equal(hi, positions.max(axis=0))


def test_any_per_row_is_numpys():
    from surfel.cloud import any_per_row

    rng = np.random.default_rng(5)
    for columns in (1, 2, 3, 16):
        mask = rng.random((5_000, columns)) > 0.9
        assert np.array_equal(any_per_row(mask), mask.any(axis=1))
    assert any_per_row(np.zeros((0, 3), bool)).shape == (0,)


def test_ellipse_axes_are_tangent_and_right_handed():
    p = sphere(5_000)
    axes = fit_ellipses(p, p).astype(np.float64)
    lengths = np.linalg.norm(axes, axis=2)
    assert (lengths[:, 0] >= lengths[:, 1] - 1e-7).all()  # u is the major axis
    assert np.abs(np.einsum("ntj,nj->nt", axes, p)).max() < 1e-5 * lengths.max()
    assert (np.einsum("ij,ij->i", np.cross(axes[:, 0], axes[:, 1]), p) > 0).all()


def test_ellipses_follow_the_principal_curvature_directions():
    """On a cylinder sampled at random the neighbours spread evenly, so only the normals tell
    the principal directions: around (curvature 1) and along the axis (curvature 0)."""
    rng = np.random.default_rng(12)
    phi, height = rng.uniform(0, 2 * np.pi, 20_000), rng.uniform(-3, 3, 20_000)
    normals = np.c_[np.cos(phi), np.sin(phi), np.zeros_like(phi)]
    points = normals + np.c_[np.zeros((len(phi), 2)), height]
    axes = fit_ellipses(points, normals)
    lengths = np.linalg.norm(axes.astype(np.float64), axis=2)
    axial = np.abs(axes[:, 0, 2]) / lengths[:, 0]  # |cos| of u's angle to the cylinder's axis
    assert ((axial > 0.97) | (axial < 0.25)).mean() > 0.99
    alpha, beta = fit_normal_field(points, normals, axes)
    around, along = np.where(axial > 0.97, beta, alpha), np.where(axial > 0.97, alpha, beta)
    around_length = np.where(axial > 0.97, lengths[:, 1], lengths[:, 0])
    # eq. 8 then holds exactly: the tilt at the rim is semi-axis / radius around, 0 along
    assert np.median(np.abs(around / around_length - 1)) < 0.01
    assert np.median(np.abs(along) / around_length) < 0.001


def test_normals_passed_as_k_are_refused():
    p = sphere(100)
    with pytest.raises(TypeError, match="k must be a positive integer"):
        estimate_radii(p, p)  # normals= is a keyword: the second argument is k


# --- sharp features ------------------------------------------------------------------------------


def test_sharp_edge_splats_end_at_the_edge():
    """Splats at a crease are cut at the other face's plane and still cover their own face up
    to the edge; the edge's own points (normals averaged over both faces) are dropped."""
    h = 0.05
    cloud, labels = edge_wedge(h)
    prepared, report = prepare(cloud)
    lines = prepared.attributes["clip_lines"]
    assert "sharp_features" in report
    dropped = lines[:, 0, 2] < -1
    assert dropped[labels == 2].mean() > 0.8 and not dropped[labels < 2].any()
    rng = np.random.default_rng(4)
    # face A: nothing sticks out past x = 0, and the strip next to the edge is covered
    face_a = np.flatnonzero(labels == 0)
    beyond = np.stack([rng.uniform(0.002, 2 * h, 4000), rng.uniform(0.1, 0.9, 4000), np.zeros(4000)], 1)
    assert not covered_by(prepared, face_a, beyond).any()
    strip = np.stack([rng.uniform(-2 * h, 0, 4000), rng.uniform(0.1, 0.9, 4000), np.zeros(4000)], 1)
    assert covered_by(prepared, face_a, strip).all()
    # without sharp features the edge's splats are whole disks, and they stick out of the solid
    plain, _ = prepare(cloud, sharp_features=False)
    assert "clip_lines" not in plain.attributes
    edge = np.flatnonzero(labels == 2)
    uv = rng.uniform(-0.7, 0.7, (500, 2))
    disk = (plain.positions[edge][:, None] + uv[None, :, :1] * plain.axes[edge][:, None, 0]
            + uv[None, :, 1:] * plain.axes[edge][:, None, 1])
    assert ((disk[..., 0] > 0.01 * h) | (disk[..., 2] > 0.01 * h)).mean() > 0.5


def test_a_face_cuts_the_splats_of_a_coarse_curved_surface_meeting_it():
    """A flat cap on a cylinder sampled as a CAD part's mesh is, 12 vertices round: the side's
    normals turn 30 degrees from vertex to vertex, so no point there is flat, but the cap is.
    The rim's splats (normals averaged over cap and side) end at the cap's plane instead of
    standing above it."""
    side, cap, circle, normals = capped_cylinder()
    step = 2 * np.pi / len(circle)
    prepared, _ = prepare(PointCloud(np.concatenate([side, cap, circle]), normals=normals))
    rim = np.arange(len(side) + len(cap), len(prepared))
    lines = prepared.attributes["clip_lines"][rim].astype(np.float64)
    axes = prepared.axes[rim].astype(np.float64)
    uv = np.random.default_rng(1).uniform(-1, 1, (4000, 2))
    uv = uv[(uv ** 2).sum(1) <= 1]
    kept = ((lines[:, None, :, 0] * uv[None, :, None, 0] + lines[:, None, :, 1] * uv[None, :, None, 1])
            <= lines[:, None, :, 2]).all(axis=2)
    height = prepared.positions[rim, 2:3] + uv[None, :, 0] * axes[:, None, 0, 2] + uv[None, :, 1] * axes[:, None, 1, 2]
    assert kept.any(axis=1).all()
    assert height[kept].max() < 1e-4 * step


def test_a_coarse_face_leaves_a_bolt_hole_open():
    """A CAD plate triangulated coarsely around a bolt hole of radius 1: the hole's wall is a
    cylinder 16 vertices round (no point on it is flat), its rim's normals are averaged over
    plate and wall, and the plate's vertices lie on rings 2, 4 and 6 from the hole's axis. The
    plate's big splats reached across the hole (86% of its core covered); the rim points, in
    the plate's plane with normals 45 degrees off, now end them short of it, and the plate
    itself stays covered."""
    around = 16
    angles = 2 * np.pi * np.arange(around) / around
    rim = np.stack([np.cos(angles), np.sin(angles), np.zeros(around)], 1)
    wall = np.concatenate([rim - [0, 0, 0.4 * k] for k in range(1, 4)])
    plate = np.concatenate([np.stack([radius * np.cos(a), radius * np.sin(a), 0 * a], 1)
                            for radius, count, turn in [(2.0, 8, 0.0), (4.0, 12, 0.3), (6.0, 16, 0.0)]
                            for a in [turn + 2 * np.pi * np.arange(count) / count]])
    normals = np.concatenate([np.tile([0.0, 0, 1], (len(plate), 1)), -wall * [1, 1, 0], unit(-rim + [0, 0, 1])])
    prepared, _ = prepare(PointCloud(np.concatenate([plate, wall, rim]), normals=normals))
    rng = np.random.default_rng(0)
    distance, angle = np.sqrt(rng.uniform(0, 36, 20000)), rng.uniform(0, 2 * np.pi, 20000)
    samples = np.stack([distance * np.cos(angle), distance * np.sin(angle), np.zeros_like(distance)], 1)
    covered = covered_by(prepared, np.arange(len(plate)), samples)
    assert covered[distance < 0.5].mean() < 0.25
    assert covered[(distance > 1) & (distance < 5.5)].all()


def test_a_crease_line_through_the_splat_keeps_the_side_away_from_the_neighbour_whatever_its_axes():
    """A splat's centre p on its neighbour's tangent plane cannot tell the crease's sides apart
    by its own height: it keeps the side away from where q projects into its plane. In the
    splat's semi-axes (u, v), q's coordinates there are its offsets along them over |u|^2 and
    |v|^2; taken without, an elliptical splat (|u| = 4, |v| = 1/2) kept q's side."""
    from surfel.preprocess.cell_kernels import _crease_half_plane

    normal_q = unit(np.array([-0.1, 0.5, 0.8]))
    points = np.array([[0.0, 0, 0], [1.0, 1.0, -0.5]])  # p, and q with p on q's plane
    rng = np.random.default_rng(0)
    offsets = np.concatenate([rng.uniform(-2, 2, (500, 2)), np.zeros((500, 1))], 1)  # in p's plane z = 0
    q_in_plane = points[1] * [1, 1, 0]
    for lengths in [(1.0, 1.0), (4.0, 0.5), (0.5, 4.0)]:
        frame = np.diag([*lengths, 0.0])[:2]
        a, b, c = _crease_half_plane(points, 0, 1, normal_q, frame, 1e-4)
        # world points p + x u + y v: x = offset . u / |u|^2, y likewise
        coordinates = offsets[:, :2] / lengths
        kept = coordinates @ [a, b] <= c
        assert np.array_equal(kept, offsets @ normal_q <= 0), lengths  # the half-plane away from q
        assert q_in_plane[:2] / lengths @ [a, b] > c, lengths


def _panel_under_a_fillet() -> tuple[np.ndarray, np.ndarray]:
    """Columns 0.012 apart: a panel facing +z at v >= 0 (rows 0.012 apart), and from its last
    row v = 0 a fillet sampled every 0.001, rising at 53 degrees over -v and rolling over to
    24 degrees (a car's door panel below the fillet of its belt line). (positions, unit normals)."""
    columns = np.arange(-0.06, 0.0601, 0.012)
    panel = [(u, v, 0.0) for u in columns for v in np.arange(0.0, 0.0601, 0.012)]
    fillet, fillet_normals = [], []
    for u in columns:
        v = z = 0.0
        for k in range(40):
            rise = np.radians(53.0 - 8.0 * k / 11.0)
            v, z = v - 0.001 * np.cos(rise), z + 0.001 * np.sin(rise)
            fillet.append((u, v, z))
            fillet_normals.append((0.0, np.sin(rise), np.cos(rise)))
    normals = np.concatenate([np.tile([0.0, 0.0, 1.0], (len(panel), 1)), fillet_normals])
    return np.array(panel + fillet), normals


def _panel_features():
    """The panel and fillet's neighbourhood, sorted normals and sharp features, with the panel's
    last row neither flat nor a crease (a curved door's), and the index of its middle point."""
    from surfel.preprocess.cells import RADIUS_NEIGHBOURS
    from surfel.preprocess.neighbourhood import Neighbourhood
    from surfel.preprocess.sharp_features import find_sharp_features

    positions, normals = _panel_under_a_fillet()
    nbh = Neighbourhood.build(positions, RADIUS_NEIGHBOURS, -1, False)
    sorted_normals = nbh.sort(normals)
    last_row = nbh.sort((positions[:, 1] == 0.0) & (positions[:, 2] == 0.0))
    features = find_sharp_features(nbh, sorted_normals, RADIUS_NEIGHBOURS)
    features = features._replace(flat=features.flat & ~last_row, crease=features.crease & ~last_row)
    return nbh, sorted_normals, features, int(np.argmin(np.linalg.norm(positions, axis=1)))


def test_a_face_below_a_concave_fillet_keeps_its_side_of_the_crease():
    """The panel's last row, not flat itself (a curved door's), lies on the crease with the
    fillet. The fillet's first rows cut its splats there, through their centres. Its farther
    rows, rolled over, turn their planes back across the panel: their lines cut the panel's
    side too, and the splat kept a sliver 3% of its radius wide, off its centre (holes along a
    car's door, beetle-alt.obj)."""
    from surfel.preprocess.cells import clip_lines

    nbh, sorted_normals, features, centre = _panel_features()
    count = len(sorted_normals)
    axes = tangent_frames(sorted_normals, np.full(count, 0.006))
    lines = nbh.unsort(clip_lines(nbh, sorted_normals, axes, features, np.zeros((count, 3)), np.zeros(count), False))
    u_axis, v_axis = nbh.unsort(axes)[centre]
    for offset, kept in [((0.0, 0.0), True), ((0.0, 0.003), True), ((0.003, 0.005), True), ((0.0, -0.003), False)]:
        world = np.array([*offset, 0.0])
        local = np.array([world @ u_axis / (u_axis @ u_axis), world @ v_axis / (v_axis @ v_axis)])
        assert np.all(lines[centre, :, :2] @ local <= lines[centre, :, 2]) == kept, (offset, lines[centre])


def test_a_face_below_a_concave_fillet_keeps_its_cell():
    """The same panel and fillet: the last row's cell reaches half-way to the next row and to
    its columns' neighbours, as on an open panel. The fillet's farther rows, whose planes turn
    back across the panel, cut it too, and left a disk 0.7 times as wide, an ellipse 0.3
    times as wide across the rows (holes along a car's door, beetle-alt.obj)."""
    from surfel.preprocess.cells import RADIUS_MARGIN, covering_ellipses, covering_radii

    nbh, sorted_normals, features, centre = _panel_features()
    radius = nbh.unsort(covering_radii(nbh, sorted_normals, False, features=features))[centre]
    semi_axes = np.linalg.norm(nbh.unsort(covering_ellipses(nbh, sorted_normals, False, features=features)[0])[centre],
                               axis=1)
    half_row = 0.006  # rows and columns lie 0.012 apart
    assert radius >= 0.999 * RADIUS_MARGIN * np.hypot(half_row, half_row)
    assert semi_axes.min() >= 0.999 * RADIUS_MARGIN * half_row


def test_a_tip_gets_a_small_splat_and_stays_covered():
    """The apex of a cone of half-angle 20 degrees (a horn, a hoof), sampled in rings as a mesh's
    vertices are: all its neighbours lie more than 45 degrees below its tangent plane. Its cell
    ends where their tangent planes meet its own, so its disk, which stands out sideways past
    the tip seen from the side, is narrower than the first ring lies from the axis (it was as
    wide as the whole neighbourhood, four times that), and the cone stays covered."""
    half, step = np.radians(20.0), 0.1
    points, normals = [np.zeros((1, 3))], [np.array([[0.0, 0, 1]])]
    for ring in range(1, 16):
        count = max(6, round(2 * np.pi * ring * np.sin(half)))
        around = 2 * np.pi * (np.arange(count) + 0.5 * ring) / count
        radius, height = ring * step * np.sin(half), -ring * step * np.cos(half)
        points.append(np.stack([radius * np.cos(around), radius * np.sin(around), np.full(count, height)], 1))
        normals.append(np.stack([np.cos(half) * np.cos(around), np.cos(half) * np.sin(around),
                                 np.full(count, np.sin(half))], 1))
    points, normals = np.concatenate(points), np.concatenate(normals)
    radii = estimate_radii(points, normals=normals)
    assert radii[0] < step * np.sin(half)
    rng = np.random.default_rng(0)
    slant, around = np.sqrt(rng.uniform(0, (10 * step) ** 2, 100_000)), rng.uniform(0, 2 * np.pi, 100_000)
    surface = np.stack([slant * np.sin(half) * np.cos(around), slant * np.sin(half) * np.sin(around),
                        -slant * np.cos(half)], 1)
    assert coverage(surface, points, normals, tangent_frames(normals, radii)) >= 0.998


def test_smooth_surfaces_get_no_clip_lines():
    """A coarsely sampled sphere has neighbours with very different normals, but no faces:
    its splats stay whole disks."""
    p = sphere(300, seed=5)
    prepared, report = prepare(PointCloud(p, normals=p))
    lines = prepared.attributes.get("clip_lines")
    assert lines is None or (lines[:, :, 2] >= 1).all()


def test_a_surface_sampled_from_both_sides_keeps_its_splats():
    """A scan that sees an open shell from inside and out: denoised, the samples facing either
    way interleave in one plane, and each one's plane holds the others. That is no crease: no
    point is dropped, and no splat away from the sheet's border is cut."""
    rng = np.random.default_rng(3)
    grid = np.arange(-1, 1 + 1e-9, 0.05)
    x, y = (values.ravel() for values in np.meshgrid(grid, grid))
    points = np.stack([x, y, np.zeros(len(x))], 1)
    normals = unit(np.array([0.0, 0, 1]) + rng.normal(0, 0.03, (len(x), 3)) * [1, 1, 0])
    normals[rng.random(len(x)) < 0.5] *= -1
    prepared, _ = prepare(PointCloud(points, normals=normals))
    lines = prepared.attributes["clip_lines"]
    inner = np.abs(points).max(axis=1) < 0.8
    assert not clipped_away(prepared).any()
    assert (lines[inner, :, 2] >= 1).all()


# --- borders of open surfaces ------------------------------------------------------------------


def _open_sheet(h: float = 0.05):
    """A flat unit square (z = 0, normal +z) sampled on a grid of spacing h, jittered inside and
    along its four straight borders, as a mesh's vertices sample an open sheet."""
    rng = np.random.default_rng(11)
    s = np.arange(0, 1 + 1e-9, h)
    x, y = (g.ravel() for g in np.meshgrid(s, s, indexing="ij"))
    inner_x, inner_y = (0 < x) & (x < 1), (0 < y) & (y < 1)
    x = x + np.where(inner_x, rng.uniform(-0.2 * h, 0.2 * h, x.size), 0.0) * inner_y
    y = y + np.where(inner_y, rng.uniform(-0.2 * h, 0.2 * h, y.size), 0.0) * inner_x
    points = np.stack([x, y, np.zeros(x.size)], 1)
    return PointCloud(points, normals=np.tile([0.0, 0, 1], (len(points), 1)))


def test_open_sheets_end_at_their_border():
    """The splats of an open sheet end at its border line instead of spilling past it by
    their radius, and the sheet stays covered up to the border."""
    h = 0.05
    prepared, _ = prepare(_open_sheet(h))
    everything = np.arange(len(prepared))
    rng = np.random.default_rng(12)
    beyond = np.stack([rng.uniform(1 + 0.05 * h, 1 + 2 * h, 4000), rng.uniform(0.1, 0.9, 4000), np.zeros(4000)], 1)
    assert covered_by(prepared, everything, beyond).mean() < 0.01
    inside = np.stack([rng.uniform(0, 1, 20000), rng.uniform(0, 1, 20000), np.zeros(20000)], 1)
    assert covered_by(prepared, everything, inside).all()
    # without the border lines the same splats spill past the border
    inactive = np.broadcast_to(np.float32(INACTIVE_CLIP), prepared.attributes["clip_lines"].shape)
    whole = prepared.with_(attributes={**prepared.attributes, "clip_lines": inactive})
    assert covered_by(whole, everything, beyond).mean() > 0.5


def test_thin_closed_parts_end_at_their_rim():
    """A thin closed part (a cut-out figure, a tail: two sides 0.4 spacings apart, facing away
    from each other) ends at its rim as an open sheet does: the far side's samples close no
    border gap, so neither side spills past the rim, and the border line moves out as far as
    the far side reaches, so the narrower side still covers up to the wider one's rim."""
    h = 0.05
    top = _open_sheet(h)
    wider = 1 + 0.5 * h  # the bottom side reaches half a spacing further in x
    bottom = top.positions * [wider, 1.0, 1.0] - [0.0, 0.0, 0.4 * h]
    cloud = PointCloud(np.concatenate([top.positions, bottom]),
                       normals=np.concatenate([top.normals, -top.normals]))
    prepared, _ = prepare(cloud)
    rng = np.random.default_rng(15)
    everything = np.arange(len(prepared))
    beyond = np.stack([rng.uniform(wider + 0.05 * h, 1 + 2 * h, 4000), rng.uniform(0.1, 0.9, 4000), np.zeros(4000)], 1)
    assert covered_by(prepared, everything, beyond).mean() < 0.01
    inside = np.stack([rng.uniform(0, 1, 20000), rng.uniform(0, 1, 20000), np.zeros(20000)], 1)
    top_side = np.arange(len(top.positions))
    assert covered_by(prepared, top_side, inside).all()
    between_rims = np.stack([rng.uniform(1 + 0.05 * h, wider - 0.05 * h, 2000), rng.uniform(0.1, 0.9, 2000),
                             np.zeros(2000)], 1)
    assert covered_by(prepared, top_side, between_rims).mean() > 0.95
    inactive = np.broadcast_to(np.float32(INACTIVE_CLIP), prepared.attributes["clip_lines"].shape)
    whole = prepared.with_(attributes={**prepared.attributes, "clip_lines": inactive})
    assert covered_by(whole, everything, beyond).mean() > 0.5


def test_a_noisy_scan_moves_its_border_lines_out():
    """A raw scan's last samples lie short of its edge: where the normals were estimated on a
    noisy cloud, its border lines lie NOISY_MARGIN further out than those of the same cloud
    given the normals it estimated, and it covers more of the strip past its last samples."""
    from surfel.preprocess import borders

    h = 0.05
    sheet = _open_sheet(h)
    rng = np.random.default_rng(16)
    noisy = sheet.positions + np.c_[np.zeros((len(sheet), 2)), rng.normal(0, 0.15 * h, len(sheet))]
    estimated, report = prepare(PointCloud(noisy))
    assert "noisy" in report["normals"]
    given, _ = prepare(PointCloud(noisy, normals=estimated.normals))
    out, kept = estimated.attributes["clip_lines"][:, 0], given.attributes["clip_lines"][:, 0]
    border = (out[:, 2] < 1) & (kept[:, 2] < 1)
    assert border.sum() > 40
    assert np.allclose(out[border, 2] - kept[border, 2], borders.NOISY_MARGIN, atol=1e-5)
    everything = np.arange(len(noisy))
    strip = np.stack([rng.uniform(1, 1 + 0.1 * h, 2000), rng.uniform(0.1, 0.9, 2000), np.zeros(2000)], 1)
    assert covered_by(estimated, everything, strip).mean() > covered_by(given, everything, strip).mean() + 0.2


def test_a_denoised_scan_keeps_the_margin_of_its_border_lines():
    """Denoising (`prepare --smooth`) leaves the scan's samples lost near its edge lost: its
    border lines still lie NOISY_MARGIN further out than those of the same positions taken for
    a clean cloud, though the normals estimated after smoothing no longer find it noisy."""
    from surfel.preprocess import borders

    h = 0.05
    sheet = _open_sheet(h)
    rng = np.random.default_rng(16)
    noisy = sheet.positions + np.c_[np.zeros((len(sheet), 2)), rng.normal(0, 0.15 * h, len(sheet))]
    smoothed, report = prepare(PointCloud(noisy), smooth=True)
    assert "smooth" in report and "noisy" not in report["normals"]
    clean, _ = prepare(PointCloud(smoothed.positions))
    out, kept = smoothed.attributes["clip_lines"][:, 0], clean.attributes["clip_lines"][:, 0]
    border = (out[:, 2] < 1) & (kept[:, 2] < 1)
    assert border.sum() > 40
    assert np.allclose(out[border, 2] - kept[border, 2], borders.NOISY_MARGIN, atol=1e-5)


def _rows(x, step, y_step=0.018):
    """Points of the plane z = 0 at x in `x` (a range with `step`), y in [-0.3, 0.3] every y_step."""
    xs, ys = np.meshgrid(np.arange(x[0], x[1] + 1e-9, step), np.arange(-0.3, 0.3 + 1e-9, y_step), indexing="ij")
    return np.c_[xs.ravel(), ys.ravel(), np.zeros(xs.size)]


def test_a_face_of_sparse_rows_beside_a_dense_strip_has_no_border():
    """A CAD part's face tessellated by rows 0.05 apart (0.018 along them) between two strips
    sampled 0.006 apart (fillets): the 64 nearest of the rows' points all lie in the strip
    beside them, but the next row lies within their closing distance ahead, so no border cuts
    their splats; where no row follows, the last row is a border."""
    strip = _rows((-0.08, -0.012), 0.006, 0.006)
    row, next_row = _rows((0.0, 0.0), 1.0), _rows((0.05, 0.05), 1.0)
    other_strip = _rows((0.062, 0.13), 0.006, 0.006)
    middle = np.arange(len(strip), len(strip) + len(row))[5:-5]  # away from the rows' ends

    def clipped(*parts):
        points = np.concatenate(parts)
        prepared, _ = prepare(PointCloud(points, normals=np.tile([0.0, 0.0, 1.0], (len(points), 1))))
        return prepared.attributes["clip_lines"][middle, 0, 2] < 1

    assert not clipped(strip, row, next_row, other_strip).any()
    assert clipped(strip, row).all()


def test_a_lopsided_cell_cuts_its_splat_at_its_short_side():
    """A row of points 0.05 from the next row on one side and 0.01 from a dense strip on the
    other: its cells end 0.005 from it on the strip's side and reach 0.025 the other way. The
    ellipses, centred on the points, reached as far into the strip, where a curved surface
    stands them out of it (the beads along the Newell teapot's lid); a clip line at
    SHORT_MARGIN times the short side's distance ends them there, and the plane stays covered
    (not a scan's: its cells stay whole)."""
    from surfel.preprocess.cells import SHORT_MARGIN

    sparse, row, strip = _rows((-0.3, -0.05), 0.05, 0.03), _rows((0.0, 0.0), 1.0, 0.03), _rows((0.01, 0.1), 0.01, 0.03)
    points = np.concatenate([sparse, row, strip])
    prepared, _ = prepare(PointCloud(points, normals=np.tile([0.0, 0.0, 1.0], (len(points), 1))), elliptical=True)
    members = np.arange(len(sparse), len(sparse) + len(row))[3:-3]  # away from the rows' ends
    rng = np.random.default_rng(13)
    into_strip = np.c_[rng.uniform(SHORT_MARGIN * 0.005 + 1e-4, 0.025, 4000), rng.uniform(-0.2, 0.2, 4000),
                       np.zeros(4000)]
    assert not covered_by(prepared, members, into_strip).any()
    inside = np.c_[rng.uniform(-0.3, 0.1, 20000), rng.uniform(-0.25, 0.25, 20000), np.zeros(20000)]
    assert covered_by(prepared, np.arange(len(points)), inside).all()
    # without the line the row's ellipses reach into the strip
    inactive = np.broadcast_to(np.float32(INACTIVE_CLIP), prepared.attributes["clip_lines"].shape)
    whole = prepared.with_(attributes={**prepared.attributes, "clip_lines": inactive})
    assert covered_by(whole, members, into_strip).mean() > 0.3
    # a scan's cells stay whole: the same rows as an aerial survey's
    survey, _ = prepare(PointCloud(points, normals=np.tile([0.0, 0.0, 1.0], (len(points), 1)), geospatial=True),
                        elliptical=True)
    assert covered_by(survey, members, into_strip).mean() > 0.3


def test_closed_surfaces_and_aerial_scans_have_no_borders():
    """Neither a sphere, nor a sampling much denser on one side than the other, nor aerial
    LiDAR scan lines 30 times farther apart than the points on a line has border lines; the
    same lines taken for an object scan would have them."""
    rng = np.random.default_rng(13)
    p = sphere(2000, seed=3)
    dense = p[p[:, 2] > 0.3]
    sparse = p[p[:, 2] <= 0.3][::6]
    for points in [p, np.concatenate([dense, sparse])]:
        prepared, _ = prepare(PointCloud(points, normals=points))
        lines = prepared.attributes.get("clip_lines")
        assert lines is None or (lines[:, :, 2] >= 1).all()
    xy = scan_lines(rng, 0.3, line=1.0, along=0.03, half=6.0)
    interior = np.abs(xy).max(axis=1) < 4
    for geospatial in (True, False):
        cloud = PointCloud(np.c_[xy, np.zeros(len(xy))], normals=np.tile([0.0, 0, 1], (len(xy), 1)),
                           geospatial=geospatial)
        lines = prepare(cloud)[0].attributes["clip_lines"]
        assert (lines[interior, :, 2] >= 1).all() == geospatial


def test_compiled_border_and_cap_kernels_match_numpy():
    """The border kernel's gaps and the outlier cap's median, against numpy's sort and median
    on a half disc (a border along its diameter) with ragged radii."""
    from surfel.preprocess import borders, cells
    from surfel.preprocess.frames import orthonormal_basis
    from surfel.preprocess.neighbourhood import Neighbourhood
    from surfel.preprocess.outlier_cap import ISOLATED_FACTOR, outlier_cap

    # no BORDER_RUN + 1 consecutive empty bins leave no gap of BORDER_GAP (an angle is at most
    # twice its pseudo-angle): the kernel's early answer
    assert (borders.BORDER_RUN + 2) * borders.KEY_BIN < borders.BORDER_GAP / 2
    rng = np.random.default_rng(5)
    xy = rng.uniform(-1, 1, size=(4_000, 2))
    xy = xy[(np.hypot(*xy.T) < 1) & (xy[:, 1] > 0)]
    # and a lattice (neighbours in the same directions, gaps of exactly 45 and 90 degrees), a
    # half disc too, rotated off the frame's axes
    lattice = np.stack(np.meshgrid(np.arange(-30, 31), np.arange(0, 31)), -1).reshape(-1, 2) / 30.0
    lattice = lattice[np.hypot(*lattice.T) < 1] @ np.array([[0.8, 0.6], [-0.6, 0.8]])
    for plane in (xy, lattice):
        nbh = Neighbourhood.build(np.column_stack([plane, 0.01 * plane[:, 0] ** 2]), 16, progress=False)
        normals = np.tile([0.0, 0.0, 1.0], (len(nbh.points), 1))
        frames = orthonormal_basis(normals)
        rows = np.arange(len(nbh.points))
        unbounded = np.full(len(nbh.points), np.inf)
        got, reach = borders._border_outwards(nbh.points, normals, nbh.index, rows, frames, cells.SHEET_COS,
                                              borders.FLAT_SIN2, unbounded, unbounded)
        assert not reach.any()  # no fold: every normal faces one way
        d = nbh.points[nbh.index] - nbh.points[:, None]
        angles = np.sort(np.arctan2(np.einsum("nkj,nj->nk", d, frames[:, 1]),
                                    np.einsum("nkj,nj->nk", d, frames[:, 0]))[:, 1:], axis=1)
        gaps = np.diff(np.concatenate([angles, angles[:, :1] + 2 * np.pi], axis=1), axis=1)
        ranked = np.sort(gaps, axis=1)
        border = (ranked[:, -1] >= borders.BORDER_GAP) & (ranked[:, -2] <= borders.INTERIOR_GAP)
        assert border.sum() > 50 and np.array_equal(got.any(axis=1), border)
        widest = np.argmax(gaps, axis=1)
        middle = angles[rows, widest] + gaps[rows, widest] / 2
        expected = np.cos(middle)[:, None] * frames[:, 0] + np.sin(middle)[:, None] * frames[:, 1]
        assert np.allclose(got[border], expected[border], atol=1e-12)
    raw = rng.uniform(0.1, 1, len(nbh.points)) ** 4
    # another surface's points: many, or a few scattered ones (which have none on their surface)
    for share in (0.3, 0.02):
        flipped = np.where(rng.uniform(size=(len(raw), 1)) < share, -normals, normals)
        for k in (16, 15):  # an odd and an even count of neighbours
            index = nbh.index[:, :k]
            for oriented in (False, True):
                cap = outlier_cap(raw, index, flipped, oriented)
                same = (np.einsum("nkj,nj->nk", flipped[index[:, 1:]], flipped) > 0) | (not oriented)
                alone = ~same.any(axis=1)
                assert alone.any() == oriented
                same[alone] = True  # none on its surface: all count
                median = np.array([np.median(raw[row[1:]][keep]) for row, keep in zip(index, same, strict=True)])
                reference = np.minimum(1.0, ISOLATED_FACTOR * median / raw)
                assert np.array_equal(cap, reference) and (cap < 1).sum() > 10


def test_border_prefilter_bins_hold_every_direction_within_its_error():
    """The border kernel's early answer bins each near neighbour's direction (`_near_angles`)
    within ATAN_ERROR of its angle, and a gap of BORDER_GAP between two directions then leaves
    ANGLE_RUN + 1 whole bins empty: so the early answer drops no border (the kernel's gaps are
    checked against numpy's in the test above)."""
    from surfel.preprocess import borders

    width = 2 * np.pi / borders.ANGLE_BINS
    assert (borders.ANGLE_RUN + 2) * width <= borders.BORDER_GAP - 2 * borders.ATAN_ERROR
    rng = np.random.default_rng(8)
    angles = np.concatenate([rng.uniform(0, 2 * np.pi, 20_000), np.arange(16) * np.pi / 8])
    scale = np.exp(rng.uniform(-20, 5, len(angles)))
    found = []
    for angle, length in zip(angles, scale, strict=True):
        offsets = np.zeros((7, 2))
        offsets[0:2, 0] = length * np.cos(angle), length * np.sin(angle)
        offsets[5, 0] = 1.0  # the neighbour's normal, as the point's
        offsets[6] = np.inf, -1.0  # the second: the point itself, which counts as no neighbour
        bits = borders._near_angles(offsets, 2, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, np.inf, np.inf,
                                    borders.SHEET_COS, borders.FLAT_SIN2)
        assert bin(int(bits)).count("1") == 1
        found.append(int(bits).bit_length() - 1)
    found = np.array(found)
    lowest = np.floor((angles - borders.ATAN_ERROR) / width)
    highest = np.floor((angles + borders.ATAN_ERROR) / width)
    assert np.all((found == lowest % borders.ANGLE_BINS) | (found == highest % borders.ANGLE_BINS))
    assert (found != np.floor(angles / width) % borders.ANGLE_BINS).sum() > 0  # the error shows


def test_clip_kernel_early_answer_keeps_every_candidate():
    """A point none of whose neighbours `_cutting_neighbours` counts gets no clip line: every
    neighbour that makes a crease, rim, turn or border candidate (`_crease_candidates`,
    `_border_candidates`) is counted, over random neighbours of every kind (a turn's normal
    lies more than SHARP_ANGLE from p's: its neighbour is more than 45 degrees below p's plane
    and p below the neighbour's)."""
    from surfel.preprocess import cell_kernels
    from surfel.preprocess.frames import orthonormal_basis
    from surfel.preprocess.sharp_features import SharpFeatures

    rng = np.random.default_rng(21)
    index = np.array([[0, 1]])
    candidates = np.empty((4, 3))
    kinds = {"flat": 0, "curved": 0, "border": 0}  # which neighbours made candidates
    for _ in range(4000):
        points = np.zeros((2, 3))
        points[1] = rng.normal(size=3)
        normal = rng.normal(size=3)
        if rng.uniform() < 0.5:  # the neighbour's plane near p's: only turns and borders cut
            normal = normal * [0.2, 0.2, 1.0] + [0.0, 0.0, 1.0]
        normals = np.array([[0.0, 0.0, 1.0], normal / np.linalg.norm(normal)])
        features = SharpFeatures(rng.uniform(size=2) < 0.5, np.zeros(2, bool), *SharpFeatures.none(2)[2:])
        axes = orthonormal_basis(normals[:1]) * rng.uniform(0.2, 2.0)
        on_border = rng.uniform(size=2) < 0.1
        outwards = np.zeros((2, 3))
        tangents = rng.normal(size=(2, 3)) * [1, 1, 0]
        outwards[on_border] = (tangents / np.linalg.norm(tangents, axis=1, keepdims=True))[on_border]
        layers = np.full(2, np.inf)
        creases = cell_kernels._crease_candidates(points, normals, index, axes, 0, 0, features, layers, candidates)
        borders = cell_kernels._border_candidates(points, normals, index, axes, 0, 0, features, outwards, on_border,
                                                  np.zeros(2), 0.0, candidates, 0)
        gathered = np.vstack([(points - points[0]).T, normals.T, on_border[None].astype(float)])
        counted = cell_kernels._cutting_neighbours(gathered, 2, 0.0, 0.0, 1.0, features.sharp_cos)
        assert counted > 0 or creases + borders == 0
        kinds["flat" if features.flat[1] else "curved"] += creases > 0
        kinds["border"] += borders > 0
    assert min(kinds.values()) > 50, kinds


def test_crease_points_are_pairs_of_flat_neighbours_sharply_apart():
    """`_crease_points` (with its early answer, `_far_flat_neighbours`) against its rule written
    in numpy: a point is a crease point when two of its flat neighbours, p in both their planes
    and neither facing away, have normals more than SHARP_ANGLE apart; over random neighbours
    whose planes pass through p or miss it, near p's normal or not."""
    from surfel.preprocess import sharp_features as sf

    rng = np.random.default_rng(34)
    k = 6
    found = []
    for _ in range(3000):
        points = np.vstack([np.zeros(3), rng.normal(size=(k - 1, 3))])
        normals = rng.normal(size=(k, 3)) * [1.0, 1.0, rng.uniform(0.5, 6.0)]
        normals[0] = [0.0, 0.0, 1.0]
        through = rng.uniform(size=k) < 0.8  # planes through p: normals across (p - q)
        towards = points / np.maximum(np.linalg.norm(points, axis=1, keepdims=True), 1e-12)
        normals[through] -= np.sum(normals * towards, axis=1, keepdims=True)[through] * towards[through]
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        flat = rng.uniform(size=k) < 0.8
        got = sf._crease_points(points, np.arange(k)[None], 0, normals, flat)[0]
        offset = points[0] - points[1:]
        side = np.sum(offset * normals[1:], axis=1)
        counted = (flat[1:] & (side ** 2 <= sf.ON_PLANE_SIN2 * np.sum(offset ** 2, axis=1))
                   & (normals[1:] @ normals[0] >= sf.SHEET_COS))
        pairs = normals[1:][counted] @ normals[1:][counted].T
        assert got == bool((pairs < sf.SHARP_COS).any())
        found.append(got)
    assert 300 < sum(found) < 2700


def test_bound_semi_axes_is_numpys_formula():
    """The compiled sampling bound gives numpy's values to the bit: semi-axes and radii capped
    at BOUND_FACTOR x spacing, and the mask of the capped splats."""
    from surfel.preprocess.spacing import BOUND_FACTOR, bound_semi_axes

    rng = np.random.default_rng(3)
    axes = rng.normal(size=(5_000, 2, 3))
    radii = np.linalg.norm(axes, axis=2).max(axis=1) * rng.uniform(0.5, 1.5, 5_000)
    spacing = rng.uniform(0.1, 1.0, 5_000)
    bound = BOUND_FACTOR * spacing
    scale = np.minimum(1.0, bound[:, None] / np.maximum(np.linalg.norm(axes, axis=2), 1e-300))
    for r in (radii, radii.astype(np.float32)):
        got_axes, got_radii, capped = bound_semi_axes(axes, r, spacing)
        assert np.array_equal(got_axes, axes * scale[:, :, None])
        assert np.array_equal(got_radii, np.minimum(r, bound))
        assert np.array_equal(capped, (scale < 1.0).any(axis=1) | (r > bound))
        assert 100 < capped.sum() < 4_900
    # float32 axes (as complete.prepare passes them) give the bits of their float64 values
    single = axes.astype(np.float32)
    for got, expected in zip(bound_semi_axes(single, radii, spacing), bound_semi_axes(single.astype(np.float64), radii,
                                                                                      spacing), strict=True):
        assert got.dtype == expected.dtype and np.array_equal(got, expected)


@pytest.mark.parametrize("along", [0.01, 0.004])
def test_rows_far_apart_stay_covered_and_a_wire_stays_thin(along):
    """A sheet sampled in rows 10 and 25 times farther apart than the points along a row (a CAD
    tessellation's long thin triangles): the sampling bound lets each splat reach across to the
    next row (spacing.anisotropic_spacing), where the median distance to the 4 nearest, all on
    the row, left holes between the rows (at 25 to one the cells among 16 neighbours stop short
    of the middle too: the splats grow to the bound). A lone row (a wire) keeps its bound."""
    from surfel.preprocess.spacing import ROW_REACH

    rng = np.random.default_rng(21)
    across = 0.1
    x, y = (g.ravel() for g in np.meshgrid(np.arange(0, 1 + 1e-9, along), np.arange(0, 1 + 1e-9, across)))
    x = x + rng.uniform(-0.1, 0.1, x.size) * along
    points = np.stack([x, y, np.zeros(x.size)], 1)
    prepared, report = prepare(PointCloud(points, normals=np.tile([0.0, 0, 1], (len(points), 1))))
    assert report["splat_bound"]["anisotropic"] > 0.5 * len(points)
    inside = np.stack([rng.uniform(0.1, 0.9, 20_000), rng.uniform(0.1, 0.9, 20_000), np.zeros(20_000)], 1)
    assert covered_by(prepared, np.arange(len(prepared)), inside).all()
    # no farther than that share of the way across (the ends of the rows, on the sheet's border, see farther rows)
    inner = (prepared.positions[:, 0] > 0.05) & (prepared.positions[:, 0] < 0.95)
    assert prepared.radii[inner].max() <= ROW_REACH * across * 1.01
    wire = points[np.abs(points[:, 1] - 0.5) < 1e-9]
    thin, report = prepare(PointCloud(wire, normals=np.tile([0.0, 0, 1], (len(wire), 1))))
    assert report["splat_bound"].get("anisotropic", 0) == 0
    assert np.median(thin.radii) < 0.75 * ROW_REACH * across  # 2.5 x 1.5 along: the median distance to 4 nearest


def test_a_thin_part_sampled_in_rings_keeps_splats_no_wider_than_its_rings():
    """A cylinder of radius 1 sampled as a coarse mesh's tail is: rings of 16 vertices, 6 apart,
    so that each point's nearest neighbours all lie on its own ring and its cell is open along
    the axis. The ellipse is fitted to the part of the cell the sampling bound leaves (cells.py):
    fitted to the whole open cell, the aspect limit widened it around the ring to a quarter of
    its length or more, and the bound kept that width, a splat standing out of the part's outline."""
    around, gap = 16, 6.0
    angles = 2 * np.pi * np.arange(around) / around
    ring = np.stack([np.cos(angles), np.sin(angles), np.zeros(around)], 1)
    points = np.concatenate([ring + [0, 0, gap * k] for k in range(6)])
    prepared, _ = prepare(PointCloud(points, normals=np.tile(ring, (6, 1))), elliptical=True)
    axes = prepared.axes.astype(np.float64)
    tangent = np.tile(np.stack([-np.sin(angles), np.cos(angles), np.zeros(around)], 1), (6, 1))
    reach_around = np.linalg.norm(np.einsum("nij,nj->ni", axes, tangent), axis=1)
    chord = 2 * np.sin(np.pi / around)
    assert reach_around.min() >= 0.5 * chord  # still covering the ring
    assert np.median(reach_around) <= 0.5  # 0.62 fitted to the open cell; the next vertex lies 0.39 away


def test_layer_thickness_separates_close_layers_and_nothing_else():
    """Two surfaces 0.3 apart, closer than a splat radius: each point's layer thickness is half
    the gap; where the body lies alone, and on single surfaces (noisy, curved, creased), none."""
    from surfel.attributes import INFINITE_LENGTH
    from surfel.preprocess.neighbourhood import Neighbourhood
    from surfel.preprocess.thickness import layer_thickness

    def thickness(points, normals):
        nbh = Neighbourhood.build(points, 16)
        return nbh.unsort(layer_thickness(nbh.points, unit(nbh.sort(normals)), nbh.index))

    cloud, sheet = sheet_over_body(np.random.default_rng(4))
    x, y = cloud.positions[:, 0], cloud.positions[:, 1]
    tau = thickness(cloud.positions, cloud.normals)
    both = (np.abs(x) < 18) & (y > -18) & (y < -2)
    assert (tau[both] < INFINITE_LENGTH).mean() > 0.98
    assert np.abs(np.median(tau[both]) - 0.15) < 0.02
    assert (tau[y > 2] == INFINITE_LENGTH).all()
    # curved layers: a sphere of 3000 samples and a cap 0.3 spacings above its top half
    body, cap = sphere(3_000, seed=5), sphere(3_000, seed=6)
    cap = cap[cap[:, 2] > 0.2] * (1 + 0.3 * np.sqrt(4 * np.pi / 3_000))
    layered = np.concatenate([body, cap])
    tau = thickness(layered, unit(layered))
    assert (tau[np.r_[body[:, 2] > 0.3, cap[:, 2] > 0.3]] < INFINITE_LENGTH).mean() > 0.9
    noisy = sphere(20_000, seed=2, noise=0.004)  # noise a sixth of the spacing
    normals, _ = estimate_normals(noisy)
    assert (thickness(noisy, normals) < INFINITE_LENGTH).mean() < 0.01
    coarse = sphere(300, seed=3)  # neighbours far down the curve
    assert (thickness(coarse, coarse) < INFINITE_LENGTH).mean() < 0.01
    wedge, _ = edge_wedge()
    assert (thickness(wedge.positions, wedge.normals) < INFINITE_LENGTH).mean() < 0.01
    part = turned_part()  # creases of 23 degrees between a face and its corner's averaged normal
    assert (thickness(part.positions, part.normals) < INFINITE_LENGTH).mean() < 0.001


def test_another_layer_close_by_does_not_cut_the_cells():
    """The body's samples under a sheet 0.3 above it keep the radii of the body alone: the
    sheet's samples, another layer, do not bound their cells (they cut them to 0.82 before)."""
    cloud, sheet = sheet_over_body(np.random.default_rng(4))
    y = cloud.positions[:, 1]
    for radii in (estimate_radii(cloud.positions, normals=cloud.normals),
                  np.linalg.norm(fit_ellipses(cloud.positions, cloud.normals), axis=2).max(axis=1)):
        alone = np.median(radii[~sheet & (y > 3)])
        assert np.median(radii[~sheet & (y < -3)]) > 0.97 * alone
        assert np.median(radii[sheet & (y < -3)]) > 0.97 * alone


def test_a_sheet_lying_close_on_a_body_ends_at_its_last_samples():
    """The sheet's last row is a border although the body's samples lie beyond it, 0.3 below:
    another layer does not close the gap (they did: the sheet ran on a splat past its edge)."""
    cloud, sheet = sheet_over_body(np.random.default_rng(4))
    lines = prepare(cloud)[0].attributes["clip_lines"]
    x, y = cloud.positions[:, 0], cloud.positions[:, 1]
    edge = sheet & (y > -1.3) & (np.abs(x) < 18)  # the row at y = -1
    assert (lines[edge, 0, 2] < 1).mean() > 0.9  # cut by a line
    assert (lines[~sheet & (y > 2) & (y < 18) & (np.abs(x) < 18), 0, 2] >= 1).all()  # the body alone: none


def test_a_rolled_rim_keeps_its_outer_wall_whole():
    """A sheet rolled over at its top (a teapot's rim): an outer wall going down 1.0, the inner
    wall 0.1 behind it ending after 0.2 at an open edge. The inner wall's border line, moved
    out by its fold's reach to the outer wall's samples, cut those splats in half, and the
    outer wall, which goes on past the line, showed a band of holes (1.3% of it)."""
    h = 0.05
    ys = np.arange(-0.5, 0.5 + 1e-9, h)
    outer = np.array([(0.0, y, z) for y in ys for z in np.arange(-1.0, 1e-9, h)])
    angles = np.linspace(0, np.pi, 5)[1:-1]
    roll = np.array([(0.05 * (np.cos(a) - 1), y, 0.05 * np.sin(a)) for y in ys for a in angles])
    inner = np.array([(-0.1, y, z) for y in ys for z in np.arange(-0.2, 1e-9, h)])
    normals = np.concatenate([np.tile([1.0, 0, 0], (len(outer), 1)),
                              [(np.cos(a), 0.0, np.sin(a)) for _ in ys for a in angles],
                              np.tile([-1.0, 0, 0], (len(inner), 1))])
    prepared, _ = prepare(PointCloud(np.concatenate([outer, roll, inner]), normals=normals), elliptical=True)
    rng = np.random.default_rng(3)
    wall = np.c_[np.zeros(20000), rng.uniform(-0.4, 0.4, 20000), rng.uniform(-0.8, -0.05, 20000)]
    assert covered_by(prepared, np.arange(len(outer)), wall).all()
    # the inner wall still ends at its edge
    below = np.c_[np.full(4000, -0.1), rng.uniform(-0.4, 0.4, 4000), rng.uniform(-0.35, -0.26, 4000)]
    assert not covered_by(prepared, np.arange(len(outer) + len(roll), len(prepared)), below).any()


def test_a_border_beside_an_inner_corner_points_straight_out():
    """The outward direction of a border point is that of its nearest neighbours' gap, also
    where the wider neighbourhood confirms it: along a straight edge running into an inner
    corner (an L-shaped flat part, a shoulder turning into a neck), the samples of the other
    edge among the wider neighbours would tilt the gap's middle by up to 26 degrees, and the
    clip lines with it, cutting the outline into a sawtooth."""
    from surfel.preprocess import borders, cells
    from surfel.preprocess.neighbourhood import Neighbourhood

    grid = np.stack(np.meshgrid(np.arange(60.0), np.arange(60.0)), -1).reshape(-1, 2)
    grid[:, 0] += 0.5 * (grid[:, 1] % 2)  # staggered rows
    shape = grid[(grid[:, 1] < 12) | (grid[:, 0] < 12)]  # an L, its inner corner at (12, 12)
    jitter = np.random.default_rng(1).normal(0, 0.05, shape.shape)
    points = np.c_[shape + jitter, np.zeros(len(shape))]
    nbh = Neighbourhood.build(points, 16, progress=False)
    normals = np.tile([0.0, 0, 1], (len(points), 1))
    outwards, _ = borders.border_outwards(nbh, normals, nbh.first(cells.RADIUS_NEIGHBOURS), False)
    p = nbh.sort(points)
    on_border = outwards.any(axis=1)
    for edge, normal in [((p[:, 1] > 10.5) & (p[:, 0] > 14) & (p[:, 0] < 55), [0.0, 1.0]),  # top of the foot
                         ((p[:, 0] > 10.5) & (p[:, 1] > 14) & (p[:, 1] < 55), [1.0, 0.0])]:  # right of the leg
        found = edge & on_border
        assert found.sum() > 30
        assert np.degrees(np.arccos(np.clip(outwards[found, :2] @ normal, -1, 1))).max() < 10


def _in_notch(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Inside a V notch cut into the top of the 20 x 20 part: apex (10, 8), 8 wide at y = 20."""
    return (y > 8) & (np.abs(x - 10) < (y - 8) / 3)


def test_a_notch_in_an_outline_stays_open(monkeypatch):
    """A flat part sampled as a coarse mesh's vertices (a jittered grid, its outline sampled
    along), with a V notch cut into it: the samples across the notch close no border gap of
    the samples along its sides (borders.CLOSING_SPACINGS), so their splats end at the sides
    and leave most of the notch open, where they filled more than half of it, and the part stays
    covered."""
    from surfel.preprocess import borders

    rng = np.random.default_rng(3)
    grid = np.stack(np.meshgrid(np.arange(0.0, 20.01), np.arange(0.0, 20.01)), -1).reshape(-1, 2)
    grid += rng.uniform(-0.25, 0.25, grid.shape)
    grid = grid[~_in_notch(*grid.T) & (grid.min(axis=1) >= 0) & (grid.max(axis=1) <= 20)]
    t = np.arange(12) / 12.0
    sides = np.r_[np.c_[10 - 4 * t, 8 + 12 * t], np.c_[10 + 4 * t, 8 + 12 * t]]
    grid = grid[np.min(np.linalg.norm(grid[:, None] - sides[None], axis=2), axis=1) > 0.5]
    xy = np.r_[grid, sides]
    cloud = PointCloud(np.c_[xy, np.zeros(len(xy))], normals=np.tile([0.0, 0, 1], (len(xy), 1)))
    probe = rng.uniform(0, 20, (40_000, 2))
    to_sides = np.abs(np.abs(probe[:, 0] - 10) - (probe[:, 1] - 8) / 3) / np.hypot(1, 1 / 3)
    notch = probe[_in_notch(*probe.T) & (to_sides > 0.3)]
    part = probe[~_in_notch(*probe.T) & (to_sides > 0.3) & (probe.min(axis=1) > 1) & (probe.max(axis=1) < 19)]
    notch, part = (np.c_[p, np.zeros(len(p))] for p in (notch, part))
    prepared, _ = prepare(cloud)
    everything = np.arange(len(prepared))
    assert covered_by(prepared, everything, notch).mean() < 0.35
    assert covered_by(prepared, everything, part).all()
    monkeypatch.setattr(borders, "CLOSING_SPACINGS", np.inf)
    assert covered_by(prepare(cloud)[0], everything, notch).mean() > 0.5


def test_settled_candidates_keep_the_borders_of_the_full_confirmation():
    """Candidates settled by the neighbours certainly among their BORDER_CONFIRM nearest
    (Grid.within, borders._settled) are no borders, as the query of all those nearest finds:
    border_outwards gives bit for bit what confirming every candidate by the query gives, on a
    sampling denser on one side (candidates the wider neighbourhood rejects), an open sheet
    (borders) and a lattice (ties of distance and direction)."""
    from surfel.preprocess import borders, cells
    from surfel.preprocess.frames import orthonormal_basis
    from surfel.preprocess.neighbourhood import Neighbourhood
    from surfel.preprocess.spacing import local_spacing
    from surfel.preprocess.thickness import layer_thickness

    # no EMPTY_RUN + 1 consecutive empty bins leave no gap counted
    assert (borders.EMPTY_RUN + 2) * borders.KEY_BIN < borders.INTERIOR_GAP / 2
    p = sphere(20_000, seed=4)
    sheet = _open_sheet(0.02).positions
    lattice = np.stack(np.meshgrid(np.arange(40), np.arange(40), [0]), -1).reshape(-1, 3) / 40.0
    tally = np.zeros(3, int)  # candidates settled, confirmed, rejected by the query
    for points, normals in [(np.concatenate([p[p[:, 2] > 0.3], p[p[:, 2] <= 0.3][::6]]), None),
                            (sheet, np.tile([0.0, 0, 1], (len(sheet), 1))),
                            (lattice, np.tile([0.0, 0, 1], (len(lattice), 1)))]:
        nbh = Neighbourhood.build(points, 16, progress=False)
        normals = unit(nbh.points) if normals is None else normals
        index = nbh.first(cells.RADIUS_NEIGHBOURS)
        layers = layer_thickness(nbh.points, normals, index)
        spacing = local_spacing(nbh, False)
        closing2 = (borders.CLOSING_SPACINGS * spacing) ** 2
        got, _ = borders.border_outwards(nbh, normals, index, False, layers, spacing)
        rows = np.arange(len(nbh.points))
        first, _ = borders._border_outwards(nbh.points, normals, index, rows, orthonormal_basis(normals),
                                            cells.SHEET_COS, borders.FLAT_SIN2, layers, closing2)
        candidates = np.flatnonzero(first.any(axis=1))
        expected = first.copy()
        wide, _ = borders._border_outwards(nbh.points, normals, nbh.nearest(candidates, 64), candidates,
                                           orthonormal_basis(normals[candidates]), cells.SHEET_COS, borders.FLAT_SIN2,
                                           layers, closing2)
        expected[candidates[~wide.any(axis=1)]] = 0.0  # confirmed ones keep their nearest neighbours' direction
        assert np.array_equal(got, expected)
        sure, count = nbh.within(candidates, borders.BORDER_CONFIRM)
        settled = borders._settled(nbh.points, normals, sure, count, candidates, orthonormal_basis(normals[candidates]),
                                   cells.SHEET_COS, borders.FLAT_SIN2, layers, closing2)
        assert not expected[candidates[settled]].any()
        confirmed = expected[candidates].any(axis=1)
        tally += [settled.sum(), confirmed.sum(), (~settled & ~confirmed).sum()]
    assert tally[0] > 50 and tally[1] > 100 and tally[2] > 100
