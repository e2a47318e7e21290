"""Per-point attributes: the schema, read-only clouds, every reader and writer keeping every
field (checked against laspy and against files written by hand), the adapters, `surfel info`."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import laspy
import numpy as np
import pytest

from surfel.adapters import from_numpy, from_trimesh, to_numpy, to_trimesh
from surfel.attributes import CATEGORICAL, CONTINUOUS, MAX_CATEGORIES, AttributeSpec, Schema, canonical_names
from surfel.cloud import PointCloud
from surfel.errors import InputError, SurfelError
from surfel.io import load, write_ply
from surfel.io.npz import cloud_arrays
from test_io import ply_file

DATA = Path(__file__).parent / "data"  # laspy's test files, BSD licence (see the .LICENSE files)
LAS_FILES = ["simple.las", "extrabytes.las", "1_4_w_evlr.laz"]


def typed_cloud(n: int = 200, seed: int = 0) -> PointCloud:
    """A cloud with attributes of many dtypes, shapes and kinds, and a derived array."""
    rng = np.random.default_rng(seed)
    return PointCloud(
        rng.normal(size=(n, 3)) * 100 + 636000.5,
        attributes={
            "intensity": rng.integers(0, 65536, n).astype(np.uint16),
            "classification": rng.choice(np.array([2, 6, 9], np.uint8), n),
            "gps_time": 3e8 + rng.random(n) * 1e3,
            "withheld": rng.random(n) < 0.1,
            "point_id": rng.integers(-2 ** 40, 2 ** 40, n),
            "Colors": rng.integers(0, 65536, (n, 3)).astype(np.uint16),
            "tilt": rng.normal(size=(n, 2, 2)).astype(np.float16),
            "label": rng.integers(0, 5, n).astype(np.int16),
            "clip_lines": rng.normal(size=(n, 2, 3)),
        },
        kinds={"label": CONTINUOUS},  # a reader may state what inference would not say
        geospatial=True)


def assert_same_attributes(a: PointCloud, b: PointCloud) -> None:
    assert a.schema == b.schema  # names, order, dtypes, shapes, kinds
    for name, values in a.attributes.items():
        np.testing.assert_array_equal(b.attributes[name], values, err_msg=name)


# ---- the schema -------------------------------------------------------------------------

def test_schema_json_round_trip_and_bad_entries():
    schema = typed_cloud().schema
    assert Schema.from_json(schema.to_json()) == schema == Schema.from_json(schema.to_list())
    assert list(schema) == list(typed_cloud().attributes)
    assert [spec.name for spec in schema.scanner()] == [name for name in schema if name != "clip_lines"]
    assert schema["clip_lines"].derived and not schema["intensity"].derived
    entry = {"name": "a", "dtype": "uint8", "shape": [], "kind": CATEGORICAL}
    for bad in ({**entry, "dtype": "object"}, {**entry, "kind": "nominal"}, {**entry, "shape": [-1]},
                {**entry, "shape": "3"}, {"name": "a"}):
        with pytest.raises(ValueError):
            Schema.from_json([bad])
    with pytest.raises(ValueError, match="twice"):
        Schema.from_json([entry, entry])
    with pytest.raises(ValueError):
        AttributeSpec("s", np.dtype("U3"))


def test_kinds_known_inferred_and_stated():
    n = 500
    codes = np.arange(n) % MAX_CATEGORIES
    cloud = PointCloud(np.random.default_rng(0).normal(size=(n, 3)), attributes={
        "Classification": np.zeros(n, np.uint8), "scalar_Intensity": np.zeros(n, np.uint16),
        "ReturnNumber": np.ones(n, np.uint8), "codes": codes.astype(np.uint16),
        "many": (np.arange(n) % (MAX_CATEGORIES + 1) * 1000).astype(np.int32), "flag": np.arange(n) % 2 == 0,
        "height": np.linspace(0, 1, n), "pairs": np.zeros((n, 2), np.uint8), "phong_alpha": np.zeros(n)})
    kinds = cloud.schema.kinds
    assert kinds == {"Classification": CATEGORICAL, "scalar_Intensity": CONTINUOUS, "ReturnNumber": CATEGORICAL,
                     "codes": CATEGORICAL, "many": CONTINUOUS, "flag": CATEGORICAL, "height": CONTINUOUS,
                     "pairs": CONTINUOUS, "phong_alpha": CONTINUOUS}
    stated = cloud.with_(kinds={"codes": CONTINUOUS, "height": CATEGORICAL, "gone": CATEGORICAL})
    assert stated.schema["codes"].kind == CONTINUOUS and stated.schema["height"].kind == CATEGORICAL
    assert "gone" not in stated.kinds
    with pytest.raises(InputError, match="derived"):
        cloud.with_(kinds={"phong_alpha": CATEGORICAL})
    with pytest.raises(InputError, match="kind"):
        cloud.with_(kinds={"codes": "ordinal"})


def test_canonical_names():
    assert canonical_names(["Intensity", "scalar_Classification", "GpsTime", "ScanAngleRank", "Pulse width"]) == \
        ["intensity", "classification", "gps_time", "scan_angle", "Pulse_width"]
    # a standard name already taken keeps the file's spelling
    assert canonical_names(["Intensity"], taken=["intensity"]) == ["Intensity"]
    assert canonical_names(["intensity", "Intensity"]) == ["intensity", "Intensity"]


def test_attributes_keep_their_dtype_and_are_validated():
    cloud = typed_cloud()
    dtypes = {name: values.dtype for name, values in cloud.attributes.items()}
    assert dtypes["intensity"] == np.uint16 and dtypes["classification"] == np.uint8
    assert dtypes["gps_time"] == np.float64 and dtypes["withheld"] == np.bool_ and dtypes["tilt"] == np.float16
    assert dtypes["clip_lines"] == np.float32  # derived arrays are float32
    positions = np.zeros((3, 3))
    for attributes, message in [({"normals": np.zeros(3)}, "cannot name"), ({"s": np.array(["a", "b", "c"])},
                                "not numeric"), ({"lod_emin": np.array([0.0, np.nan, 1.0])}, "NaN"),
                                ({"h": np.zeros(4)}, "shape")]:
        with pytest.raises(InputError, match=message):
            PointCloud(positions, attributes=attributes)
    # a scanner's missing values (NaN in a LAS extra-bytes field) are kept; surfel's estimates must be finite
    kept = PointCloud(positions, attributes={"h": np.array([0.0, np.nan, 1.0])}).attributes["h"]
    assert np.isnan(kept[1]) and kept[2] == 1.0


def test_cloud_arrays_are_read_only():
    positions = np.random.default_rng(0).normal(size=(10, 3))
    intensity = np.arange(10, dtype=np.uint16)
    cloud = PointCloud(positions, normals=np.tile([0.0, 0, 1], (10, 1)), radii=np.ones(10, np.float32),
                       attributes={"intensity": intensity}, faces=np.array([[0, 1, 2]]))
    # the caller's arrays are used as they are, not copied
    assert cloud.positions is positions and cloud.attributes["intensity"] is intensity
    with pytest.raises(ValueError, match="read-only"):
        cloud.positions += 1
    for array in (cloud.normals, cloud.radii, cloud.faces, cloud.attributes["intensity"], cloud.bounds[0]):
        with pytest.raises(ValueError, match="read-only"):
            array[0] = 0
    with pytest.raises(ValueError, match="read-only"):
        positions[0, 0] = 1.0
    taken = cloud.take([1, 2])
    assert not taken.positions.flags.writeable and not taken.attributes["intensity"].flags.writeable


# ---- readers and writers ----------------------------------------------------------------

@pytest.mark.parametrize("name", LAS_FILES)
def test_las_keeps_every_dimension(name):
    cloud = load(DATA / name)
    las = laspy.read(DATA / name)
    expected = set(las.point_format.dimension_names) - {"X", "Y", "Z", "red", "green", "blue"}
    renamed = {"scan_angle_rank": "scan_angle", "Intensity": "Intensity"}
    assert set(cloud.attributes) == {renamed.get(dim, dim) for dim in expected}
    for dimension in las.point_format.dimensions:
        if dimension.name in ("X", "Y", "Z", "red", "green", "blue"):
            continue
        raw = np.asarray(las[dimension.name])
        values = cloud.attributes[renamed.get(dimension.name, dimension.name)]
        if dimension.name == "scan_angle":
            np.testing.assert_allclose(values, raw * 0.006, atol=1e-5)
        else:
            np.testing.assert_array_equal(values, raw, err_msg=dimension.name)
        if dimension.kind == laspy.DimensionKind.BitField and dimension.num_bits == 1:
            assert values.dtype == np.bool_
    schema = cloud.schema
    assert schema["intensity"].dtype == np.uint16 and schema["intensity"].kind == CONTINUOUS
    assert schema["classification"].dtype == np.uint8 and schema["classification"].kind == CATEGORICAL
    assert schema["gps_time"].dtype == np.float64 and schema["scan_angle"].dtype == np.float32
    assert schema["point_source_id"].kind == CATEGORICAL and schema["withheld"].kind == CATEGORICAL


def test_las_extra_bytes_keep_type_and_shape():
    schema = load(DATA / "extrabytes.las").schema
    # 'Intensity' is an extra dimension beside the standard 'intensity': it keeps its spelling
    assert (schema["Colors"].dtype, schema["Colors"].shape) == (np.uint16, (3,))
    assert (schema["Flags"].dtype, schema["Flags"].shape) == (np.int8, (2,))
    assert schema["Intensity"].dtype == np.uint32 and schema["Time"].dtype == np.uint64


@pytest.mark.parametrize("binary", [True, False])
def test_ply_round_trip_keeps_types_shapes_and_kinds(tmp_path, binary):
    cloud = typed_cloud()
    write_ply(cloud, tmp_path / "t.ply", binary=binary)
    back = load(tmp_path / "t.ply")
    assert_same_attributes(cloud, back)
    header = (tmp_path / "t.ply").read_bytes().split(b"end_header")[0].decode()
    assert "property ushort intensity" in header and "property uchar classification" in header


def test_ply_with_unknown_64_bit_integers_refuses_what_double_cannot_hold(tmp_path):
    cloud = PointCloud(np.zeros((2, 3)), attributes={"id": np.array([0, 2 ** 60])})
    with pytest.raises(SurfelError, match="64-bit"):
        write_ply(cloud, tmp_path / "big.ply")


def test_ply_scalar_properties_of_other_tools(tmp_path):
    props = [("x", "float"), ("y", "float"), ("z", "float"), ("scalar_Intensity", "ushort"),
             ("scalar_Classification", "uchar"), ("Deviation", "float"), ("faces_seen", "list", "uchar", "int")]
    rows = [(0, 0, 0, 1200, 2, 0.5, [1, 2]), (1, 0, 0, 65535, 6, -0.25, [3])]
    cloud = load(ply_file(tmp_path / "cc.ply", "binary_big_endian", [("vertex", props, rows)]))
    assert list(cloud.attributes) == ["intensity", "classification", "Deviation"]  # lists are skipped
    assert cloud.attributes["intensity"].dtype == np.uint16 and cloud.attributes["intensity"].tolist() == [1200, 65535]
    assert cloud.schema["classification"].kind == CATEGORICAL and cloud.schema["intensity"].kind == CONTINUOUS
    # an ascii body holds text: integer properties must hold whole numbers of their type
    bad = ply_file(tmp_path / "bad.ply", "ascii", [("vertex", props[:5], [(0, 0, 0, 1.5, 2)])])
    with pytest.raises(InputError, match="not uint16"):
        load(bad)


def test_ply_of_older_surfel_versions(tmp_path):
    props = [("x", "float"), ("y", "float"), ("z", "float")] + [(f"clip_lines_{i}", "float") for i in range(6)]
    path = ply_file(tmp_path / "old.ply", "ascii", [("vertex", props, [(0, 0, 0, 1, 2, 3, 4, 5, 6)])],
                    comments=("surfel_extra clip_lines 2 3",))
    cloud = load(path)
    assert list(cloud.attributes) == ["clip_lines"] and cloud.schema["clip_lines"].shape == (2, 3)
    np.testing.assert_array_equal(cloud.attributes["clip_lines"], [[[1, 2, 3], [4, 5, 6]]])


def test_npz_keeps_arrays_and_stated_kinds(tmp_path):
    cloud = typed_cloud()
    np.savez(tmp_path / "t.npz", **cloud_arrays(cloud))
    back = load(tmp_path / "t.npz")
    assert_same_attributes(cloud, back)
    assert back.schema["label"].kind == CONTINUOUS  # stated; inference would say categorical
    np.savez(tmp_path / "bad.npz", positions=np.zeros((2, 3)), surfel_schema=np.str_("[{}]"))
    with pytest.raises(InputError, match="surfel_schema"):
        load(tmp_path / "bad.npz")


def test_text_header_names_the_columns(tmp_path):
    (tmp_path / "cc.txt").write_text("//X,Y,Z,R,G,B,Intensity,Classification\n"
                                     "0,0,0,255,0,0,0.5,2\n1,0,0,0,255,0,0.25,6\n")
    cloud = load(tmp_path / "cc.txt")
    np.testing.assert_allclose(cloud.colors, [[1, 0, 0], [0, 1, 0]])
    assert cloud.attributes["intensity"].tolist() == [0.5, 0.25]
    assert cloud.attributes["classification"].dtype == np.int32
    assert cloud.schema["classification"].kind == CATEGORICAL
    (tmp_path / "h.xyz").write_text("# from a script\nz y x nx ny nz return_number\n3 2 1 0 0 1 1\n6 5 4 0 1 0 2\n")
    cloud = load(tmp_path / "h.xyz")
    np.testing.assert_array_equal(cloud.positions, [[1, 2, 3], [4, 5, 6]])
    np.testing.assert_allclose(cloud.normals, [[0, 0, 1], [0, 1, 0]])
    assert cloud.attributes["return_number"].tolist() == [1, 2]


# ---- adapters and info --------------------------------------------------------------------

def test_adapters_keep_attributes():
    cloud = typed_cloud()
    assert_same_attributes(cloud, from_numpy(**to_numpy(cloud)))
    assert_same_attributes(cloud, from_trimesh(to_trimesh(cloud)))


def test_pyvista_adapter_keeps_attributes():
    pytest.importorskip("pyvista")
    from surfel.adapters import from_pyvista, to_pyvista

    cloud = typed_cloud()
    assert_same_attributes(cloud, from_pyvista(to_pyvista(cloud)))


def _info(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "surfel.cli", "info", *map(str, args)],
                          capture_output=True, text=True, check=True)


def test_info_lists_attributes_with_ranges():
    las = laspy.read(DATA / "simple.las")
    report = json.loads(_info(DATA / "simple.las", "--json").stdout)
    schema = report["schema"]
    codes, counts = np.unique(np.asarray(las.classification), return_counts=True)
    assert schema["classification"]["kind"] == CATEGORICAL and schema["classification"]["dtype"] == "uint8"
    assert schema["classification"]["values"] == {str(c): int(k) for c, k in zip(codes, counts, strict=True)}
    assert schema["intensity"]["kind"] == CONTINUOUS
    assert (schema["intensity"]["min"], schema["intensity"]["max"]) == (int(las.intensity.min()),
                                                                         int(las.intensity.max()))
    assert schema["gps_time"]["min"] == float(las.gps_time.min())
    assert len(schema["user_data"]["values"]) == 12 and schema["user_data"]["more"] > 0  # capped
    text = _info(DATA / "simple.las").stdout
    line = next(line for line in text.splitlines() if line.strip().startswith("classification"))
    assert "uint8" in line and "categorical" in line and f"{codes[0]}: {counts[0]}" in line
    line = next(line for line in text.splitlines() if line.strip().startswith("intensity"))
    assert f"{int(las.intensity.min())} .. {int(las.intensity.max())}" in line
