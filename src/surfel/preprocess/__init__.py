"""What surface splatting assumes of its points, estimated from raw positions.

One module per estimation, each citing its source, with its tuning constants at its top:

  normals.py         PCA normals; orientation by propagation (Hoppe et al. 1992) or towards a
                     viewpoint
  frames.py          circular splat axes: tangent frames (Duff et al. 2017)
  cells.py           tangent-plane Voronoi cells: covering radii and ellipses (Botsch et al.
                     2004), cut at creases, and the splats' clip lines there and at the
                     borders of open surfaces (its kernels: cell_kernels.py)
  outlier_cap.py     radii no larger than twice the median of the neighbours' on the same surface
  sharp_features.py  flat points and crease points (Zwicker et al. 2002, Pauly et al. 2003)
  borders.py         border points of open surfaces and their outward directions (Pauly et al.
                     2003), from the neighbours or a mesh's boundary edges
  normal_field.py    Phong splatting's linear normal fields (Botsch et al. 2004)
  structure.py       points on no surface (vegetation, wires, noise; Demantké et al. 2011) and
                     points without a tangent plane: round splats facing the camera
  smoothing.py       denoised positions: projection onto the MLS surface (Adamson & Alexa 2003)
  spacing.py         the sampling bound: splats no larger than the local and the acquisition's
                     point spacing warrant
  coincident.py      points that repeat a position (a mesh's seams): estimated once per position
  mesh_samples.py    points spread evenly over a mesh's faces (dart throwing, Cook 1986) with
                     crease-angle normals: `surfel sample`, for CAD exports
  complete.py        `prepare`: fill in what a cloud lacks; `complete`: the one policy for what
                     a method gets estimated

They share two steps: `neighbourhood.py`, the k nearest neighbours (`grid_knn.py`, a grid of
Morton-ordered cells) in that cell order, and `chunked.py`, the chunked, progress-reporting loop
every per-point kernel runs in.

Memory stays bounded: the neighbour lists (N x k indices) and the propagation graph are the
only O(N k) arrays; all per-neighbour work runs in numba kernels (parallel over points) in
chunks. Every public function takes and returns arrays in the input's order.
"""

from .cell_kernels import CLIP_LINES, INACTIVE_CLIP
from .cells import clipped_away, estimate_radii, fit_ellipses
from .complete import complete, completes_with_clip_lines, prepare
from .frames import tangent_frames
from .normal_field import fit_normal_field, has_normal_field, splat_slopes
from .normals import estimate_normals
from .structure import drawn_normals, facing_mask
from .thickness import splat_thickness

__all__ = ["CLIP_LINES", "INACTIVE_CLIP", "clipped_away", "complete", "completes_with_clip_lines", "drawn_normals",
           "estimate_normals", "estimate_radii", "facing_mask", "fit_ellipses", "fit_normal_field", "has_normal_field",
           "prepare", "splat_slopes", "splat_thickness", "tangent_frames"]
