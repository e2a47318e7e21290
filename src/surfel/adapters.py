"""Conversions between PointCloud and the libraries our users bring; each imported only when used.

numpy : from_numpy(positions, normals=None, colors=None, radii=None) / to_numpy(cloud) -> dict
Open3D: from_open3d(o3d.geometry.PointCloud | TriangleMesh) / to_open3d(cloud)
trimesh: from_trimesh(trimesh.Trimesh | trimesh.PointCloud) / to_trimesh(cloud)
PyVista: from_pyvista(pv.PolyData) / to_pyvista(cloud)
"""

from __future__ import annotations

import numpy as np

from .cloud import PointCloud


def from_numpy(positions, normals=None, colors=None, radii=None, **kwargs) -> PointCloud:
    colors = None if colors is None else np.asarray(colors)
    if colors is not None and colors.dtype == np.uint8:
        colors = colors.astype(np.float32) / 255
    return PointCloud(positions, normals=normals, colors=colors, radii=radii, **kwargs)


def to_numpy(cloud: PointCloud) -> dict[str, np.ndarray]:
    names = ("positions", "normals", "colors", "radii", "axes", "faces")
    out = {name: getattr(cloud, name) for name in names if getattr(cloud, name) is not None}
    return {**out, **cloud.attributes}


def _mesh_cloud(vertices, faces, normals=None, colors=None, source=None) -> PointCloud:
    from .io.mesh import area_weighted_vertex_normals, referenced_vertices

    vertices, faces = np.asarray(vertices, np.float64), np.asarray(faces, np.int64)
    keep, faces = referenced_vertices(faces, len(vertices))
    vertices = vertices[keep]
    colors = None if colors is None else np.asarray(colors)[keep]
    normals = area_weighted_vertex_normals(vertices, faces) if normals is None else np.asarray(normals)[keep]
    return PointCloud(vertices, normals=normals, colors=colors, faces=faces, source=source)


def from_open3d(geometry) -> PointCloud:
    points = np.asarray(geometry.vertices if hasattr(geometry, "triangles") else geometry.points)
    if hasattr(geometry, "triangles") and len(geometry.triangles):
        colors = np.asarray(geometry.vertex_colors) if geometry.has_vertex_colors() else None
        return _mesh_cloud(points, np.asarray(geometry.triangles), colors=colors, source="open3d")
    normals = np.asarray(geometry.normals) if geometry.has_normals() else None
    colors = np.asarray(geometry.colors) if geometry.has_colors() else None
    return PointCloud(points, normals=normals, colors=colors, source="open3d")


def to_open3d(cloud: PointCloud):
    import open3d as o3d

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(cloud.positions))
    if cloud.normals is not None:
        pcd.normals = o3d.utility.Vector3dVector(cloud.normals.astype(np.float64))
    if cloud.colors is not None:
        pcd.colors = o3d.utility.Vector3dVector(cloud.colors.astype(np.float64))
    return pcd


def from_trimesh(geometry) -> PointCloud:
    colors = None
    visual = getattr(geometry, "visual", None)
    if visual is not None and getattr(visual, "kind", None) == "vertex":
        colors = np.asarray(visual.vertex_colors)[:, :3].astype(np.float32) / 255
    if hasattr(geometry, "faces") and len(geometry.faces):
        return _mesh_cloud(geometry.vertices, geometry.faces, colors=colors, source="trimesh")
    if colors is None and getattr(geometry, "colors", None) is not None and len(geometry.colors):
        colors = np.asarray(geometry.colors)[:, :3].astype(np.float32) / 255
    return PointCloud(np.asarray(geometry.vertices), colors=colors, source="trimesh")


def to_trimesh(cloud: PointCloud):
    import trimesh

    colors = None if cloud.colors is None else np.round(cloud.colors * 255).astype(np.uint8)
    if cloud.is_mesh:
        return trimesh.Trimesh(cloud.positions, cloud.faces, vertex_colors=colors, process=False)
    return trimesh.PointCloud(cloud.positions, colors=colors)


def from_pyvista(polydata) -> PointCloud:
    points = np.asarray(polydata.points)
    normals = polydata.point_data.get("Normals")
    colors = polydata.point_data.get("RGB")
    if colors is not None and np.asarray(colors).dtype == np.uint8:
        colors = np.asarray(colors, np.float32)[:, :3] / 255
    if polydata.faces.size and polydata.is_all_triangles:
        faces = np.asarray(polydata.faces).reshape(-1, 4)[:, 1:]
        return _mesh_cloud(points, faces, normals=normals, colors=colors, source="pyvista")
    return PointCloud(points, normals=normals, colors=colors, source="pyvista")


def to_pyvista(cloud: PointCloud):
    import pyvista as pv

    if cloud.is_mesh:
        faces = np.hstack([np.full((len(cloud.faces), 1), 3), cloud.faces]).ravel()
        data = pv.PolyData(cloud.positions, faces)
    else:
        data = pv.PolyData(cloud.positions)
    if cloud.normals is not None:
        data.point_data["Normals"] = cloud.normals
    if cloud.colors is not None:
        data.point_data["RGB"] = np.round(cloud.colors * 255).astype(np.uint8)
    return data
