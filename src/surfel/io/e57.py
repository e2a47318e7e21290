"""E57 terrestrial scans (ASTM E2807): `read_e57`, every scan of a file merged by its pose.

Decoding is libE57Format's, through pye57 (MIT; libE57Format is under the Boost licence). An
E57 file holds Data3D scans, each with its points in the scan's own frame, cartesian
(x, y, z) or spherical (range r, azimuth a, elevation e: x = r cos e cos a, y = r cos e sin a,
z = r sin e), and a pose, the rigid motion to the file's coordinates:

    p = R(q) p_scan + t,    q = (w, x, y, z) the pose's unit quaternion, t its translation.

Points whose invalid state is set are dropped. The scans are merged into one cloud:

* positions in the file's coordinates (float64);
* colours colorRed/Green/Blue divided by 255 (pye57 reads them as 8-bit values);
* attributes: `intensity` (float32, as stored), `row_index` and `column_index` of the scanner's
  grid when present, and `scan` (categorical), the index of each point's scan;
* `sensors`: each scan's origin in the file's coordinates (its pose's t), so that estimated
  normals face the scanner that saw the point and splat sizes follow the range from it
  (surfel.preprocess). A scan without a pose sits at the origin with no rotation.

The cloud is geospatial (E57's Z axis is up). Before any point is read, the point counts the
file states are bounded by its size: at most MAX_POINTS_PER_BYTE points per byte (one bit per
point, below what any real encoding packs), so a header that lies is refused without
allocating what it claims.
"""

from __future__ import annotations

import os

import numpy as np

from ..attributes import CATEGORICAL
from ..cloud import PointCloud
from ..errors import InputError

MAX_POINTS_PER_BYTE = 8
COLOR_SCALE = 255.0


def read_e57(path: str) -> PointCloud:
    """Read every scan of an E57 file and merge them (see the module docstring); errors raise
    InputError naming the file."""
    try:
        import pye57
    except ImportError:  # pragma: no cover - pye57 is a dependency
        raise InputError(path, "reading E57 needs pye57 (pip install pye57)") from None
    try:
        with pye57.E57(path) as e57:
            headers = [e57.get_header(index) for index in range(e57.scan_count)]
            counts = [header.point_count for header in headers]
            if sum(counts) > MAX_POINTS_PER_BYTE * os.path.getsize(path):
                raise InputError(path, f"the file states {sum(counts)} points, more than its "
                                       f"{os.path.getsize(path)} bytes can hold")
            scans = [e57.read_scan(index, intensity=True, colors=True, row_column=True, transform=True,
                                   ignore_missing_fields=True) for index in range(len(headers))]
            sensors = np.array([header.translation if header.has_pose() else np.zeros(3) for header in headers],
                               np.float64).reshape(-1, 3)
    except InputError:
        raise
    except Exception as error:  # libE57Format and pye57 raise many types; all mean a bad file here
        message = (str(error).splitlines() or [type(error).__name__])[0][:120]
        raise InputError(path, f"cannot decode E57 data: {message}") from error
    return merge_scans(path, scans, sensors)


def merge_scans(path: str, scans: list[dict], sensors: np.ndarray) -> PointCloud:
    """One cloud of pye57's scans (dicts of per-point fields, in file coordinates) and their
    sensor positions (S, 3)."""
    sizes = [len(scan.get("cartesianX", ())) for scan in scans]
    if not sum(sizes):
        raise InputError(path, "no points")
    positions = np.concatenate([np.column_stack([scan["cartesianX"], scan["cartesianY"], scan["cartesianZ"]])
                                for scan, size in zip(scans, sizes, strict=True) if size])
    used = [scan for scan, size in zip(scans, sizes, strict=True) if size]

    def field(name: str, dtype) -> np.ndarray | None:
        if not all(name in scan for scan in used):
            return None
        return np.concatenate([np.asarray(scan[name], dtype) for scan in used])

    rgb = [field(name, np.float32) for name in ("colorRed", "colorGreen", "colorBlue")]
    colors = None if any(channel is None for channel in rgb) else np.column_stack(rgb) / np.float32(COLOR_SCALE)
    attributes = {name: values for name, values in (("intensity", field("intensity", np.float32)),
                                                    ("row_index", field("rowIndex", np.uint16)),
                                                    ("column_index", field("columnIndex", np.uint16)))
                  if values is not None}
    scan_dtype = np.uint16 if len(scans) <= np.iinfo(np.uint16).max else np.uint32
    attributes["scan"] = np.repeat(np.arange(len(scans), dtype=scan_dtype), sizes)
    return PointCloud(positions, colors=colors, attributes=attributes, kinds={"scan": CATEGORICAL},
                      geospatial=True, source=path, sensors=sensors)
