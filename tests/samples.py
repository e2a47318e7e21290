"""Point samples of known surfaces, and what the preprocessing tests measure on them."""

from __future__ import annotations

from functools import cache

import numpy as np
from scipy.spatial import cKDTree

from surfel.cloud import PointCloud


def unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def sphere(n: int, seed: int = 0, noise: float = 0.0) -> np.ndarray:
    """Unit-sphere samples (also their exact outward normals when noise = 0)."""
    rng = np.random.default_rng(seed)
    p = unit(rng.normal(size=(n, 3)))
    return p + rng.normal(0, noise, p.shape) if noise else p


def angles(a: np.ndarray, b: np.ndarray, oriented: bool = True) -> np.ndarray:
    """Angle in degrees between unit row vectors (ignoring sign unless oriented)."""
    dot = np.einsum("ij,ij->i", unit(a), unit(b))
    return np.degrees(np.arccos(np.clip(dot if oriented else np.abs(dot), -1, 1)))


@cache
def dense_samples() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A dense organic mesh (Spot refined to 46,850 vertices, tests/models.py): its vertices as
    the cloud, its area-weighted vertex normals, and 200,000 samples of its faces as the true
    surface."""
    from models import dense_spot

    mesh = dense_spot()
    vertices, faces = mesh.positions, mesh.faces
    used = np.unique(faces)
    cross = np.cross(vertices[faces[:, 1]] - vertices[faces[:, 0]], vertices[faces[:, 2]] - vertices[faces[:, 0]])
    normals = np.zeros_like(vertices)
    for corner in range(3):  # area-weighted vertex normals: |cross| is twice the area
        np.add.at(normals, faces[:, corner], cross)
    rng = np.random.default_rng(1)
    area = np.linalg.norm(cross, axis=1)
    tri = rng.choice(len(faces), 200_000, p=area / area.sum())
    r1, r2 = np.sqrt(rng.random(len(tri))), rng.random(len(tri))
    w = np.stack([1 - r1, r1 * (1 - r2), r1 * r2], axis=1)
    surface = np.einsum("nc,ncj->nj", w, vertices[faces[tri]])
    return vertices[used], unit(normals[used]), surface


def coverage(surface: np.ndarray, centres: np.ndarray, normals: np.ndarray, axes: np.ndarray) -> float:
    """Fraction of surface samples inside some splat: within half its largest semi-axis of its
    plane, and inside its ellipse in the plane (u^2 + v^2 <= 1). Candidates: the 24 nearest
    splat centres (a miss among them only lowers the measured coverage)."""
    axes = axes.astype(np.float64)
    length2 = np.einsum("ntj,ntj->nt", axes, axes)
    _, cand = cKDTree(centres).query(surface, 24)
    d = surface[:, None] - centres[cand]
    u = np.einsum("skj,skj->sk", d, axes[cand, 0]) / length2[cand, 0]
    v = np.einsum("skj,skj->sk", d, axes[cand, 1]) / length2[cand, 1]
    height = np.abs(np.einsum("skj,skj->sk", d, normals[cand].astype(np.float64)))
    inside = (u * u + v * v <= 1) & (height <= 0.5 * np.sqrt(length2[cand].max(axis=2)))
    return float(inside.any(axis=1).mean())


def nn_spacing(points: np.ndarray) -> float:
    return float(cKDTree(points).query(points, 2)[0][:, 1].mean())


def scan_lines(rng, angle: float, line: float, along: float, half: float = 25.0) -> np.ndarray:
    """An aerial-LiDAR-like strip: noisy scan lines `line` apart, `along` spacing on a line."""
    rows = []
    y = -half
    while y < half:
        x = np.arange(-half, half, along) + rng.uniform(-0.35, 0.35) * along
        x = x + rng.normal(0, 0.15 * along, len(x))
        rows.append(np.c_[x, y + rng.normal(0, 0.08 * line, len(x)) + 0.003 * rng.normal() * x])
        y += line * rng.uniform(0.7, 1.3)
    c, s = np.cos(angle), np.sin(angle)
    return np.concatenate(rows) @ np.array([[c, s], [-s, c]])


def capped_cylinder(around: int = 12):
    """A flat cap on a cylinder of radius 1, sampled as a CAD part's mesh is: the side in rings
    of `around` vertices a step 2 pi / around apart (normals turning that much from vertex to
    vertex, so that no point there is flat), the cap on a grid of half that step, and the rim
    with normals averaged over cap and side. Returns (side, cap, rim, normals), the normals of
    side, cap and rim in that order."""
    step = 2 * np.pi / around
    angles = step * np.arange(around)
    rim = np.stack([np.cos(angles), np.sin(angles), np.zeros(around)], 1)
    side = np.concatenate([rim - [0, 0, k * step] for k in range(1, 8)])
    grid = np.arange(-1, 1 + 1e-9, step / 2)
    x, y = (values.ravel() for values in np.meshgrid(grid, grid))
    inside = np.hypot(x, y) < 1 - step / 4
    cap = np.stack([x[inside], y[inside], np.zeros(inside.sum())], 1)
    normals = np.concatenate([side * [1, 1, 0], np.tile([0.0, 0, 1], (len(cap), 1)), unit(rim + [0, 0, 1])])
    return side, cap, rim, normals


def edge_wedge(h: float = 0.05):
    """Two faces meeting at a 90 degree convex edge along y (the solid is x <= 0, z <= 0): face A
    (z = 0, x <= 0, normal +z) and face B (x = 0, z <= 0, normal +x), sampled on a jittered grid
    of spacing h; the edge points carry the averaged normal, as a mesh's vertices do."""
    rng = np.random.default_rng(3)
    s = np.arange(0, 1 + 1e-9, h)
    a, y = np.meshgrid(-s, s, indexing="ij")

    def jitter(shape):
        return rng.uniform(-0.2 * h, 0.2 * h, shape)

    face_a = np.stack([a[1:].ravel() + jitter(a[1:].size), y[1:].ravel() + jitter(a[1:].size), np.zeros(a[1:].size)], 1)
    face_b = np.stack([np.zeros(a[1:].size), y[1:].ravel() + jitter(a[1:].size), a[1:].ravel() + jitter(a[1:].size)], 1)
    edge = np.stack([np.zeros(len(s)), s, np.zeros(len(s))], 1)
    normals = np.concatenate([np.tile([0.0, 0, 1], (len(face_a), 1)), np.tile([1.0, 0, 0], (len(face_b), 1)),
                              np.tile(unit(np.array([1.0, 0, 1])), (len(edge), 1))])
    labels = np.repeat([0, 1, 2], [len(face_a), len(face_b), len(edge)])
    return PointCloud(np.concatenate([face_a, face_b, edge]), normals=normals), labels


def covered_by(cloud: PointCloud, members: np.ndarray, samples: np.ndarray) -> np.ndarray:
    """Whether each sample point (lying in the members' common plane) is inside one of their
    clipped splats: within the ellipse and on the kept side of both clip lines."""
    c, axes = cloud.positions[members], cloud.axes[members].astype(np.float64)
    lines = cloud.attributes["clip_lines"][members]
    d = samples[:, None, :] - c[None]
    u = np.einsum("skj,kj->sk", d, axes[:, 0]) / np.einsum("kj,kj->k", axes[:, 0], axes[:, 0])
    v = np.einsum("skj,kj->sk", d, axes[:, 1]) / np.einsum("kj,kj->k", axes[:, 1], axes[:, 1])
    inside = u * u + v * v <= 1
    for line in range(lines.shape[1]):
        inside &= lines[None, :, line, 0] * u + lines[None, :, line, 1] * v <= lines[None, :, line, 2]
    return inside.any(axis=1)
