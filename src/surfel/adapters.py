"""Conversions between PointCloud and the libraries our users bring; each imported only when used.

numpy : from_numpy(positions, normals=None, colors=None, radii=None, **fields) / to_numpy(cloud) -> dict,
        so that from_numpy(**to_numpy(cloud)) gives the cloud back
Open3D: from_open3d(o3d.geometry.PointCloud | TriangleMesh | o3d.t.geometry.PointCloud) / to_open3d(cloud)
trimesh: from_trimesh(trimesh.Trimesh | trimesh.PointCloud) / to_trimesh(cloud)
PyVista: from_pyvista(pv.PolyData) / to_pyvista(cloud)

Attributes (surfel.attributes) go where each library keeps per-point data: to_numpy's
"attributes" (with their kinds under "kinds"), trimesh's vertex_attributes (a Trimesh) or
metadata["vertex_attributes"] (a PointCloud, which has no per-vertex store), PyVista's
point_data (arrays of more than two dimensions flattened to (N, k), float16 as float32, both
restored from the schema), and Open3D's tensor point
clouds (`to_open3d(cloud, tensor=True)`: the legacy o3d.geometry.PointCloud holds no
attributes). Kinds travel in trimesh's metadata["attribute_kinds"] and, with the whole schema,
in PyVista's field_data["surfel_schema"]; from Open3D they are resolved again
(surfel.attributes.resolve_kind).
"""

from __future__ import annotations

import numpy as np

from .attributes import Schema
from .cloud import PointCloud

_KINDS_KEY = "attribute_kinds"
_SCHEMA_KEY = "surfel_schema"


def from_numpy(positions, normals=None, colors=None, radii=None, **fields) -> PointCloud:
    """A cloud from arrays; `fields` as PointCloud takes them (axes, attributes, kinds, ...)."""
    colors = None if colors is None else np.asarray(colors)
    if colors is not None and colors.dtype == np.uint8:
        colors = colors.astype(np.float32) / 255
    return PointCloud(positions, normals=normals, colors=colors, radii=radii, **fields)


def to_numpy(cloud: PointCloud) -> dict:
    """The cloud's arrays by field name (those it has), "attributes" (name -> array) and
    "kinds" (name -> kind)."""
    names = ("positions", "normals", "colors", "radii", "axes", "faces")
    out = {name: getattr(cloud, name) for name in names if getattr(cloud, name) is not None}
    return {**out, "attributes": dict(cloud.attributes), "kinds": cloud.schema.kinds}


def _mesh_cloud(vertices, faces, normals=None, colors=None, attributes=None, kinds=None, source=None) -> PointCloud:
    from .io.mesh import mesh_normals, referenced_vertices

    vertices, faces = np.asarray(vertices, np.float64), np.asarray(faces, np.int64)
    keep, faces = referenced_vertices(faces, len(vertices))
    vertices = vertices[keep]
    colors = None if colors is None else np.asarray(colors)[keep]
    normals = mesh_normals(vertices, faces) if normals is None else np.asarray(normals)[keep]
    attributes = {name: np.asarray(values)[keep] for name, values in (attributes or {}).items()}
    return PointCloud(vertices, normals=normals, colors=colors, faces=faces, attributes=attributes,
                      kinds=kinds or {}, source=source)


def from_open3d(geometry) -> PointCloud:
    if hasattr(geometry, "point"):  # a tensor point cloud (o3d.t.geometry.PointCloud)
        arrays = {name: geometry.point[name].numpy() for name in geometry.point}
        normals, colors = arrays.pop("normals", None), arrays.pop("colors", None)
        return PointCloud(arrays.pop("positions"), normals=normals, colors=colors, attributes=arrays,
                          source="open3d")
    points = np.asarray(geometry.vertices if hasattr(geometry, "triangles") else geometry.points)
    if hasattr(geometry, "triangles") and len(geometry.triangles):
        colors = np.asarray(geometry.vertex_colors) if geometry.has_vertex_colors() else None
        return _mesh_cloud(points, np.asarray(geometry.triangles), colors=colors, source="open3d")
    normals = np.asarray(geometry.normals) if geometry.has_normals() else None
    colors = np.asarray(geometry.colors) if geometry.has_colors() else None
    return PointCloud(points, normals=normals, colors=colors, source="open3d")


def to_open3d(cloud: PointCloud, *, tensor: bool = False):
    """An o3d.geometry.PointCloud, or with `tensor` an o3d.t.geometry.PointCloud that also
    holds the attributes."""
    import open3d as o3d

    if tensor:
        pcd = o3d.t.geometry.PointCloud(o3d.core.Tensor(cloud.positions))
        for name, values in (("normals", cloud.normals), ("colors", cloud.colors), *cloud.attributes.items()):
            if values is not None:
                pcd.point[name] = o3d.core.Tensor(np.ascontiguousarray(values))
        return pcd
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(cloud.positions))
    if cloud.normals is not None:
        pcd.normals = o3d.utility.Vector3dVector(cloud.normals.astype(np.float64))
    if cloud.colors is not None:
        pcd.colors = o3d.utility.Vector3dVector(cloud.colors.astype(np.float64))
    return pcd


def from_trimesh(geometry) -> PointCloud:
    colors = None
    visual = getattr(geometry, "visual", None)
    if visual is not None and getattr(visual, "kind", None) == "vertex" and len(visual.vertex_colors):
        colors = np.asarray(visual.vertex_colors)[:, :3].astype(np.float32) / 255
    metadata = getattr(geometry, "metadata", None) or {}
    kinds = metadata.get(_KINDS_KEY, {})
    if hasattr(geometry, "faces") and len(geometry.faces):
        return _mesh_cloud(geometry.vertices, geometry.faces, colors=colors,
                           attributes=dict(geometry.vertex_attributes), kinds=kinds, source="trimesh")
    if colors is None and getattr(geometry, "colors", None) is not None and len(geometry.colors):
        colors = np.asarray(geometry.colors)[:, :3].astype(np.float32) / 255
    return PointCloud(np.asarray(geometry.vertices), colors=colors, attributes=metadata.get("vertex_attributes", {}),
                      kinds=kinds, source="trimesh")


def to_trimesh(cloud: PointCloud):
    import trimesh

    colors = None if cloud.colors is None else np.round(cloud.colors * 255).astype(np.uint8)
    metadata = {_KINDS_KEY: cloud.schema.kinds}
    if cloud.is_mesh:
        return trimesh.Trimesh(cloud.positions, cloud.faces, vertex_colors=colors, process=False,
                               vertex_attributes=dict(cloud.attributes), metadata=metadata)
    return trimesh.PointCloud(cloud.positions, colors=colors,
                              metadata={**metadata, "vertex_attributes": dict(cloud.attributes)})


def from_pyvista(polydata) -> PointCloud:
    points = np.asarray(polydata.points)
    normals = polydata.point_data.get("Normals")
    colors = polydata.point_data.get("RGB")
    if colors is not None and np.asarray(colors).dtype == np.uint8:
        colors = np.asarray(colors, np.float32)[:, :3] / 255
    attributes = {name: np.asarray(polydata.point_data[name]) for name in polydata.point_data.keys()
                  if name not in ("Normals", "RGB")}
    kinds = {}
    if _SCHEMA_KEY in polydata.field_data.keys():
        schema = Schema.from_json(str(np.asarray(polydata.field_data[_SCHEMA_KEY]).ravel()[0]))
        kinds = schema.kinds
        attributes = {name: values.reshape(len(values), *schema[name].shape).astype(schema[name].dtype)
                      if name in schema else values for name, values in attributes.items()}
    if polydata.faces.size and polydata.is_all_triangles:
        faces = np.asarray(polydata.faces).reshape(-1, 4)[:, 1:]
        return _mesh_cloud(points, faces, normals=normals, colors=colors, attributes=attributes, kinds=kinds,
                           source="pyvista")
    return PointCloud(points, normals=normals, colors=colors, attributes=attributes, kinds=kinds, source="pyvista")


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
    for name, values in cloud.attributes.items():
        values = values.reshape(len(values), -1) if values.ndim > 2 else values
        data.point_data[name] = values.astype(np.float32) if values.dtype == np.float16 else values  # VTK lacks it
    data.field_data[_SCHEMA_KEY] = [cloud.schema.to_json()]  # dtypes, shapes and kinds
    return data
