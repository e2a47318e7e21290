"""Completing a cloud: the one place that decides what gets estimated, and in which order.

`prepare(cloud, ...)` fills in what a cloud lacks with explicit choices (the `surfel prepare`
command): one k-nearest-neighbour search, k = max(k_normals, RADIUS_NEIGHBOURS,
FIELD_NEIGHBOURS), serves every estimation (once per position where points coincide,
`coincident.py`), in this order, each using the ones before:

  1. normals (`normals.py`): u x v of given axes, else PCA (when the cloud is not geospatial
     and k_normals is the default: each point's neighbourhood size selected if it is noisy,
     refined by quadrics (`jets.py`) if it is clean),
     oriented towards the sensor when its position is known (`sensor`, or the cloud's
     `sensors`), else by propagation, each connected part facing up (+Z) for geospatial clouds
     (aerial scans, seen from above) or outward; with them, from the same PCA, the points
     drawn facing the camera (`structure.py`); given normals, where no sensor says which
     side was seen, are oriented by propagation if their signs disagree between neighbours,
     or turned if they are a closed mesh's and face inward as a whole (`normals.orient_given`;
     also on a cloud that needs nothing else);
  2. with the splats, the thickness of each point's layer (`thickness.py`), which caps z_t
     where another surface lies within a splat radius and keeps that surface's samples out of
     the cells (splats given with the cloud keep their z_t);
  3. the sampling spacing (`spacing.py`), when radii or axes are estimated;
  4. sharp features (`sharp_features.py`), when both radii and axes are estimated;
  5. radii (`cells.py`): covering radii of the tangent-plane Voronoi cells;
  6. axes: fitted ellipses (`cells.py`; for points sampled from a surface, to the part of each
     cell within the sampling bound) or circular tangent frames of the radii (`frames.py`);
  7. the sampling bound on both (`spacing.py`), and the radii of the screen-facing splats
     (`structure.py`);
  8. clip lines at the sharp features, where the surface turns sharply away (a thin part's
     rim), and at the borders of open surfaces (`borders.py`, `cells.py`; a margin out where
     the normals were estimated on a noisy cloud, also when `smooth` denoised it first), then
     at the short sides of lopsided cells (`cells.py`; fitted ellipses of points sampled from a
     surface), none on screen-facing splats;
  9. Phong splatting's normal fields (`normal_field.py`): the shading's and the curved
     surface's, flat on screen-facing splats;

Given attributes are kept as they are.

`complete(cloud, needs_radii=..., elliptical=..., normal_field=...)` is the policy every consumer
of a cloud follows (rendering, benchmarks, the LOD builders, COPC): it takes a method's capability
flags and prepares the cloud with the defaults when it lacks what the method needs.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..attributes import FIELD_SLOPES, INFINITE_LENGTH
from ..cloud import PointCloud, any_per_row
from ..io.mesh import opening
from .borders import NOISY_MARGIN, border_outwards, mesh_border_outwards
from .cell_kernels import INACTIVE_CLIP
from .cells import RADIUS_MARGIN, RADIUS_NEIGHBOURS, clip_lines, covering_ellipses, covering_radii
from .coincident import coincident_groups
from .frames import tangent_frames, unit
from .neighbourhood import Neighbourhood
from .normal_field import FIELD_NEIGHBOURS, field_slopes, has_normal_field
from .normals import CLOSED_OPENING, NORMAL_NEIGHBOURS, ORIENT_NEIGHBOURS, SCALES, orient_given, oriented_normals
from .sharp_features import SHARP_ANGLE, find_sharp_features
from .smoothing import SMOOTH_NEIGHBOURS, smoothed_points
from .spacing import BOUND_FACTOR, anisotropic_spacing, bound_semi_axes, reach_next_row, sampling_spacing
from .structure import round_radii, scans_surroundings, screen_facing
from .thickness import layer_thickness

UP = np.array([0.0, 0.0, 1.0])  # a geospatial cloud's up axis


def complete(cloud: PointCloud, *, needs_radii: bool = True, elliptical: bool = False,
             normal_field: bool = False, progress: bool | None = None,
             reference_spacing: np.ndarray | None = None, smooth: bool = False) -> tuple[PointCloud, dict]:
    """The cloud with what a method needs, and the report of what was estimated ({} if nothing).

    The method's capability flags say what it needs: every method needs normals;
    `needs_radii`: splats (radii and axes); `elliptical`: fitted ellipses rather than circles
    when the axes are estimated; `normal_field`: Phong splatting's normal fields. A cloud that
    lacks any of them is prepared (`prepare`, its defaults), which estimates normals, radii and
    axes alike whichever was missing, so that one completed cloud serves every method. One that
    lacks nothing still has its given normals oriented as `prepare` would orient them.
    `reference_spacing`, `smooth`: as `prepare`'s (smooth: always prepared).
    """
    if not _prepares(cloud, needs_radii, normal_field, smooth):
        return _given_normals_oriented(cloud, progress=progress)
    return prepare(cloud, elliptical=elliptical, normal_field=normal_field, progress=progress,
                   reference_spacing=reference_spacing, smooth=smooth)


def _given_normals_oriented(cloud: PointCloud, nbh: Neighbourhood | None = None,
                            progress: bool | None = None) -> tuple[PointCloud, dict]:
    """`cloud` with its given normals oriented where nothing says which side was seen (no axes,
    sensors or up direction; normals.orient_given, which turns inward normals only on a closed
    mesh's vertices), and the report of it; `nbh`: the cloud's neighbourhood, else one is built."""
    if cloud.normals is None or cloud.axes is not None or cloud.geospatial or cloud.sensors is not None:
        return cloud, {}
    if nbh is None:
        nbh = Neighbourhood.build(cloud.positions, ORIENT_NEIGHBOURS + 1, -1, progress)
    closed_mesh = cloud.is_mesh and opening(cloud.positions, cloud.faces) < CLOSED_OPENING
    normals, how = orient_given(nbh, nbh.sort(cloud.normals), closed_mesh)
    if how is None:
        return cloud, {}
    return cloud.with_(normals=nbh.unsort(np.asarray(normals, np.float32))), {"normals": f"given, {how}"}


def completes_with_clip_lines(cloud: PointCloud, *, needs_radii: bool = True, normal_field: bool = False,
                              smooth: bool = False) -> bool:
    """Whether `complete` with these flags leaves `cloud` with clip lines (given, or estimated
    with its radii and axes), known before completing it (compile_ahead.py asks: the kernels
    take clip lines or None)."""
    return "clip_lines" in cloud.attributes or (_prepares(cloud, needs_radii, normal_field, smooth)
                                                and _estimates_splats(cloud))


def _prepares(cloud: PointCloud, needs_radii: bool, normal_field: bool, smooth: bool) -> bool:
    """`complete`'s policy: prepare a cloud that lacks what the method needs, or is to be smoothed."""
    missing = cloud.normals is None or (needs_radii and (cloud.radii is None or cloud.axes is None))
    return smooth or missing or (normal_field and "phong_alpha" not in cloud.attributes)


def _estimates_splats(cloud: PointCloud) -> bool:
    """Whether `prepare` estimates the splats of `cloud` (neither radii nor axes given), and so
    ends them at creases and borders (with sharp_features)."""
    return cloud.radii is None and cloud.axes is None


def prepare(cloud: PointCloud, *, k_normals: int = NORMAL_NEIGHBOURS, sensor: np.ndarray | None = None,
            elliptical: bool = False, normal_field: bool = False, sharp_features: bool = True,
            progress: bool | None = None, reference_spacing: np.ndarray | None = None,
            smooth: bool = False) -> tuple[PointCloud, dict]:
    """Fill in what `cloud` lacks for splatting; returns (cloud, report).

    smooth: first move the positions onto the MLS surface of the points (`smoothing.py`),
    guided by the given normals, else by normals estimated as below, then estimate from them.
    Points with no tangent plane (screen_facing, given or estimated: vegetation) stay where they
    are; projecting a canopy's scattered returns gathered them into blobs.

    normals: estimated if None: towards the sensor (`sensor` (3,), else the cloud's own
    `sensors`) if known; otherwise propagated, each part facing up (+Z) for geospatial clouds
    (aerial scans, seen from above) or outward. A cloud with axes but no normals gets u x v,
    the orientation its splats already have. Given normals without axes, sensors or an up
    direction are oriented where their signs disagree between neighbours, or where they are
    a closed mesh's and face inward as a whole (normals.orient_given). With estimated normals,
    attributes["screen_facing"] marks the points drawn as round splats facing the camera
    (`structure.py`).
    radii: estimated if None (covering radii of the tangent-plane Voronoi cells).
    axes: if None, fitted ellipses when `elliptical`, else circular frames of the radii.
    Estimated radii and axes are bounded by the sampling (`spacing.py`), whose reference spacing
    is `reference_spacing` (N,) when the caller knows it (a COPC node's), else its model's.
    normal_field: also fit the normal field (attributes FIELD_SLOPES) if missing.
    sharp_features: when radii and axes are estimated, cells end at creases and
    attributes["clip_lines"] (N, CLIP_LINES, 3) cut the splats there and at the borders of open
    surfaces (`cells.py`; a mesh's boundary edges among them, `borders.py`).
    Where the splats are estimated, coincident points (`coincident.py`: a mesh's vertices
    repeated along its seams) are estimated once per position and drawn alike, with their
    mean normal (`_prepare_per_position`); other given attributes are kept as they are.
    The report names every estimated attribute and how, plus "ambiguous_normals" when normals
    were estimated, "screen_facing" (how many points face the camera),
    "splat_bound" (the spacing model and how many splats it capped) and "coincident" (how many
    points repeat another's position).
    """
    report: dict = {}
    need_field = normal_field and not has_normal_field(cloud)
    complete = cloud.normals is not None and cloud.radii is not None and cloud.axes is not None
    if complete and not need_field and not smooth:
        return cloud, report
    k_estimations = max(k_normals, RADIUS_NEIGHBOURS, FIELD_NEIGHBOURS if need_field else 1)
    k = max(k_estimations, SMOOTH_NEIGHBOURS if smooth else 1)
    nbh = Neighbourhood.build(cloud.positions, k, -1, progress)
    if sensor is None:
        cloud, report = _given_normals_oriented(cloud, nbh)
    groups = coincident_groups(cloud, nbh) if _estimates_splats(cloud) else None  # the cells are what copies upset
    if groups is not None:
        prepared, per_position = _prepare_per_position(
            cloud, *groups, reference_spacing, k_normals=k_normals, sensor=sensor, elliptical=elliptical,
            normal_field=normal_field, sharp_features=sharp_features, progress=progress, smooth=smooth)
        return prepared, {**report, **per_position}
    given = {name: None if getattr(cloud, name) is None else nbh.sort(getattr(cloud, name))
             for name in ("normals", "radii", "axes")}
    sensors = cloud.sensor_positions() if sensor is None else np.broadcast_to(sensor, cloud.positions.shape)
    towards_sensor = None if sensors is None else nbh.sort(sensors - cloud.positions)
    if towards_sensor is not None:
        towards, how = towards_sensor, "facing the sensor"
    else:
        towards, how = None, f"oriented by MST propagation, {'facing up (+Z)' if cloud.geospatial else 'outward'}"
    up = UP if cloud.geospatial else None
    # geospatial tiles keep one scale and the plane: millions of points, and aerial noise is not an object's
    adaptive = not cloud.geospatial and k_normals == NORMAL_NEIGHBOURS
    estimated: dict = {}
    attributes = dict(cloud.attributes)
    normals = given["normals"]
    if given["axes"] is not None:
        axes64 = given["axes"].astype(np.float64)
        from_axes = unit(np.cross(axes64[:, 0], axes64[:, 1]))
    positions = None
    # normals estimated on a noisy cloud (a raw scan): its borders get a margin (borders.py); a
    # raw scan keeps it once denoised, since its samples lost at grazing angles stay lost
    noisy = False
    located = cloud if sensor is None else cloud.with_(sensors=np.asarray(sensor, np.float64).reshape(1, 3))
    if smooth:
        # points with no tangent plane (vegetation, structure.py) have no surface to be moved onto
        planeless = nbh.sort(cloud.attributes["screen_facing"] > 0.5) if "screen_facing" in cloud.attributes \
            else None
        if normals is not None:
            guide = normals
        elif given["axes"] is not None:
            guide = from_axes
        else:
            guide, _, eigenvalues, noisy = oriented_normals(nbh, k_normals, towards, progress, adaptive, up)
            if planeless is None:
                planeless = screen_facing(eigenvalues, raw_scan=scans_surroundings(located))
        moved = smoothed_points(nbh, guide, progress)
        if planeless is not None:
            moved[planeless] = nbh.points[planeless]
        positions = cloud.positions + nbh.unsort(moved - nbh.points)
        report["smooth"] = (f"MLS projection (k={SMOOTH_NEIGHBOURS}), mean move "
                            f"{float(np.mean(np.linalg.norm(moved - nbh.points, axis=1))):.4g}")
        # the same neighbours, moved by about the noise; the estimations below take no more
        # than k_estimations of them (one contiguous copy, not one per estimation: Neighbourhood.first)
        nbh = replace(nbh, points=moved, index=nbh.first(k_estimations))
    facing = None
    if normals is None and given["axes"] is not None:
        normals = estimated["normals"] = from_axes
        report["normals"] = "from the splat axes (u x v)"
    elif normals is None:
        normals, ambiguous, eigenvalues, noisy_now = oriented_normals(nbh, k_normals, towards, progress, adaptive, up)
        estimated["normals"] = normals
        scale = f"k per point in {SCALES[0]}..{SCALES[-1]} (noisy)" if noisy_now else \
            f"k={k_normals}, refined by quadrics" if adaptive else f"k={k_normals}"
        noisy = noisy or noisy_now
        report["normals"] = f"estimated (PCA, {scale}, {how})"
        report["ambiguous_normals"] = int(ambiguous.sum())
        facing = screen_facing(eigenvalues, raw_scan=scans_surroundings(located))
        attributes["screen_facing"] = nbh.unsort(facing.astype(np.float32))
        report["screen_facing"] = int(facing.sum())
    # the points drawn facing the camera: as the cloud flags them, else as estimated now
    drawn_facing = facing if "screen_facing" not in cloud.attributes else \
        nbh.sort(cloud.attributes["screen_facing"] > 0.5)
    radii, axes = given["radii"], given["axes"]
    short_sides = None
    # what is estimated from the positions is bounded by their sampling (circles of given radii keep them)
    bound_radii = radii is None
    bound_axes = axes is None and (bound_radii or elliptical)
    thickness = None
    unit_normals = unit(normals)  # made once: every estimation below asks for them
    if bound_radii or bound_axes:  # the layers first: another layer's samples must not cut this one's cells
        thickness = layer_thickness(nbh.points, unit_normals, nbh.first(RADIUS_NEIGHBOURS))
        if facing is not None:
            thickness[facing] = INFINITE_LENGTH  # no tangent plane, no layer
        if "thickness" not in cloud.attributes:
            attributes["thickness"] = nbh.unsort(thickness.astype(np.float32))
            report["thickness"] = (f"{float(np.mean(thickness < INFINITE_LENGTH)):.1%} of splats lie within a "
                                   f"splat radius of another layer (z_t capped there)")
    spacing = None
    if bound_radii or bound_axes:
        ranges = incidence = None
        if towards_sensor is not None:
            ranges = np.linalg.norm(towards_sensor, axis=1)
            # cos of the angle between each splat's normal and its sensor's ray; facing the
            # camera, a point has no tangent plane to tilt
            incidence = np.abs(np.einsum("ij,ij->i", unit_normals, towards_sensor)) / np.maximum(ranges, 1e-300)
            if drawn_facing is not None:
                incidence[drawn_facing] = 1.0
        spacing, spacing_report = sampling_spacing(
            nbh, geospatial=cloud.geospatial, ranges=ranges, incidence=incidence,
            framing_radius=cloud.bounding_radius,
            reference=None if reference_spacing is None else nbh.sort(reference_spacing),
            surface=None if drawn_facing is None else ~drawn_facing, progress=progress)
    features = None
    if sharp_features and _estimates_splats(cloud):
        features = find_sharp_features(nbh, unit_normals, RADIUS_NEIGHBOURS)
    if radii is None:
        radii = estimated["radii"] = covering_radii(nbh, unit_normals, progress, features, layers=thickness)
        report["radii"] = (f"estimated (Voronoi covering radius, k={RADIUS_NEIGHBOURS}, "
                           f"x{RADIUS_MARGIN}, mean {float(np.mean(radii)):.4g})")
    if axes is None and elliptical:
        bound = None
        # the cells of points sampled from a surface end at the bound and at their short sides
        # (cells.py); a scan's, bounded by its acquisition's spacing (a sensor's, a survey's, a
        # COPC level's), keep the whole cell
        sampled = spacing is not None and towards_sensor is None and reference_spacing is None and not cloud.geospatial
        if sampled:
            lifted_spacing, _ = anisotropic_spacing(nbh, unit_normals, spacing,  # where the bound will be lifted
                                                    np.flatnonzero(radii > BOUND_FACTOR * spacing))
            bound = BOUND_FACTOR * lifted_spacing
        axes, short_sides = covering_ellipses(nbh, unit_normals, progress, features, layers=thickness, bound=bound)
        short_sides = short_sides if sampled else None
        report["axes"] = f"fitted ellipses (k={RADIUS_NEIGHBOURS})"
    elif axes is None:
        axes = tangent_frames(normals, radii)
        report["axes"] = "circular (tangent frames of the radii)"
    if spacing is not None:
        bounded_axes, bounded_radii, capped = bound_semi_axes(axes, radii, spacing)  # float32 axes taken as they are
        if not cloud.geospatial and capped.any():  # rows far apart: the splats the bound cut may reach the next row
            spacing, lifted = anisotropic_spacing(nbh, unit_normals, spacing, np.flatnonzero(capped))
            bounded_axes[lifted], bounded_radii[lifted], capped[lifted] = reach_next_row(
                axes[lifted], radii[lifted], spacing[lifted])
            spacing_report["anisotropic"] = len(lifted)
        if bound_axes:
            axes = bounded_axes
        if bound_radii:
            radii = estimated["radii"] = bounded_radii
        report["splat_bound"] = {"factor": BOUND_FACTOR, "median_spacing": float(np.median(spacing)),
                                 **spacing_report, "capped": int(capped.sum())}
    if facing is not None and facing.any():
        round = round_radii(eigenvalues[facing], spacing[facing]) if bound_radii else radii[facing]
        if bound_radii:
            radii[facing] = round
        if given["axes"] is None:
            axes[facing] = tangent_frames(normals[facing], round)
    if given["axes"] is None:
        estimated["axes"] = axes
    changes = {name: nbh.unsort(np.asarray(value, np.float32)) for name, value in estimated.items()}
    if features is not None:
        # aerial scan lines look like borders (borders.py)
        outwards, reach = ((np.zeros((len(nbh.points), 3)), np.zeros(len(nbh.points))) if cloud.geospatial
                           else border_outwards(nbh, unit_normals, nbh.first(RADIUS_NEIGHBOURS), progress, thickness,
                                                spacing))
        on_edge = None
        if cloud.is_mesh:  # its boundary edges are its borders, facing out of their faces (borders.py)
            edge = nbh.sort(mesh_border_outwards(cloud.positions, cloud.faces, nbh.unsort(unit_normals)))
            on_edge = any_per_row(edge != 0.0)
            outwards[on_edge] = edge[on_edge]
        lines = clip_lines(nbh, unit_normals, axes, features, outwards, reach, progress,
                           margin=NOISY_MARGIN if noisy else 0.0, layers=thickness, short_sides=short_sides,
                           mesh_borders=on_edge)
        if facing is not None:
            lines[facing] = INACTIVE_CLIP  # a disk facing the camera has no crease to end at
        attributes["clip_lines"] = nbh.unsort(lines)
        report["sharp_features"] = (f"{float(np.mean(lines[:, 0, 2] < 1)):.1%} of splats end at creases "
                                    f"(normals > {SHARP_ANGLE:g} degrees apart) or borders, "
                                    f"{int(features.crease.sum())} crease points dropped")
    if need_field:
        slopes = field_slopes(nbh, unit_normals, axes, progress, rims=not noisy)
        if drawn_facing is not None:
            slopes[drawn_facing] = 0.0  # facing the camera: flat, lit head-on
        slopes = nbh.unsort(slopes)
        attributes.update({key: slopes[:, column].copy() for column, key in enumerate(FIELD_SLOPES)})
        report["normal_field"] = f"fitted (weighted least squares, k={FIELD_NEIGHBOURS})"
    if attributes.keys() != cloud.attributes.keys():
        changes["attributes"] = attributes
    if positions is not None:
        changes["positions"] = positions
    return cloud.with_(**changes), report


def _prepare_per_position(cloud: PointCloud, first: np.ndarray, inverse: np.ndarray, normals: np.ndarray | None,
                          reference_spacing: np.ndarray | None, **options) -> tuple[PointCloud, dict]:
    """`prepare` once per group of coincident points (coincident.py), splats estimated: each copy
    gets its group's estimates, the group's mean normal among them (two splats in one place
    facing a little apart would fight over each pixel and speckle the shading), and keeps its
    own colour and attributes."""
    spacing = None if reference_spacing is None else np.asarray(reference_spacing)[first]
    distinct = cloud.take(first)
    if cloud.is_mesh:  # the copies welded: its boundary edges are the borders (borders.py)
        distinct = distinct.with_(faces=inverse[cloud.faces])
    if normals is not None:
        distinct = distinct.with_(normals=normals)
    prepared, report = prepare(distinct, reference_spacing=spacing, **options)
    every = prepared.take(inverse)
    copies = len(cloud) - len(first)
    report["coincident"] = (f"{copies} {'point repeats' if copies == 1 else 'points repeat'} another sample's "
                            "position: estimated once per position")
    every = every.with_(colors=cloud.colors, attributes={**every.attributes, **cloud.attributes}, faces=cloud.faces)
    return every, report
