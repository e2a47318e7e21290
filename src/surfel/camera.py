"""Cameras: OpenGL look-at with a vertical field of view, OpenCV pinhole (K, R, t), orthographic.

One representation serves all of them (docs/conventions.md, "Coordinates and camera"):

* `world_to_eye`: 4x4 float64 rigid transform into OpenGL eye space (x right, y up,
  looking down -z).
* Intrinsics `fx, fy, cx, cy` in pixels, in *continuous* image coordinates: the image's
  top-left corner is (0, 0) and the centre of pixel (row i, column j) is (j + 0.5, i + 0.5).
  OpenCV puts pixel centres on integers, so its cx, cy are 0.5 smaller.
* `ortho_height`: if set, an orthographic camera whose view is that many world units tall.

A point at eye coordinates (X, Y, Z), Z < 0, lands on image position
    x = cx + fx * X / -Z,     y = cy - fy * Y / -Z      (y grows downwards).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from .errors import SurfelError

VIEWS = ("front", "back", "left", "right", "top", "bottom", "iso")
EXTENT_MARGIN = 0.05  # geospatial framing: the projected bounding box leaves this fraction of the image each side
AUTO = "auto"  # ortho_height: fit the view to the data like auto-framing


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    n = np.linalg.norm(v)
    if n == 0 or not np.isfinite(n):
        raise SurfelError(f"cannot normalise vector {v.tolist()}")
    return v / n


def image_size(size) -> tuple[int, int]:
    """(width, height) as ints, or a one-line SurfelError for anything else (a "WxH" string,
    a fraction of a pixel)."""
    try:
        w, h = size
        if isinstance(w, str) or isinstance(h, str) or int(w) != w or int(h) != h:
            raise ValueError
    except (TypeError, ValueError):
        raise SurfelError(f"image size must be two whole numbers (width, height), got {size!r}") from None
    return int(w), int(h)


def look_at(eye, target, up) -> np.ndarray:
    """The OpenGL world-to-eye matrix (gluLookAt), float64."""
    eye = np.asarray(eye, np.float64)
    f = _unit(np.asarray(target, np.float64) - eye)
    s = np.cross(f, _unit(up))
    if np.linalg.norm(s) < 1e-9:
        raise SurfelError("camera up vector is parallel to the viewing direction")
    s = _unit(s)
    u = np.cross(s, f)
    m = np.eye(4)
    m[0, :3], m[1, :3], m[2, :3] = s, u, -f
    m[:3, 3] = -m[:3, :3] @ eye
    return m


@dataclass(frozen=True, eq=False)
class Camera:
    world_to_eye: np.ndarray
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    ortho_height: float | None = None
    near: float = 0.01
    far: float = 100.0

    # ---- construction -------------------------------------------------------------
    @classmethod
    def look_at(cls, eye, target, up=(0, 1, 0), *, fov: float = 30.0, size=(1024, 1024),
                ortho_height: float | None = None, near: float = 0.01, far: float = 100.0) -> Camera:
        """A look-at camera with vertical field of view `fov` degrees and `size` = (W, H)."""
        w, h = image_size(size)
        if w <= 0 or h <= 0:
            raise SurfelError(f"image size must be positive, got {w}x{h}")
        if not 0 < fov < 180:
            raise SurfelError(f"field of view must be in (0, 180) degrees, got {fov}")
        focal = (h / 2) / math.tan(math.radians(fov) / 2)
        return cls(look_at(eye, target, up), w, h, focal, focal, w / 2, h / 2,
                   ortho_height=ortho_height, near=near, far=far)

    @classmethod
    def from_opencv(cls, K, R, t, size, *, near: float = 0.01, far: float = 100.0) -> Camera:
        """From OpenCV intrinsics K (3x3) and world-to-camera extrinsics x_cam = R x_world + t."""
        K = np.asarray(K, np.float64)
        cv_to_gl = np.diag([1.0, -1.0, -1.0])  # OpenCV: y down, z forward
        m = np.eye(4)
        m[:3, :3] = cv_to_gl @ np.asarray(R, np.float64)
        m[:3, 3] = cv_to_gl @ np.asarray(t, np.float64).reshape(3)
        return cls(m, int(size[0]), int(size[1]), K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5,
                   near=near, far=far)

    def to_opencv(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(K, R, t) such that from_opencv(K, R, t, size) reproduces this camera."""
        if self.ortho_height is not None:
            raise SurfelError("an orthographic camera has no pinhole intrinsics")
        cv_to_gl = np.diag([1.0, -1.0, -1.0])
        K = np.array([[self.fx, 0, self.cx - 0.5], [0, self.fy, self.cy - 0.5], [0, 0, 1]])
        return K, cv_to_gl @ self.world_to_eye[:3, :3], cv_to_gl @ self.world_to_eye[:3, 3]

    def with_(self, **changes) -> Camera:
        return replace(self, **changes)

    def supersampled(self, factor: int) -> Camera:
        """The same view on a render target `factor` times larger per side (supersampling)."""
        if factor == 1:
            return self
        return replace(self, width=self.width * factor, height=self.height * factor, fx=self.fx * factor,
                       fy=self.fy * factor, cx=self.cx * factor, cy=self.cy * factor)

    def scaled(self, factor: float) -> Camera:
        """The same view of a world whose lengths are multiplied by `factor` (PointCloud.scaled):
        the same image, eye depths times `factor`."""
        m = self.world_to_eye.copy()
        m[:3, 3] *= factor
        return replace(self, world_to_eye=m, near=self.near * factor, far=self.far * factor,
                       ortho_height=None if self.ortho_height is None else self.ortho_height * factor)

    # ---- derived quantities ---------------------------------------------------------
    @property
    def size(self) -> tuple[int, int]:
        return self.width, self.height

    @property
    def eye(self) -> np.ndarray:
        r, t = self.world_to_eye[:3, :3], self.world_to_eye[:3, 3]
        return -r.T @ t

    @property
    def forward(self) -> np.ndarray:
        """Unit viewing axis in world coordinates."""
        return -self.world_to_eye[2, :3]

    @property
    def fov(self) -> float:
        return math.degrees(2 * math.atan((self.height / 2) / self.fy))

    def view_matrix(self, origin=None) -> np.ndarray:
        """World-to-eye for positions given relative to `origin` (float64 math, then float32)."""
        m = self.world_to_eye.copy()
        if origin is not None:
            m[:3, 3] += m[:3, :3] @ np.asarray(origin, np.float64)
        return m

    def projection_matrix(self) -> np.ndarray:
        """OpenGL clip-from-eye matrix reproducing the intrinsics; rows flip on readback."""
        n, f, w, h = self.near, self.far, self.width, self.height
        p = np.zeros((4, 4))
        if self.ortho_height is not None:
            oh = self.ortho_height
            ow = oh * w / h
            p[0, 0], p[1, 1] = 2 / ow, 2 / oh
            p[0, 3] = 1 - 2 * self.cx / w
            p[1, 3] = 2 * self.cy / h - 1
            p[2, 2], p[2, 3] = -2 / (f - n), -(f + n) / (f - n)
            p[3, 3] = 1
        else:
            p[0, 0], p[0, 2] = 2 * self.fx / w, 1 - 2 * self.cx / w
            p[1, 1], p[1, 2] = 2 * self.fy / h, 2 * self.cy / h - 1
            p[2, 2], p[2, 3] = -(f + n) / (f - n), -2 * f * n / (f - n)
            p[3, 2] = -1
        return p

    def pixel_scale(self) -> float:
        """Pixels per world unit at eye depth 1 (perspective) or everywhere (orthographic)."""
        if self.ortho_height is not None:
            return self.height / self.ortho_height
        return self.fy

    def project(self, points, origin=None) -> tuple[np.ndarray, np.ndarray]:
        """Image positions (N, 2) in continuous pixel coordinates and eye depths (N,)."""
        m = self.view_matrix(origin)
        p = np.asarray(points, np.float64) @ m[:3, :3].T + m[:3, 3]
        depth = -p[:, 2]
        if self.ortho_height is not None:
            s = self.height / self.ortho_height
            x, y = self.cx + s * p[:, 0], self.cy - s * p[:, 1]
        else:
            x = self.cx + self.fx * p[:, 0] / depth
            y = self.cy - self.fy * p[:, 1] / depth
        return np.stack([x, y], axis=1), depth

    def rays(self, origin=None) -> tuple[np.ndarray, np.ndarray]:
        """Per-pixel ray origins and unit directions in eye space, each (H, W, 3) float64.

        Rays go through pixel centres; `origin` is unused in eye space but kept symmetric
        with `view_matrix` for callers that transform rays to world space themselves.
        """
        rows, cols = np.divmod(np.arange(self.width * self.height), self.width)
        o, d = self.rays_at(rows, cols)
        return o.reshape(self.height, self.width, 3), d.reshape(self.height, self.width, 3)

    def rays_at(self, rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Eye-space ray origins and unit directions, each (N, 3) float64, through the centres
        of the pixels (rows[k], cols[k])."""
        j, i = np.asarray(cols) + 0.5, np.asarray(rows) + 0.5
        if self.ortho_height is not None:
            s = self.ortho_height / self.height
            o = np.stack([(j - self.cx) * s, (self.cy - i) * s, np.zeros_like(j)], axis=-1)
            d = np.broadcast_to(np.array([0.0, 0.0, -1.0]), o.shape).copy()
            return o, d
        d = np.stack([(j - self.cx) / self.fx, (self.cy - i) / self.fy, -np.ones_like(j)], axis=-1)
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        return np.zeros_like(d), d

    def fit_clip_planes(self, center, radius: float) -> Camera:
        """Near/far planes bracketing a bounding sphere (they change no output, only precision)."""
        d = float(-(self.view_matrix() @ np.append(np.asarray(center, np.float64), 1.0))[2])
        # relative to the scene's own scale, which may be anything from 1e-10 to 1e18
        far = max(d + radius * 1.05, 1e-6 * max(radius, abs(d)))
        near = max(d - radius * 1.05, far * 1e-4)
        if self.ortho_height is not None:
            near = d - radius * 1.05  # may be negative: orthographic needs no positive near
        return replace(self, near=near, far=far)


@dataclass(frozen=True)
class OpenCvCamera:
    """A pinhole camera from an OpenCV JSON file {"K": 3x3, "R": 3x3, "t": 3}, checked."""

    path: str
    K: np.ndarray
    R: np.ndarray
    t: np.ndarray

    @classmethod
    def read(cls, path: str) -> OpenCvCamera:
        try:
            spec = json.loads(Path(path).read_text())
            K, R, t = (np.array(spec[key], float) for key in ("K", "R", "t"))
        except (OSError, UnicodeDecodeError, ValueError, KeyError, TypeError) as exc:
            reason = getattr(exc, "strerror", None) or f"{type(exc).__name__}: {exc}"
            raise SurfelError(f"{path}: not an OpenCV camera JSON with K, R, t ({reason})") from None
        problem = cls.problem(K, R, t)
        if problem:
            raise SurfelError(f"{path}: {problem}")
        return cls(path, K, R, t.reshape(3))

    @staticmethod
    def problem(K: np.ndarray, R: np.ndarray, t: np.ndarray) -> str | None:
        for name, array, shape in (("K", K, (3, 3)), ("R", R, (3, 3)), ("t", t, (3,))):
            if array.shape != shape and not (name == "t" and array.size == 3):
                return f"{name} must be {'x'.join(map(str, shape))}, got shape {array.shape}"
            if not np.isfinite(array).all():
                return f"{name} holds values that are not finite numbers"
        if not np.array_equal(K[2], [0.0, 0.0, 1.0]) or K[1, 0] != 0 or K[0, 1] != 0:
            return "K must be a pinhole matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]"
        if not (K[0, 0] > 0 and K[1, 1] > 0):
            return f"K's focal lengths must be positive, got fx={K[0, 0]:g}, fy={K[1, 1]:g}"
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-4) or np.linalg.det(R) <= 0:
            return "R must be a rotation (orthonormal, determinant 1)"
        return None


def default_up(geospatial: bool) -> np.ndarray:
    """+Z for geospatial data (LAS/LAZ), +Y otherwise."""
    return np.array([0.0, 0.0, 1.0]) if geospatial else np.array([0.0, 1.0, 0.0])


def view_direction(view: str | None, up, azimuth: float | None = None, elevation: float | None = None):
    """Unit vector from the target to the eye, and the camera up vector, for a named view.

    `front` puts the camera on +Z for +Y-up data and on -Y for +Z-up data; azimuth turns
    from front towards right about the up axis, elevation lifts towards up.
    """
    up = _unit(up)
    axes = np.eye(3)
    k = int(np.argmax(np.abs(up)))
    # front: +Z for Y-up, -Y for Z-up; in general the axis after the up axis, signed so
    # that right = up x front comes out as +X for both conventions.
    front = {0: axes[1], 1: axes[2], 2: -axes[1]}[k] * (1 if up[k] > 0 else -1)
    front = _unit(front - np.dot(front, up) * up)
    right = np.cross(up, front)
    named = {"front": (0, 0), "back": (180, 0), "right": (90, 0), "left": (-90, 0),
             "top": (0, 90), "bottom": (0, -90), "iso": (45, math.degrees(math.atan(1 / math.sqrt(2))))}
    if azimuth is None and elevation is None:
        view = view or "front"
        if view not in named:
            raise SurfelError(f"unknown view {view!r}; choose one of {', '.join(VIEWS)}")
        azimuth, elevation = named[view]
    az, el = math.radians(azimuth or 0.0), math.radians(elevation or 0.0)
    direction = math.cos(el) * (math.cos(az) * front + math.sin(az) * right) + math.sin(el) * up
    cam_up = up
    if abs(math.cos(el)) < 1e-6:  # looking straight down or up: image up is away from front
        cam_up = -math.copysign(1.0, math.sin(el)) * (math.cos(az) * front + math.sin(az) * right)
    return _unit(direction), cam_up


def _view_axes(direction, cam_up) -> tuple[np.ndarray, np.ndarray]:
    """The image's right and up axes of a camera looking along -direction."""
    right = _unit(np.cross(-np.asarray(direction, np.float64), cam_up))
    return right, np.cross(right, -np.asarray(direction, np.float64))


def _corners(bounds) -> np.ndarray:
    lo, hi = (np.asarray(b, np.float64) for b in bounds)
    return np.array([[(hi if i & 1 else lo)[0], (hi if i & 2 else lo)[1], (hi if i & 4 else lo)[2]] for i in range(8)])


def extent_distance(bounds, target, direction, cam_up, fov: float, size) -> float:
    """The distance from `target` along `direction` at which the bounding box's corners,
    projected, fill the image with EXTENT_MARGIN each side: for a corner at (x, y) across the
    view and z towards the eye, |x| / (d - z) <= t_x and |y| / (d - z) <= t_y, with
    t_y = (1 - 2 margin) tan(fov / 2), t_x = t_y W / H."""
    right, image_up = _view_axes(direction, cam_up)
    relative = _corners(bounds) - np.asarray(target, np.float64)
    x, y, z = relative @ right, relative @ image_up, relative @ np.asarray(direction, np.float64)
    t_y = (1 - 2 * EXTENT_MARGIN) * math.tan(math.radians(fov) / 2)
    t_x = t_y * size[0] / size[1]
    return float(np.max(z + np.maximum(np.abs(x) / t_x, np.abs(y) / t_y)))


def extent_height(bounds, eye, target, cam_up, size) -> float:
    """The orthographic view height at which the bounding box, projected along eye -> target
    about the target, fills the image with EXTENT_MARGIN each side."""
    direction = _unit(np.asarray(eye, np.float64) - np.asarray(target, np.float64))
    right, image_up = _view_axes(direction, cam_up)
    relative = _corners(bounds) - np.asarray(target, np.float64)
    half = max(float(np.abs(relative @ image_up).max()), float(np.abs(relative @ right).max()) * size[1] / size[0])
    return max(2 * half / (1 - 2 * EXTENT_MARGIN), 1e-9)


def frame(center, radius: float, *, view: str | None = "front", azimuth=None, elevation=None,
          up=None, geospatial: bool = False, fov: float = 30.0, size=(1024, 1024),
          eye=None, target=None, ortho_height: float | str | None = None, zoom: float = 1.0,
          bounds=None) -> Camera:
    """The camera of docs/conventions.md: explicit eye/target, or auto framing.

    Auto framing looks at the target (default `center`) along the view direction from 1.1x
    the distance at which the bounding sphere just fills the vertical field of view; for
    geospatial data whose `bounds` (lo, hi) are given, from the distance at which the
    bounding box's projection fills the image with a margin (`extent_distance`): a long tile
    seen from the top fills the image's width. Either distance is multiplied by `zoom` (used
    by benchmarks to move the camera away). `ortho_height` "auto": the orthographic height
    that fits the projected box (the bounding sphere's box without `bounds`) likewise, times
    `zoom`. Explicit eye and target are never changed.
    """
    default = up is None
    up = default_up(geospatial) if default else _unit(up)
    target = np.asarray(center if target is None else target, np.float64)
    cam_up = up
    if eye is None:
        direction, cam_up = view_direction(view, up, azimuth, elevation)
        if geospatial and bounds is not None:
            distance = extent_distance(bounds, target, direction, cam_up, fov, size) * zoom
        else:
            distance = 1.1 * radius / math.sin(math.radians(fov) / 2) * zoom
        eye = target + direction * distance
    elif default and abs(np.dot(_unit(target - np.asarray(eye, np.float64)), up)) > 1 - 1e-9:
        cam_up = view_direction("top", up)[1]  # looking along the default up axis: image up is away from front
    if ortho_height == AUTO:
        box = bounds if bounds is not None else (np.asarray(center) - radius, np.asarray(center) + radius)
        ortho_height = extent_height(box, eye, target, cam_up, size) * zoom
    cam = Camera.look_at(eye, target, cam_up, fov=fov, size=size, ortho_height=ortho_height)
    return cam.fit_clip_planes(center, radius)
