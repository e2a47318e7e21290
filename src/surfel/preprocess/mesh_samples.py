"""Points sampled evenly over a mesh's faces, for meshes whose vertices do not sample their surface.

A CAD part exported as STL is tessellated for display: a flat face is a fan of long triangles
between the vertices of its outline, with no vertex inside it, so its vertices are no point
sample of its surface and every method leaves such faces open. `surfel sample` turns such a
mesh into the point cloud a scanner would give without noise:

1. Candidates: 3 N points, each on a face chosen with probability proportional to its area A_f,
   at barycentric coordinates (1 - sqrt(r1), sqrt(r1) (1 - r2), sqrt(r1) r2) for uniform r1, r2
   (Turk 1990, "Generating random points in triangles", Graphics Gems): uniform over the surface.
2. Dart throwing (Cook 1986, "Stochastic sampling in computer graphics", ACM TOG 5(1)): the
   candidates in random order, each kept unless a kept one lies within r, with
   r = sqrt(4 c A / (pi N)): N disks of radius r / 2 cover the fraction c = 0.33 of the area A,
   and of the 3 N candidates 97-98% of N remain (measured on a CAD plate and on Spot), spaced
   at least r apart: even splats, without the clumps and gaps of independent samples.
3. Normals with a crease angle theta, as mesh viewers smooth a mesh's shading ("auto smooth"):
   an edge whose two faces' normals differ by more than theta is sharp; around each vertex the
   corners of the faces that smooth edges join share n = normalize(sum of 2 A_g n_g over those
   faces g); each sample interpolates its face's three corner normals barycentrically. A sharp
   edge stays a crease, a tessellated curved surface shades smoothly.
4. Colours and continuous attributes (a scanned mesh's intensity, say): the vertices' values,
   interpolated barycentrically (rounded back to an integer type's values); categorical ones
   (a class) never blended: each sample takes its nearest corner's. surfel's own per-vertex
   estimates (splat slopes, clip lines) describe the vertices' splats and are left behind.

On trimesh's plate with octagonal pockets (tests/data/octagonal_pocket.stl, 1,658 vertices), 18
views at 512 x 512 against the mesh shaded by these crease normals, `deferred` gives 12.5 dB with
up to 63% of the plate open from its vertices, 36.8 dB without holes from 200,000 samples
(`python benchmarks/readme_numbers.py cad`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from ..attributes import CATEGORICAL, DERIVED
from ..cloud import PointCloud
from ..errors import SurfelError
from ..io.mesh import edge_runs, face_vectors
from .neighbourhood import Neighbourhood
from .spacing import BOUND_FACTOR, LOCAL_NEIGHBOURS, local_spacing

DEFAULT_POINTS = 200_000
MAX_POINTS = 10_000_000  # 3 N candidates (0.7 GB) and their some 10 N close pairs (1.6 GB) at the limit
DEFAULT_CREASE_ANGLE = 30.0  # degrees, as mesh viewers' auto smooth
CANDIDATES = 3  # candidates per point kept
COVERAGE = 0.33  # area that N disks of radius r / 2 cover: of 3 N candidates 97-98% of N remain
SEED = 0  # one fixed seed: the same mesh always gives the same points
LARGE_FACE = 8.0  # a face whose longest edge is this many times the mesh's median edge is open
OPEN_SHARE = 0.25  # open faces holding this share of a mesh's area: its vertices are no sample of it


@dataclass(frozen=True)
class SampleSettings:
    """How many points to aim for over the whole surface, and the crease angle in degrees
    between faces whose normals are not blended."""

    points: int = DEFAULT_POINTS
    crease_angle: float = DEFAULT_CREASE_ANGLE

    def __post_init__(self):
        if not 1 <= self.points <= MAX_POINTS:
            raise SurfelError(f"--points: must be in 1..{MAX_POINTS}, got {self.points!r}")
        if not 0 <= self.crease_angle <= 180:
            raise SurfelError(f"--crease-angle: must be in [0, 180] degrees, got {self.crease_angle!r}")


def corner_normals(positions: np.ndarray, faces: np.ndarray, crease_angle: float) -> np.ndarray:
    """(F, 3, 3): each face corner's normal (module docstring, step 3): the corners around a
    vertex that edges no sharper than `crease_angle` degrees join share the normalised sum of
    their faces' 2 A_g n_g. An edge of more than two faces (non-manifold) joins none."""
    weighted = face_vectors(positions, faces)  # 2 A_f n_f
    length = np.linalg.norm(weighted, axis=1, keepdims=True)
    unit = np.divide(weighted, length, out=np.zeros_like(weighted), where=length > 0)
    count = len(faces)
    order, runs, uses = edge_runs(faces)
    pair = runs[uses == 2]  # edges of two faces: a non-manifold one joins none
    first, second = order[pair], order[pair + 1]  # half-edges (face * 3 + k) of one edge
    f, g = first // 3, second // 3
    smooth = np.einsum("ij,ij->i", unit[f], unit[g]) >= math.cos(math.radians(crease_angle)) - 1e-9
    first, second, f, g = first[smooth], second[smooth], f[smooth], g[smooth]
    # join the corners at both ends of each smooth edge: the corner of f at a vertex with g's there
    links = []
    for half_edge, face, other in ((first, f, g), (second, g, f)):
        for step in (0, 1):
            vertex = faces[face, (half_edge % 3 + step) % 3]
            corner_other = other * 3 + np.argmax(faces[other] == vertex[:, None], axis=1)
            links.append(np.stack([face * 3 + (half_edge % 3 + step) % 3, corner_other]))
    links = np.concatenate(links, axis=1)
    graph = coo_matrix((np.ones(links.shape[1], np.int8), (links[0], links[1])), shape=(3 * count, 3 * count))
    _, group = connected_components(graph, directed=False)
    sums = np.zeros((group.max() + 1, 3))
    np.add.at(sums, group, np.repeat(weighted, 3, axis=0))
    normals = sums[group]
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    normals = np.divide(normals, length, out=np.repeat(unit, 3, axis=0), where=length > 0)
    return normals.reshape(count, 3, 3)


@numba.njit(cache=True)
def _throw_darts(first, second, count):
    """Which of `count` candidates, thrown in index order, land within r of one kept before:
    each close pair (first < second, sorted by first, so that whether its first is kept is
    settled) removes its second where its first is kept."""
    removed = np.zeros(count, np.bool_)
    for k in range(len(first)):
        if not removed[first[k]]:
            removed[second[k]] = True
    return removed


def open_face_share(mesh: PointCloud) -> float:
    """The share of the mesh's area in faces its vertices leave open (module docstring): faces
    whose longest edge exceeds LARGE_FACE times the mesh's median edge, or whose point farthest
    from its corners (the circumcentre; the longest edge's midpoint where the triangle is
    obtuse) lies farther from them than any corner's splat may reach (BOUND_FACTOR times its
    local spacing, spacing.py). Above OPEN_SHARE the vertices leave much of the surface open:
    0.42 to 0.995 on nine of trimesh's CAD exports (the plate with pockets 0.77; a rod whose
    wall is slivers as long as the rod 0.995, which long edges alone put at 0), at most 0.17
    on 18 models of alecjacobson/common-3d-test-models and 10 decimations of them (ogre 0.17,
    the others 0.041 or less). Boxes of 8 and 14 vertices read 0: their splats cover their
    faces, and spill past them."""
    positions = np.asarray(mesh.positions, np.float64)
    triangles = positions[mesh.faces]
    edges = np.linalg.norm(triangles - np.roll(triangles, 1, axis=1), axis=2)
    area = 0.5 * np.linalg.norm(face_vectors(positions, mesh.faces), axis=1)
    total = area.sum()
    if not total > 0:
        return 0.0
    # room for LOCAL_NEIGHBOURS distinct neighbours past a vertex's copies along seams
    nbh = Neighbourhood.build(positions, min(2 * LOCAL_NEIGHBOURS + 1, len(positions)), progress=False)
    reach = BOUND_FACTOR * nbh.unsort(local_spacing(nbh, progress=False))  # NaN without a distinct neighbour
    squares = np.sort(edges**2, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        farthest = np.where(squares[:, 2] > squares[:, 0] + squares[:, 1], 0.5 * np.sqrt(squares[:, 2]),
                            edges.prod(axis=1) / (4 * area))  # circumradius abc / 4A
    open_faces = (edges.max(axis=1) > LARGE_FACE * np.median(edges)) | (farthest > reach[mesh.faces].max(axis=1))
    return float(area[open_faces].sum() / total)


def sample_surface(mesh: PointCloud, settings: SampleSettings = SampleSettings()) -> PointCloud:
    """About `settings.points` points spread evenly over `mesh`'s faces, with crease-angle
    normals and the vertices' colours interpolated (module docstring)."""
    if not mesh.is_mesh:
        raise SurfelError(f"{mesh.source}: sample needs a mesh (faces) to sample")
    positions = np.asarray(mesh.positions, np.float64)
    faces = np.asarray(mesh.faces, np.int64)
    triangles = positions[faces]
    area = 0.5 * np.linalg.norm(face_vectors(positions, faces), axis=1)
    total = float(area.sum())
    if not total > 0:
        raise SurfelError(f"{mesh.source}: the mesh's faces have no area to sample")
    rng = np.random.default_rng(SEED)
    count = CANDIDATES * settings.points
    face = np.minimum(np.searchsorted(np.cumsum(area), rng.random(count) * total, side="right"), len(faces) - 1)
    root, r2 = np.sqrt(rng.random(count)), rng.random(count)
    bary = np.stack([1 - root, root * (1 - r2), root * r2], axis=1)
    points = np.einsum("ij,ijk->ik", bary, triangles[face])
    radius = math.sqrt(4 * COVERAGE * total / (math.pi * settings.points))
    pairs = cKDTree(points).query_pairs(radius, output_type="ndarray")  # i < j: j is thrown after i
    pairs = pairs[np.argsort(pairs[:, 0], kind="stable")]
    kept = np.flatnonzero(~_throw_darts(pairs[:, 0].astype(np.int64), pairs[:, 1].astype(np.int64), count))
    face, bary, points = face[kept], bary[kept], points[kept]
    normals = np.einsum("ij,ijk->ik", bary, corner_normals(positions, faces, settings.crease_angle)[face])
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-300)
    corners = faces[face]
    colors = None
    if mesh.colors is not None:
        colors = np.einsum("ij,ijk->ik", bary, np.asarray(mesh.colors, np.float64)[corners]).astype(np.float32)
    schema, nearest = mesh.schema, corners[np.arange(len(corners)), np.argmax(bary, axis=1)]
    attributes = {}
    for name, values in mesh.attributes.items():
        if name in DERIVED:
            continue
        if schema[name].kind == CATEGORICAL:
            attributes[name] = values[nearest]
            continue
        blend = np.einsum("ij,ij...->i...", bary, values[corners].astype(np.float64))
        attributes[name] = (np.rint(blend) if values.dtype.kind in "biu" else blend).astype(values.dtype)
    kinds = {name: kind for name, kind in mesh.kinds.items() if name in attributes}
    return PointCloud(points, normals=normals, colors=colors, attributes=attributes, kinds=kinds,
                      source=mesh.source)
