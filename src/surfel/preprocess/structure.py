"""Points that are not on a surface: vegetation, wires, noise, and clouds without a tangent plane.

A splat is a piece of surface, a disk in the tangent plane of its neighbourhood. A canopy, a
power line or a bird has no such plane: oriented by the PCA normal of a neighbourhood that is
no surface, their disks tilt at random, some edge-on and dark. The shape of a neighbourhood is
read from the eigenvalues lambda0 <= lambda1 <= lambda2 of the covariance of its k nearest
neighbours (the PCA of normals.py), with the dimensionality features of Demantké, Mallet, David
& Vallet 2011 ("Dimensionality based scale selection in 3D lidar point clouds", ISPRS
Archives XXXVIII-5/W12):

    scattering  S = lambda0 / lambda2             a volume (foliage, noise):    S > SCATTERING_LIMIT
    linearity   L = (lambda2 - lambda1) / lambda2  a line (a wire, a branch):    L > LINEARITY_LIMIT

A point with either lies on no surface. Only scans of surroundings are judged so
(`scans_surroundings`): geospatial clouds (airborne and terrestrial LiDAR) and clouds with a
sensor inside their bounds (a scanner standing in the scene it measures). A cloud sampled from
a surface (a mesh's vertices, an object scanned from around it, its sensors outside its
bounds) is surface throughout; its creases, fine detail and noisy or misregistered overlaps,
whose neighbourhoods scatter too, are drawn by the cells of cells.py, cut at creases.

Whatever the cloud, a point without a tangent plane, lambda1 <= PLANE_EPSILON lambda2 (its
neighbours all on one line: two points, collinear points) or lambda2 = 0 (one point, or only
coincident ones), has no normal to orient a splat by either.

Both are drawn as round splats facing the camera: `screen_facing` (a derived attribute, float32,
1 for them) makes every splat method place the disk perpendicular to the viewing ray through
its centre, with its normal the direction to the eye, so that shading lights it as a surface
seen head-on (neither black nor random), its radius SCREEN_FACING_RADIUS times the point's
spacing s (spacing.py), the way point viewers draw such returns, so that neighbours overlap and
a canopy reads as a volume. Points without a tangent plane get LINE_RADIUS s instead: beads
along their line, two points two dots, not a blob that swallows the view. The rasterizers read
the flag as a zero normal (`drawn_normals`): a splat with no orientation faces the camera.
"""

from __future__ import annotations

import numpy as np

from ..cloud import PointCloud

SCATTERING_LIMIT = 0.05      # lambda0 / lambda2 above which a neighbourhood is a volume
LINEARITY_LIMIT = 0.8        # (lambda2 - lambda1) / lambda2 above which it is a line
PLANE_EPSILON = 1e-12        # lambda1 / lambda2 at or below which there is no tangent plane
SCREEN_FACING_RADIUS = 2.0   # radius of a screen-facing splat / the point's spacing: neighbours
                             # overlap, so a canopy reads as a volume and not as loose dots
LINE_RADIUS = 0.25           # the same for a point without a tangent plane: separate dots


def no_tangent_plane(eigenvalues: np.ndarray) -> np.ndarray:
    """(N,) bool: neighbourhoods that are a line or a point (eigenvalues (N, 3), ascending)."""
    return eigenvalues[:, 1] <= PLANE_EPSILON * eigenvalues[:, 2]


def not_on_surface(eigenvalues: np.ndarray) -> np.ndarray:
    """(N,) bool: neighbourhoods that scatter in volume or stretch along a line (module docstring)."""
    largest = np.maximum(eigenvalues[:, 2], 1e-300)
    scattering = eigenvalues[:, 0] / largest
    linearity = (eigenvalues[:, 2] - eigenvalues[:, 1]) / largest
    return (scattering > SCATTERING_LIMIT) | (linearity > LINEARITY_LIMIT) | no_tangent_plane(eigenvalues)


def scans_surroundings(cloud: PointCloud) -> bool:
    """Whether `cloud` is a scan of surroundings, where points may lie on no surface: geospatial,
    or one of its sensors inside its bounds (an object scanned from around has them outside)."""
    if cloud.geospatial:
        return True
    if cloud.sensors is None:
        return False
    lo, hi = cloud.bounds
    return bool(((cloud.sensors >= lo) & (cloud.sensors <= hi)).all(axis=1).any())


def screen_facing(eigenvalues: np.ndarray, raw_scan: bool) -> np.ndarray:
    """(N,) bool: the points drawn facing the camera: those without a tangent plane, and for
    a raw scan those on no surface."""
    return not_on_surface(eigenvalues) if raw_scan else no_tangent_plane(eigenvalues)


def round_radii(eigenvalues: np.ndarray, spacing: np.ndarray) -> np.ndarray:
    """Radii (n,) of screen-facing splats with these eigenvalues (n, 3) and spacings (n,)."""
    return np.where(no_tangent_plane(eigenvalues), LINE_RADIUS, SCREEN_FACING_RADIUS) * spacing


def facing_mask(cloud: PointCloud, start: int = 0, stop: int | None = None) -> np.ndarray | None:
    """(n,) bool of the screen-facing splats among points start:stop, or None if there are none."""
    flags = cloud.attributes.get("screen_facing")
    if flags is None:
        return None
    mask = flags[start:stop] > 0.5
    return mask if mask.any() else None


def drawn_normals(cloud: PointCloud, start: int = 0, stop: int | None = None) -> np.ndarray:
    """The normals (n, 3) float32 of points start:stop as the rasterizers take them: zero for
    the screen-facing splats (module docstring)."""
    normals = cloud.normals[start:stop]
    mask = facing_mask(cloud, start, stop)
    if mask is None:
        return normals
    normals = normals.copy()
    normals[mask] = 0.0
    return normals
