"""Tangent-plane Voronoi cells: splat radii and ellipses that cover the surface, cut at creases.
(The compiled kernels, and the constants they read, are `cell_kernels.py`'s.)

Radii (`estimate_radii`): each splat covers its own Voronoi cell.
    The union of disks covers a surface exactly when every sample's disk contains the part of
    the surface nearer to it than to any other sample: its Voronoi cell. So the radius is the
    distance from the point to the farthest vertex of its cell, computed in its tangent frame
    (t, s) among its k nearest neighbours: the half-planes nearer to it than to each neighbour
    d = (x, y), x X + y Y <= |d|^2 / 2, clipped to a regular CAP_SIDES-gon inscribed in the
    circle of the farthest neighbour's distance (open cells, at borders, stop there); times
    RADIUS_MARGIN for curvature and normal noise. Unlike a fixed multiple of a neighbour
    distance, this adapts to the anisotropic spacing of LiDAR scan lines (a cell is long across
    the lines, short along them) and to jittered sampling, without inflating the splats of
    regular regions. Neighbours whose oriented normals face away (n_p . n_q < SHEET_COS, the
    other side of a sheet, which would cut this side's cells into holes) do not cut the cell,
    nor do those of another layer lying close (`thickness.py`). One more than 45 degrees off the
    tangent plane (|z| > |(x, y)|) cuts nothing above it (a concave corner: the other surface
    hides what passes it) or with unoriented normals (a thin sheet's far side); below it, where
    the surface turns sharply away (a horn's or a hoof's tip, a rim), the cell ends where q's
    tangent plane meets p's, as at a crease, but no nearer than half-way to q's projection: a
    tip gets a small splat, not a disk standing out past it as wide as its neighbourhood, and at
    a sharp convex edge both sides' splats reach the edge and stop there. (On the vertices of 13
    models of common-3d-test-models, `phong` at 512 x 512, two views: median PSNR 32.87 ->
    33.11 dB, the cow 24.0 / 26.1 -> 25.4 / 29.3 dB; on their raw range scans,
    `benchmarks/scan_fidelity.py`: 30.93 -> 31.05 dB.)
    The cell's end is also a clip line of the splat where p lies below q's plane too (a convex
    edge, a thin part's rim: the disk, as wide as the cell's farthest vertex along the edge,
    would otherwise stand out past it by nearly its radius, a scalloped rim on a plate thinner
    than its sampling); not where q is another part of the surface below p (a tail hanging
    under a rump, which sees p above its plane), whose cut opened the rump (the cow's worst
    holes 0.063 -> 0.144%; 0.094% with this condition). (The vertices of 14 models and 3
    coarse figures at 512 x 512, 48 oblique views each: median PSNR +0.4 to +1.4 dB on the
    bunny, nefertiti, the cow, the teapot, casting.obj and the coarse figures for `phong` and
    `deferred`, no model lower by more than 0.03 dB, no view newly over 0.1% of holes; raw
    scans of 9 models unchanged; a 64-sided plate 0.06 thick, six tenths of its sampling, seen
    from elevation 20: 21.3 -> 27.9 dB, spill 1.2 -> 0.18%.)
    Radii far above those of the neighbours on the point's surface are capped (`outlier_cap.py`)
    so that stray points do not become blobs.

Ellipses (`fit_ellipses`, for Phong splatting, Botsch, Spernat & Kobbelt 2004):
    axis directions are the principal curvature directions ("aligned along the curvature",
    survey 2.1.4; the shape operator S, tilt = S offset, fitted by least squares to the
    neighbours' normals) where the normals turn more one way than the other (by
    CURVATURE_ANISOTROPY across the cell), else the principal directions of the neighbours
    projected into the tangent plane; the semi-axes are those of the smallest-area ellipse with
    these directions that contains the point's Voronoi cell (aspect at most ELLIPSE_MAX_ASPECT):
    with semi-axes (e^(tau/2), e^(-tau/2)) x scale, the needed scale^2 is a maximum of functions
    convex in tau, so a golden-section search finds tau. Times RADIUS_MARGIN and the same outlier
    cap: the covering rule of the radii, never with more area than the disk (one of the
    candidates). u is the major axis, (u, v, n) right-handed.
    Points sampled from a surface (not a scan, which its acquisition's spacing bounds) fit their
    ellipse to the part of the cell within the disc the sampling bound lets the splat reach
    (spacing.py, over the margin; lifted where rows lie far apart, as the bound will be). A cell
    left open (a flat cut-out's outline; a thin part sampled in rings of vertices, the next ring
    beyond the k nearest) ran out to the farthest neighbour, the aspect limit widened its ellipse
    to a quarter of that length, and the bound, cutting the long axis only, kept the width: on
    the cow's tail, splats 0.18 x 0.11 across rings of vertices 0.05 apart (now 0.18 x 0.06).
    (Vertices of 14 models, 18 views each at 512 x 512, mean PSNR per model for `deferred` /
    `phong`: alligator +0.35 / +0.40 dB and woody +0.17 / +0.17 dB, flat cut-outs; beetle-alt
    +0.17 / +0.22 dB, the teapot +0.12 / +0.12 dB, the rest within 0.04 dB; no view newly over
    0.1% holes. The cow's tail still shows beads past its outline: splats whose ellipses the
    rump's samples bound, or whose axes a curvature fit over one ring's neighbours turns at
    random. Raw scans of rocker-arm, whose underside the scan saw at grazing angles, opened
    0.105-0.122% holes in four oblique views with their ellipses clipped, and LiDAR tiles'
    uncovered footprint grew from 0.001% to 0.013%: a scan's cells stay whole.)

Short sides (`cell_kernels._short_side`): an ellipse is centred on its point, so a cell that
    ends near the point on one side (a dense row beside it) and far on the other (a sparse row)
    gets an ellipse that reaches as far past the near side as the far side needs. On a curved
    surface that part stands out of the surface: the Newell teapot's lid edge and rolled rim,
    rows 0.04 apart beside rows 0.16 apart, stood out over the lid and past its outline. Where a cell
    reaches LOPSIDED times farther the other way than to one of its bisectors, the splat is cut
    by that bisector's line moved out to SHORT_MARGIN times its distance (past the neighbour
    whose bisector it is, whose splat covers the rest), if the splat reaches more than
    1 / SHORT_SIDE times as far and a clip line is left after the creases and borders. Bisectors
    only: a crease's or a turn's end of the cell has its own line. Points sampled from a surface
    only, as for the bound above: a scan's cells stay whole (cut, a LiDAR tile's footprint left
    0.01% more of its pixels uncovered). (Vertices, 18 views at 512 x 512: the teapot 30.87 ->
    34.27 dB with `phong`, 30.76 -> 33.80 dB with `deferred`; seven decimated figures +0.06 to
    +0.47 dB with `phong`, five +0.06 to +0.49 dB with `deferred`; 12 other models -0.08 to
    +0.11 dB; no view newly over 0.1% of holes. At SHORT_MARGIN 1.2 to 2.0, with every edge of
    the cell a candidate, views opened holes past 0.1% on the cow's tail and a decimated head's
    chin.)

Cells at creases (Zwicker et al. 2002, Pauly et al. 2003; which points are flat and which lie on
creases: `sharp_features.py`):
    for a neighbour q on a face (a flat point) whose normal lies more than SHARP_ANGLE from p's,
    p's cell ends at the line where their tangent planes meet instead of at the bisector, so
    that its radius reaches the edge and no further. p may lie on a face too, or on a coarse
    curved surface meeting the face (a CAD part's cylinder or fillet, normals turning tens of
    degrees a vertex), whose rim splats would stand out past the face: a face's plane is a true
    edge; the tangent plane of a coarse curved surface is not, and cuts nothing (it would facet
    it). p keeps its centre's side of q's plane, g(X) = n_q . (X - q) having the sign of g(p);
    if its centre lies in that plane (within ON_PLANE_SIN2, on the crease line), the side away
    from q, from p on (the plane may pass p on that side within the tolerance, and cut its
    centre away). Where q lies above p's plane (a concave crease), its line must lie between
    p and q's projection, as a clip line and as the cell's end; a q projecting on p's side of
    it by more than BEYOND_MARGIN of its distance cuts nothing and bounds nothing. A denser
    fillet's rows beyond its first turn their planes back across p's face, and their lines,
    on the far side of p from q, cut the face instead: the last row of a car's door below the
    fillet of its belt line kept an elliptical cell a third as wide as its rows lie apart, and
    holes opened along the door (beetle-alt.obj, 48 oblique views, worst holes 0.158 ->
    0.136% with the clip lines' rule, -> 0.074% with the cells' too). The margin keeps a
    right angle's line, onto which q projects to within rounding: without it, a wall's rows
    bounded no floor cell beside it (casting.obj -0.07 dB). A convex crease keeps its line
    wherever it lies: past an acute edge the other face folds back under p's, and its line is
    the edge all the same (fandisk lost 6 dB without it).
    Crease points bound no cell. A q facing away (n_p . n_q < SHEET_COS) that lies in
    p's face (within FLAT_SIN2 of its plane) is the same surface seen from behind: no crease.
    A face's rim where a coarse curved surface meets it (a bolt hole's wall, a rounded outer
    edge) has no crease points, which take two faces: its points lie in the face's plane with
    normals averaged over face and wall. For a flat p and such a neighbour q in its plane
    (within FLAT_SIN2) with a normal more than SHARP_ANGLE off, p's splat is also cut by the line
    where their tangent planes meet, which runs through q along the rim, moved out by
    RIM_MARGIN of q's distance from p (in p's u, v): a clip line only, the cell stays whole.
    Without it a coarse plate's splats reached across its bolt holes and filled them (casting.obj,
    a 5,096-vertex CAD part, six views at 512 x 512: `deferred` +0.02 to +0.68 dB, `phong`
    +0.01 to +1.03 dB; nefertiti's flat base up to +0.27 dB; 11 other models, their raw scans
    and LiDAR tiles unchanged). Through q itself (no margin) the line opened the holes further
    but cut the face short beside a hole seen obliquely (holes 0.085 -> 0.164%).
    Each splat then carries up to CLIP_LINES clip lines a u + b v <= c in its local coordinates
    (u, v) (1 on the rim), attributes["clip_lines"] (N, CLIP_LINES, 3), (a, b) a unit vector:
    the crease nearest its centre, then the nearest in another direction (more than
    acos(PARALLEL_COS) apart); crease points get lines that keep nothing (c < -1,
    `clipped_away`), smooth surfaces INACTIVE_CLIP. Every splat method evaluates the lines per
    fragment (the GPU methods in the splat's plane, EWA as pixel half-planes through its
    Jacobian).

Borders of open surfaces (`borders.py`, as the boundary clipping of Pauly et al. 2003):
    the border line (X - q) . w_q <= f_q across each border point q's outward direction w_q,
    through q moved out by its fold's reach f_q (0 on an open sheet), is a clip-line candidate
    of every splat near it, beside the creases; a noisy cloud's lines move out further, by a
    margin m of the splat's extent across them (its local u, v: the line a u + b v <= c + m).
    A thin part's two sides both end at its rim, so the line of a q facing away cuts p too,
    unless p's side goes on past it: a neighbour facing p's way (within SHARP_ANGLE), not on a
    border itself, lies beyond the line (`cell_kernels._goes_on_past`). The open edge of a
    rolled rim's inner wall had cut the outer wall's splats in half there, a band of holes
    around the Newell teapot and an ogre's belly under its belt (decimated ogre, `deferred`,
    18 views at 512 x 512: worst holes 0.106 -> 0.060%; 14 models' vertices within -0.06 to
    +0.08 dB, their raw scans within -0.05 to +0.02 dB).
    A mesh's border (its boundary edges, `borders.py`) ends where its edges turn: past a concave
    corner of its outline (a slot's inner end, the root of a tooth) a line would run on across
    the surface beyond and cut slivers from it. So a mesh border point q's line cuts a splat
    only where it crosses the splat near q: q lies, along the line, within the line's half chord
    across the splat (in its u, v) plus CHORD_SLACK. (Meshes with their faces, 18 views at 512 x
    512: worst holes of woody 0.076 -> 0.044% and of the alligator 0.047 -> 0.014% with `phong`,
    the alligator's teeth under `ewa` 0.292 -> 0.049%, 11 -> 0 views over 0.1%, and +0.3 to +0.5
    dB; 8 other meshes within -0.13 to +0.05 dB.) The borders the neighbours find keep their
    lines whole: their directions, the middle of a gap, tilt along a curving outline, and a
    farther border point's line is often the one that ends the splat (the rule cost flat
    cut-outs' vertices 0.7 to 2.0 dB there).
"""

from __future__ import annotations

import numpy as np

from ..cloud import PointCloud, any_per_row
from .cell_kernels import INACTIVE_CLIP, MESH_BORDER, PARALLEL_COS, cell_clip_lines, cell_ellipses, cell_radii
from .chunked import map_chunks
from .frames import ellipse_axes, orthonormal_basis, unit
from .neighbourhood import Neighbourhood
from .normals import pca_normals
from .outlier_cap import outlier_cap
from .sharp_features import SHEET_COS, SharpFeatures
from .thickness import layer_thickness

RADIUS_NEIGHBOURS = 16         # neighbours bounding a Voronoi cell: enough to reach the next scan
                               # line when lines are up to ~8 x farther apart than points on a line
RADIUS_MARGIN = 1.2            # covering radius x this: curvature, normal noise, and overlap for
                               # the Gaussian blending (coverage 99.98% at 1.0, 99.998% at 1.2)
SHORT_MARGIN = 2.5             # a splat's line at its cell's short side: this many times the side's distance out,
SHORT_SIDE = 0.5               # ... where the splat reaches more than 1 / this as far


def _cells(nbh: Neighbourhood, normals: np.ndarray, k: int, ellipse: bool, progress: bool | None,
           features: SharpFeatures | None, oriented: bool, layers: np.ndarray | None,
           bound: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Radii (N,) float64 and, if `ellipse`, axes (N, 2, 3) float64, both including the margin
    and the outlier cap, and, if `ellipse`, the cells' short sides (N, 4): (w, c), X . w <= c in
    the tangent plane about the point, c = 0 where none. Given `features`, cells end at creases
    and ignore the crease points.
    With `oriented` normals, neighbours facing the other way (the far side of a thin sheet) do
    not bound cells, and those steeply below the tangent plane end them where their planes meet
    it; given `layers` (thickness.py), those of another layer do not bound them. Given `bound`
    (N,), each ellipse is fitted to the part of its cell within bound / RADIUS_MARGIN of the
    point, which the splat, the margin added, may reach."""
    n = len(nbh.points)
    layers = np.full(n, np.inf) if layers is None else np.asarray(layers, np.float64)
    reach_bound = np.full(n, np.inf) if bound is None else np.asarray(bound, np.float64) / RADIUS_MARGIN
    index = nbh.first(k)
    normals = unit(normals)
    features = SharpFeatures.none(n) if features is None else features
    sheet_cos = SHEET_COS if oriented else -2.0

    def radii(start: int, stop: int) -> np.ndarray:
        frames = orthonormal_basis(normals[start:stop])
        return cell_radii(nbh.points, normals, index[start:stop], start, frames, features, sheet_cos, layers)

    def ellipses(start: int, stop: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        frames = orthonormal_basis(normals[start:stop])
        radius, semi, direction, short = cell_ellipses(nbh.points, normals, index[start:stop], start, frames,
                                                       features, sheet_cos, layers, reach_bound)
        sides = np.einsum("ij,ijk->ik", short[:, :2], frames)
        return radius, ellipse_axes(frames, semi, direction), np.column_stack([sides, short[:, 2]])

    if ellipse:
        raw, axes, short = map_chunks(ellipses, n, progress, "ellipses")
    else:
        raw, axes, short = map_chunks(radii, n, progress, "radii"), None, None
    # Points all of whose neighbours coincide with them have no cell: borrow a typical size.
    positive = raw > 0
    raw[~positive] = np.median(raw[positive]) if positive.any() else 1.0
    if ellipse:
        circle = ~positive | (np.linalg.norm(axes, axis=2).min(axis=1) <= 0)
        axes[circle] = orthonormal_basis(normals[circle]) * raw[circle][:, None, None]
    scale = RADIUS_MARGIN * outlier_cap(raw, index, normals, oriented)
    if ellipse:
        axes *= scale[:, None, None]
        short[circle] = 0.0
    return raw * scale, axes, short


def covering_radii(nbh: Neighbourhood, normals: np.ndarray, progress: bool | None,
                   features: SharpFeatures | None = None, k: int = RADIUS_NEIGHBOURS,
                   oriented: bool = True, layers: np.ndarray | None = None) -> np.ndarray:
    """Splat radii (N,) float64 in the neighbourhood's order (see the module docstring)."""
    return _cells(nbh, normals, k, False, progress, features, oriented, layers)[0]


def covering_ellipses(nbh: Neighbourhood, normals: np.ndarray, progress: bool | None,
                      features: SharpFeatures | None = None, k: int = RADIUS_NEIGHBOURS,
                      layers: np.ndarray | None = None, bound: np.ndarray | None = None
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Elliptical splat axes (N, 2, 3) float64 and the cells' short sides (N, 4) (w, c: the
    side X . w <= c, c = 0 where none), in the neighbourhood's order; `bound` (N,): the most a
    semi-axis may reach (spacing.bound_semi_axes), if the sampling bounds them."""
    _, axes, short = _cells(nbh, normals, k, True, progress, features, True, layers, bound)
    return axes, short


def clip_lines(nbh: Neighbourhood, normals: np.ndarray, axes: np.ndarray, features: SharpFeatures,
               outwards: np.ndarray, reach: np.ndarray, progress: bool | None,
               k: int = RADIUS_NEIGHBOURS, margin: float = 0.0, layers: np.ndarray | None = None,
               short_sides: np.ndarray | None = None, mesh_borders: np.ndarray | None = None) -> np.ndarray:
    """Clip lines (N, CLIP_LINES, 3) float32 of the splats (normals, axes, oriented), in the
    neighbourhood's order: at creases and where the surface turns sharply away (neighbours of
    another of the `layers` aside, thickness.py), and at the borders of open surfaces given by
    `outwards` (N, 3), the border points' outward directions, zero elsewhere, and `reach` (N,),
    their folds' reach (`borders.border_outwards`); the border lines moved out by `margin` of
    each splat (a noisy cloud's, borders.NOISY_MARGIN); where a line is left, the cell's short
    side from `short_sides` (N, 4), `covering_ellipses`'. `mesh_borders` (N,) bool: the border
    points that are a mesh's boundary vertices (`borders.mesh_border_outwards`), whose lines
    end with their edges."""
    index = nbh.first(k)
    normals = unit(normals)
    layers = np.full(len(normals), np.inf) if layers is None else np.asarray(layers, np.float64)
    on_border = any_per_row(outwards != 0.0).astype(np.int8)
    if mesh_borders is not None:
        on_border[mesh_borders] = MESH_BORDER

    def chunk(start: int, stop: int) -> np.ndarray:
        chunk_axes = np.asarray(axes[start:stop], np.float64)
        lines = cell_clip_lines(nbh.points, normals, index[start:stop], start, chunk_axes, features, layers,
                                outwards, on_border, reach, margin)
        if short_sides is not None:
            _cut_short_sides(lines, chunk_axes, np.asarray(short_sides[start:stop], np.float64))
        return lines

    return map_chunks(chunk, len(nbh.points), progress, "sharp features")


def _cut_short_sides(lines: np.ndarray, axes: np.ndarray, short: np.ndarray) -> None:
    """Put each splat's short side (w, c) = short (cells with none: c = 0) into the first of its
    clip lines left inactive, as X . w <= SHORT_MARGIN c in its plane, where the splat reaches
    more than 1 / SHORT_SIDE times as far and no line there is within acos(PARALLEL_COS) of it."""
    a, b = np.einsum("nj,nj->n", axes[:, 0], short[:, :3]), np.einsum("nj,nj->n", axes[:, 1], short[:, :3])
    reach = np.hypot(a, b)  # how far the splat reaches along w
    moved = SHORT_MARGIN * short[:, 3]
    free = (lines == np.float32(INACTIVE_CLIP)).all(axis=2)
    with np.errstate(divide="ignore", invalid="ignore"):
        line = np.stack([a / reach, b / reach, moved / reach], axis=1)
    parallel = (~free & (lines[:, :, 0] * line[:, None, 0] + lines[:, :, 1] * line[:, None, 1] > PARALLEL_COS)).any(1)
    rows = np.flatnonzero((moved > 0) & (moved < SHORT_SIDE * reach) & free.any(axis=1) & ~parallel)
    lines[rows, free[rows].argmax(axis=1)] = line[rows]


def clipped_away(cloud: PointCloud) -> np.ndarray:
    """(N,) bool: the splats whose clip lines keep nothing of them (crease points)."""
    lines = cloud.attributes.get("clip_lines")
    if lines is None:
        return np.zeros(len(cloud), bool)
    return any_per_row(lines[:, :, 2] < -1)


def estimate_radii(positions: np.ndarray, k: int = RADIUS_NEIGHBOURS, normals: np.ndarray | None = None,
                   workers: int = -1, progress: bool | None = None) -> np.ndarray:
    """Splat radii (N,) float32 that cover the surface without holes: each point's covering
    radius of its tangent-plane Voronoi cell among its k nearest neighbours, times
    RADIUS_MARGIN, outliers capped (see the module docstring). Normals only define the tangent
    planes (and, oriented, which way the surface turns and the layers: thickness.py); without
    them unoriented PCA normals over the same neighbours are used."""
    nbh = Neighbourhood.build(positions, k, workers, progress)
    oriented = normals is not None
    normals = pca_normals(nbh, k, progress)[0] if normals is None else nbh.sort(normals)
    layers = layer_thickness(nbh.points, unit(normals), nbh.index) if oriented else None
    radii = covering_radii(nbh, normals, progress, k=k, oriented=oriented, layers=layers)
    return nbh.unsort(radii.astype(np.float32))


def fit_ellipses(positions: np.ndarray, normals: np.ndarray, k: int = RADIUS_NEIGHBOURS, workers: int = -1,
                 progress: bool | None = None) -> np.ndarray:
    """Elliptical splat axes (N, 2, 3) float32 (u major, (u, v, n) right-handed): principal
    directions of the curvature or of the neighbours in the tangent plane, semi-axes covering
    the point's Voronoi cell like the radius rule (see the module docstring)."""
    nbh = Neighbourhood.build(positions, k, workers, progress)
    normals = nbh.sort(normals)
    layers = layer_thickness(nbh.points, unit(normals), nbh.index)
    return nbh.unsort(covering_ellipses(nbh, normals, progress, k=k, layers=layers)[0].astype(np.float32))
