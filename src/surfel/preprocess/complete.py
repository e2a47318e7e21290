"""Completing a cloud: the one place that decides what gets estimated, and in which order.

`prepare(cloud, ...)` fills in what a cloud lacks with explicit choices (the `surfel prepare`
command): one k-nearest-neighbour search, k = max(k_normals, RADIUS_NEIGHBOURS,
FIELD_NEIGHBOURS), serves every estimation, in this order, each using the ones before:

  1. normals (`normals.py`): u x v of given axes, else PCA oriented towards a viewpoint, +Z for
     geospatial clouds (aerial scans, seen from above), or by propagation and outward;
  2. sharp features (`sharp_features.py`), when both radii and axes are estimated;
  3. radii (`cells.py`): covering radii of the tangent-plane Voronoi cells;
  4. axes: fitted ellipses (`cells.py`) or circular tangent frames of the radii (`frames.py`);
  5. clip lines at the sharp features (`cells.py`);
  6. Phong splatting's normal fields (`normal_field.py`).

Given attributes are kept as they are.

`complete(cloud, needs_radii=..., elliptical=..., normal_field=...)` is the policy every consumer
of a cloud follows (rendering, benchmarks, the LOD builders, COPC): it takes a method's capability
flags and prepares the cloud with the defaults when it lacks what the method needs.
"""

from __future__ import annotations

import numpy as np

from ..cloud import PointCloud
from .cells import RADIUS_MARGIN, RADIUS_NEIGHBOURS, clip_lines, covering_ellipses, covering_radii
from .frames import tangent_frames, unit
from .neighbourhood import Neighbourhood
from .normal_field import FIELD_NEIGHBOURS, field_slopes
from .normals import NORMAL_NEIGHBOURS, oriented_normals
from .sharp_features import SHARP_ANGLE, find_sharp_features


def complete(cloud: PointCloud, *, needs_radii: bool = True, elliptical: bool = False,
             normal_field: bool = False, progress: bool | None = None) -> tuple[PointCloud, dict]:
    """The cloud with what a method needs, and the report of what was estimated ({} if nothing).

    The method's capability flags say what it needs: every method needs normals;
    `needs_radii`: splats (radii and axes); `elliptical`: fitted ellipses rather than circles
    when the axes are estimated; `normal_field`: Phong splatting's normal fields. A cloud that
    lacks any of them is prepared (`prepare`, its defaults), which estimates normals, radii and
    axes alike whichever was missing, so that one completed cloud serves every method.
    """
    missing = cloud.normals is None or (needs_radii and (cloud.radii is None or cloud.axes is None))
    missing = missing or (normal_field and "phong_alpha" not in cloud.attributes)
    if not missing:
        return cloud, {}
    return prepare(cloud, elliptical=elliptical, normal_field=normal_field, progress=progress)


def prepare(cloud: PointCloud, *, k_normals: int = NORMAL_NEIGHBOURS, viewpoint: np.ndarray | None = None,
            elliptical: bool = False, normal_field: bool = False, sharp_features: bool = True,
            progress: bool | None = None) -> tuple[PointCloud, dict]:
    """Fill in what `cloud` lacks for splatting; returns (cloud, report).

    normals: estimated if None: towards `viewpoint` if given; geospatial clouds (aerial scans,
    seen from above) face +Z; otherwise propagated and outward. A cloud with axes but no
    normals gets u x v, the orientation its splats already have.
    radii: estimated if None (covering radii of the tangent-plane Voronoi cells).
    axes: if None, fitted ellipses when `elliptical`, else circular frames of the radii.
    normal_field: also fit attributes["phong_alpha"], attributes["phong_beta"] if missing.
    sharp_features: when radii and axes are estimated, cells end at creases and
    attributes["clip_lines"] (N, CLIP_LINES, 3) cut the splats there (`cells.py`).
    Given attributes are kept as they are. The report names every estimated attribute and
    how, plus "ambiguous_normals" when normals were estimated.
    """
    report: dict = {}
    need_field = normal_field and not {"phong_alpha", "phong_beta"} <= set(cloud.attributes)
    if cloud.normals is not None and cloud.radii is not None and cloud.axes is not None and not need_field:
        return cloud, report
    k = max(k_normals, RADIUS_NEIGHBOURS, FIELD_NEIGHBOURS if need_field else 1)
    nbh = Neighbourhood.build(cloud.positions, k, -1, progress)
    given = {name: None if getattr(cloud, name) is None else nbh.sort(getattr(cloud, name))
             for name in ("normals", "radii", "axes")}
    estimated: dict = {}
    normals = given["normals"]
    if normals is None and given["axes"] is not None:
        axes64 = given["axes"].astype(np.float64)
        normals = estimated["normals"] = unit(np.cross(axes64[:, 0], axes64[:, 1]))
        report["normals"] = "from the splat axes (u x v)"
    elif normals is None:
        if viewpoint is not None:
            towards = nbh.sort(np.asarray(viewpoint, np.float64) - cloud.positions)
            how = "facing the viewpoint"
        elif cloud.geospatial:
            towards, how = np.array([0.0, 0.0, 1.0]), "facing up (+Z)"
        else:
            towards, how = None, "oriented by MST propagation, outward"
        normals, ambiguous = oriented_normals(nbh, k_normals, towards, progress)
        estimated["normals"] = normals
        report["normals"] = f"estimated (PCA, k={k_normals}, {how})"
        report["ambiguous_normals"] = int(ambiguous.sum())
    radii = given["radii"]
    features = None
    if sharp_features and radii is None and given["axes"] is None:
        features = find_sharp_features(nbh, normals, RADIUS_NEIGHBOURS)
    if radii is None:
        radii = estimated["radii"] = covering_radii(nbh, normals, progress, features)
        report["radii"] = (f"estimated (Voronoi covering radius, k={RADIUS_NEIGHBOURS}, "
                           f"x{RADIUS_MARGIN}, mean {float(np.mean(radii)):.4g})")
    axes = given["axes"]
    if axes is None and elliptical:
        axes = covering_ellipses(nbh, normals, progress, features)
        report["axes"] = f"fitted ellipses (k={RADIUS_NEIGHBOURS})"
    elif axes is None:
        axes = tangent_frames(normals, radii)
        report["axes"] = "circular (tangent frames of the radii)"
    if given["axes"] is None:
        estimated["axes"] = axes
    changes = {name: nbh.unsort(np.asarray(value, np.float32)) for name, value in estimated.items()}
    attributes = dict(cloud.attributes)
    if features is not None:
        lines = clip_lines(nbh, normals, axes, features, progress)
        attributes["clip_lines"] = nbh.unsort(lines)
        report["sharp_features"] = (f"{float(np.mean(lines[:, 0, 2] < 1)):.1%} of splats end at creases "
                                    f"(normals > {SHARP_ANGLE:g} degrees apart), "
                                    f"{int(features.crease.sum())} crease points dropped")
    if need_field:
        alpha, beta = field_slopes(nbh, normals, axes, progress)
        attributes.update(phong_alpha=nbh.unsort(alpha), phong_beta=nbh.unsort(beta))
        report["normal_field"] = f"fitted (least squares, k={FIELD_NEIGHBOURS})"
    if attributes.keys() != cloud.attributes.keys():
        changes["attributes"] = attributes
    return cloud.with_(**changes), report
