"""Image metrics every method is judged by (issue 2): PSNR, interior PSNR, holes and spill.

All compare a method's render against the mesh render under the same camera:
* psnr          : RGB composited over black, whole image, 8-bit peak.
* interior_psnr : the same over the mesh silhouette (alpha >= 0.5) eroded by 2 pixels.
* holes         : fraction of pixels inside the silhouette eroded by 1 pixel that the method
                  leaves uncovered (alpha < 0.5).
* spill         : fraction of pixels outside the silhouette (the complement of the dilated
                  silhouette, i.e. the background eroded by 1 pixel) that the method covers.

A LiDAR tile has no mesh; its top orthographic view is judged against its returns
(`top_view_footprint`, issue 14): the share of covered pixels farther than 4 median
horizontal point spacings from every return (surface invented past the data), and the share
of the footprint (pixels within 1.5 spacings of a return) left uncovered (holes).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree


def psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> float:
    """PSNR in dB of two 8-bit-valued float images, optionally over a boolean mask."""
    diff = (a - b) ** 2
    if mask is not None:
        diff = diff[mask]
    mse = float(diff.mean()) if diff.size else 0.0
    return float("inf") if mse == 0 else 10 * np.log10(255.0**2 / mse)


def compare_images(reference_rgb, reference_alpha, rgb, alpha) -> dict:
    """The four metrics for float RGB in [0, 1] composited over black and alpha in [0, 1]."""
    ref8 = np.round(np.clip(reference_rgb, 0, 1) * 255)
    img8 = np.round(np.clip(rgb, 0, 1) * 255)
    silhouette = reference_alpha >= 0.5
    inner1 = ndimage.binary_erosion(silhouette, iterations=1)
    inner2 = ndimage.binary_erosion(silhouette, iterations=2)
    outside = ndimage.binary_erosion(~silhouette, iterations=1)
    covered = alpha >= 0.5
    return {
        "psnr": psnr(ref8, img8),
        "interior_psnr": psnr(ref8, img8, inner2),
        "holes": float((~covered & inner1).sum() / max(inner1.sum(), 1)),
        "spill": float((covered & outside).sum() / max(outside.sum(), 1)),
    }


def compare_results(reference, result) -> dict:
    """compare_images on two RenderResults rendered over a black background."""
    return compare_images(reference.color, reference.alpha, result.color, result.alpha)


def compare_with_mesh(mesh, camera, method: str, options, renderer, *, backend: str | None = None,
                      every: int = 1) -> tuple:
    """Render `mesh`'s ground truth and `method` on its vertices (every `every`th only: sparse
    sampling, normals kept, splat sizes estimated), both over black; (reference, result, metrics)."""
    from dataclasses import replace

    from .errors import SurfelError

    if not mesh.is_mesh:
        raise SurfelError(f"{mesh.source}: compare needs a mesh (faces) as ground truth")
    black = (0.0, 0.0, 0.0)  # the metrics are defined over black
    reference = renderer.render(mesh, camera, "mesh", options=replace(
        options, background=black, params=None, supersample=None, lod_error=None, point_budget=None, dump_passes=None))
    vertices = mesh.take(np.arange(0, len(mesh), every))  # every = 1: all of them, without the faces
    result = renderer.render(vertices, camera, method, backend=backend, options=replace(options, background=black))
    metrics = {"method": method, "backend": result.stats["backend"], **compare_results(reference, result),
               "ms": result.stats["ms"], "splats": result.stats["splats"]}
    return reference, result, metrics


def side_by_side(reference, result) -> bytes:
    """A PNG of the mesh, the method and their error x4, side by side."""
    import io

    from PIL import Image

    error = np.abs(reference.color - result.color).mean(axis=-1, keepdims=True)
    error = np.repeat(np.clip(4 * error, 0, 1), 3, axis=-1)
    strip = np.concatenate([reference.color, result.color, error], axis=1)
    buffer = io.BytesIO()
    Image.fromarray(np.round(strip * 255).astype(np.uint8)).save(buffer, format="PNG")
    return buffer.getvalue()


def pixel_centres_xy(camera) -> np.ndarray:
    """World x, y (H, W, 2) of the pixel centres of an orthographic top camera."""
    j, i = np.meshgrid(np.arange(camera.width) + 0.5, np.arange(camera.height) + 0.5)
    scale = camera.ortho_height / camera.height
    inverse = np.linalg.inv(camera.world_to_eye)
    right, up = ((j - camera.cx) * scale)[..., None], ((camera.cy - i) * scale)[..., None]
    return (right * inverse[:3, 0] + up * inverse[:3, 1] + inverse[:3, 3])[..., :2]


def top_view_footprint(result, camera, positions: np.ndarray, distinct: bool = False) -> tuple[float, float]:
    """(far, uncovered) of a top orthographic view of a tile (module docstring). The spacing
    is the median horizontal nearest-neighbour distance, or with `distinct` the distance to
    the nearest return elsewhere (coincident returns would make it 0)."""
    xy = np.asarray(positions, np.float64)[:, :2]
    tree = cKDTree(xy)
    distances, _ = tree.query(xy, k=min(8, len(xy)))
    distances = distances.reshape(len(xy), -1)
    if distinct:
        positive = distances > 0
        rows = positive.any(axis=1)
        spacing = float(np.median(distances[rows, positive[rows].argmax(axis=1)]))
    else:
        spacing = float(np.median(distances[:, 1]))
    nearest, _ = tree.query(pixel_centres_xy(camera).reshape(-1, 2))
    nearest = nearest.reshape(camera.height, camera.width)
    covered = result.alpha > 0
    far = (covered & (nearest > 4 * spacing)).sum() / max(covered.sum(), 1)
    footprint = nearest <= 1.5 * spacing
    return float(far), float((footprint & ~covered).sum() / max(footprint.sum(), 1))
