import math

import numpy as np
import pytest

from surfel.camera import Camera, frame, look_at, view_direction
from surfel.errors import SurfelError


def test_look_at_maps_target_to_negative_z():
    m = look_at([1, 2, 3], [1, 2, 0], [0, 1, 0])
    p = m @ np.array([1, 2, 0, 1.0])
    assert np.allclose(p[:3], [0, 0, -3])


def test_projection_matrix_matches_project():
    rng = np.random.default_rng(1)
    cam = Camera.look_at([0.3, 0.2, 5], [0, 0, 0], [0, 1, 0], fov=40, size=(320, 200)).fit_clip_planes([0, 0, 0], 1.5)
    pts = rng.uniform(-1, 1, size=(50, 3))
    xy, depth = cam.project(pts)
    clip = (cam.projection_matrix() @ cam.view_matrix() @ np.c_[pts, np.ones(50)].T).T
    ndc = clip[:, :3] / clip[:, 3:]
    x = (ndc[:, 0] + 1) / 2 * cam.width
    y = (1 - ndc[:, 1]) / 2 * cam.height  # image rows go top to bottom
    assert np.allclose(np.c_[x, y], xy)
    assert np.all(np.abs(ndc[:, 2]) < 1)


def test_opencv_round_trip_and_projection_agree():
    K = np.array([[500.0, 0, 310.5], [0, 480.0, 245.25], [0, 0, 1]])
    angle = 0.3
    R = np.array([[math.cos(angle), 0, math.sin(angle)], [0, 1, 0], [-math.sin(angle), 0, math.cos(angle)]])
    t = np.array([0.1, -0.2, 4.0])
    cam = Camera.from_opencv(K, R, t, (640, 480))
    K2, R2, t2 = cam.to_opencv()
    assert np.allclose(K, K2) and np.allclose(R, R2) and np.allclose(t, t2)
    pts = np.random.default_rng(2).uniform(-1, 1, (20, 3))
    cv = (R @ pts.T).T + t
    uv = (K @ (cv / cv[:, 2:]).T).T[:, :2]
    xy, depth = cam.project(pts)
    assert np.allclose(xy - 0.5, uv)  # OpenCV puts pixel centres on integers
    assert np.allclose(depth, cv[:, 2])


def test_auto_framing_distance_and_views():
    cam = frame([1, 2, 3], 2.0, fov=30, size=(100, 100))
    assert np.isclose(np.linalg.norm(cam.eye - [1, 2, 3]), 1.1 * 2.0 / math.sin(math.radians(15)))
    assert np.allclose(cam.forward, [0, 0, -1])  # front of +Y-up data: camera on +Z
    geo = frame([0, 0, 0], 1.0, geospatial=True)
    assert geo.eye[1] < 0 and abs(geo.eye[0]) < 1e-9  # front of +Z-up data: camera on -Y
    right, _ = view_direction("right", [0, 1, 0])
    assert np.allclose(right, [1, 0, 0])
    top, up = view_direction("top", [0, 0, 1])
    assert np.allclose(top, [0, 0, 1]) and np.allclose(up, [0, 1, 0])
    with pytest.raises(SurfelError):
        view_direction("sideways", [0, 1, 0])


def test_rays_pass_through_projected_points():
    cam = Camera.look_at([0, 0, 4], [0, 0, 0], [0, 1, 0], fov=35, size=(64, 48))
    origins, dirs = cam.rays()
    i, j = 10, 50
    p_eye = origins[i, j] + 3.0 * dirs[i, j]
    world = np.linalg.inv(cam.world_to_eye) @ np.append(p_eye, 1)
    xy, _ = cam.project(world[None, :3])
    assert np.allclose(xy[0], [j + 0.5, i + 0.5])


def test_orthographic_projection():
    cam = Camera.look_at([0, 0, 5], [0, 0, 0], [0, 1, 0], size=(200, 100), ortho_height=2.0)
    xy, depth = cam.project(np.array([[1.0, 0.5, 0.0]]))
    assert np.allclose(xy, [[100 + 50, 50 - 25]]) and np.allclose(depth, 5)
