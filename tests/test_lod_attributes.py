"""Attributes through every level-of-detail path: the in-memory tree and its sequential list,
.lod.npz files, the out-of-core build and its lazy cuts, COPC written and read (by surfel and by
laspy). Inner nodes aggregate continuous attributes by the area-weighted mean of the leaves
below them and take a categorical one from a child: never an average."""

from __future__ import annotations

from pathlib import Path

import laspy
import numpy as np
import pytest

import surfel.lod as lod
from surfel.attributes import CATEGORICAL, CONTINUOUS
from surfel.camera import frame
from surfel.cloud import PointCloud
from surfel.io import load
from surfel.lod.copc import CopcSource
from surfel.lod.copc_write import write_copc
from surfel.lod.lazy import LazyHierarchy
from surfel.lod.outofcore import BYTES_PER_POINT, MEMORY_OVERHEAD, build_outofcore
from surfel.preprocess import complete

DATA = Path(__file__).parent / "data"  # laspy's test files, BSD licence (see the .LICENSE files)
CLASSES = np.array([2, 6], np.uint8)  # an average of the two (4) is neither


def terrain(n: int, seed: int = 0) -> PointCloud:
    """A gently curved patch with two classes in patches, intensity, GPS time, a vector and a
    stated-continuous integer: normals up, circular splats covering the sampling."""
    rng = np.random.default_rng(seed)
    xy = rng.random((n, 2)) * 100
    z = 2 * np.sin(xy[:, 0] / 15) + np.cos(xy[:, 1] / 20)
    positions = np.column_stack([xy, z])
    normals = np.tile([0.0, 0.0, 1.0], (n, 1))
    patch = ((xy[:, 0] // 17 + xy[:, 1] // 23) % 2).astype(int)
    radius = 1.5 * 100 / np.sqrt(n)
    return PointCloud(positions, normals=normals, radii=np.full(n, radius), geospatial=True, attributes={
        "classification": CLASSES[patch], "intensity": rng.integers(0, 4000, n).astype(np.uint16),
        "gps_time": 4e8 + np.arange(n) * 1e-4, "tint": rng.random((n, 2)).astype(np.float32),
        "echo": rng.integers(0, 3, n).astype(np.int16)}, kinds={"echo": CONTINUOUS})


def assert_leaves_match(cloud: PointCloud, cut: PointCloud, names) -> None:
    """Every point of `cloud` is in `cut` with the same values of attributes `names` (matched by
    position), in the same dtype and kind."""
    assert len(cut) == len(cloud)
    a, b = np.lexsort(cloud.positions.T), np.lexsort(cut.positions.T)
    np.testing.assert_allclose(cut.positions[b], cloud.positions[a], rtol=0, atol=1e-6)
    for name in names:
        assert cut.schema[name].dtype == cloud.schema[name].dtype, name
        assert cut.schema[name].kind == cloud.schema[name].kind, name
        np.testing.assert_array_equal(cut.attributes[name][b], cloud.attributes[name][a], err_msg=name)


# ---- in memory ---------------------------------------------------------------------------

@pytest.fixture(scope="module")
def cloud() -> PointCloud:
    return terrain(3000)


@pytest.fixture(scope="module")
def tree(cloud) -> lod.LodTree:
    return lod.build_lod(cloud, progress=False)


def test_tree_aggregates_every_attribute(cloud, tree):
    m, leaves = len(tree), tree.n_leaves
    assert list(tree.attributes) == list(cloud.attributes)
    assert tree.kinds == cloud.schema.kinds
    # the leaves below each node, by walking every leaf's parent chain (not the child lists)
    weight = np.prod(np.linalg.norm(tree.axes[:leaves].astype(np.float64), axis=2), axis=1)
    below = [[] for _ in range(m)]
    for leaf in range(leaves):
        node = leaf
        while node >= 0:
            below[node].append(leaf)
            node = tree.parent[node]
    for name, values in cloud.attributes.items():
        nodes = tree.attributes[name]
        assert nodes.dtype == values.dtype and nodes.shape == (m, *values.shape[1:])
        np.testing.assert_array_equal(nodes[:leaves], values[tree.point_index])
        if cloud.schema[name].kind == CATEGORICAL:
            continue
        leaf_values = values[tree.point_index].reshape(leaves, -1).astype(np.float64)
        for node in range(leaves, m):
            w = weight[below[node]]
            mean = (w[:, None] * leaf_values[below[node]]).sum(axis=0) / w.sum()
            if values.dtype.kind in "iu":
                assert np.abs(nodes[node].reshape(-1) - mean).max() <= 0.5 + 1e-9, name
            else:
                np.testing.assert_allclose(nodes[node].reshape(-1), mean, rtol=1e-6, err_msg=name)


def test_categories_are_never_averaged(tree):
    classes = tree.attributes["classification"]
    assert set(np.unique(classes)) == set(CLASSES.tolist())
    inner = np.arange(tree.n_leaves, len(tree))
    mixed = 0
    for node in inner:
        children = tree.children[tree.child_start[node]:tree.child_start[node + 1]]
        assert classes[node] in classes[children]
        mixed += len(np.unique(classes[children])) > 1
    assert mixed > 10  # the tree has nodes over both classes


def test_sequential_cloud_subset_and_lod_file_keep_attributes(cloud, tree, tmp_path):
    seq = lod.to_sequential_cloud(tree)
    order = lod.sequential_order(tree)
    np.testing.assert_array_equal(seq.positions, tree.positions[order])
    for name in cloud.attributes:
        np.testing.assert_array_equal(seq.attributes[name], tree.attributes[name][order])
    assert {name: seq.schema[name].kind for name in cloud.attributes} == cloud.schema.kinds
    camera = frame(seq.center, seq.bounding_radius, geospatial=True, size=(128, 128), view="top")
    subset = lod.lod_subset(seq, camera, 2.0)
    mask = lod.select_sequential(seq, camera, 2.0)
    assert 0 < len(subset) < len(seq) and not lod.is_sequential(subset)
    for name in cloud.attributes:
        np.testing.assert_array_equal(subset.attributes[name], seq.attributes[name][mask])
    lod.save_lod(seq, tmp_path / "t.lod.npz")
    for back in (lod.load_lod(tmp_path / "t.lod.npz"), load(tmp_path / "t.lod.npz")):
        assert back.schema == seq.schema
        for name, values in seq.attributes.items():
            np.testing.assert_array_equal(back.attributes[name], values)


# ---- out of core ---------------------------------------------------------------------------

@pytest.fixture(scope="module")
def las_terrain(tmp_path_factory) -> tuple[Path, PointCloud]:
    """25,000 terrain points as LAS 1.4 (format 6) with classes, intensity, GPS time, scan
    angles and an extra-bytes dimension; and the cloud surfel reads from it."""
    source = terrain(25_000, seed=1)
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales, header.offsets = np.full(3, 1e-3), np.zeros(3)
    header.add_extra_dim(laspy.ExtraBytesParams(name="Amplitude", type=np.float32))
    las = laspy.LasData(header)
    las.x, las.y, las.z = source.positions.T
    las.classification = source.attributes["classification"]
    las.intensity = source.attributes["intensity"]
    las.gps_time = source.attributes["gps_time"]
    las.scan_angle = np.arange(len(source)) % 2000 - 1000
    las.return_number = las.number_of_returns = np.ones(len(source), np.uint8)
    las.Amplitude = np.linspace(0, 40, len(source)).astype(np.float32)
    path = tmp_path_factory.mktemp("ooc") / "terrain.las"
    las.write(path)
    return path, load(path)


def test_out_of_core_cuts_keep_attributes(las_terrain, tmp_path):
    path, cloud = las_terrain
    out = tmp_path / "t.lod"
    # partitions of about 10,000 points: the attributes take about 31 bytes a point, 5 times over
    stats = build_outofcore(path, out, memory=MEMORY_OVERHEAD + 10_000 * (BYTES_PER_POINT + 160), progress=False)
    assert stats["partitions"] >= 3 and stats["top_nodes"] >= 1 and stats["partition_cap"] < 11_000
    source = LazyHierarchy(out)
    assert {spec.name: spec.dtype for spec in source.schema.scanner()} == {
        name: values.dtype for name, values in cloud.attributes.items()}
    camera = frame(source.center, source.bounding_radius, geospatial=True, size=(128, 128), view="top")
    full, _ = source.select(camera, 1e-6)  # every leaf
    assert_leaves_match(cloud, full, cloud.attributes)
    coarse, stats = source.select(camera, 200.0)
    assert len(coarse) < 20 and stats["points_selected"] == len(coarse)
    assert set(np.unique(coarse.attributes["classification"])) <= set(CLASSES.tolist())
    assert coarse.schema["classification"].kind == CATEGORICAL
    intensity = cloud.attributes["intensity"]
    assert intensity.min() <= coarse.attributes["intensity"].min() <= coarse.attributes["intensity"].max() \
        <= intensity.max()


# ---- COPC -----------------------------------------------------------------------------------

def test_copc_writes_attributes_that_both_readers_give_back(tmp_path):
    cloud, _ = complete(load(DATA / "extrabytes.las"))
    cloud = cloud.with_(attributes={**cloud.attributes, "height": cloud.positions[:, 2].astype(np.float32),
                                    "big_class": np.full(len(cloud), 300, np.int32)},
                        kinds={"big_class": CATEGORICAL})
    path = tmp_path / "x.copc.laz"
    write_copc(cloud, path, leaf_points=300)
    source = CopcSource(path)
    camera = frame(source.center, source.bounding_radius, geospatial=True, size=(128, 128), view="top")
    cut, stats = source.select(camera, 1e-6)
    assert stats["depth_loaded"] >= 1
    scanner = [spec.name for spec in cloud.schema.scanner()]
    assert_leaves_match(cloud, cut, [name for name in scanner if name != "scan_angle"])
    a, b = np.lexsort(cloud.positions.T), np.lexsort(cut.positions.T)
    # LAS 1.4 stores scan angles in units of 0.006 degrees; these were whole degrees
    np.testing.assert_allclose(cut.attributes["scan_angle"][b], cloud.attributes["scan_angle"][a], atol=0.003)
    assert load(path).schema == cloud.schema  # the plain LAS reader reads the surfel VLR too
    with laspy.CopcReader.open(path) as reader:
        points = reader.query()
    dims = set(points.point_format.dimension_names)
    c = np.lexsort(np.column_stack([points.x, points.y, points.z]).T)
    for name in ("classification", "intensity", "gps_time", "point_source_id", "return_number", "Time"):
        np.testing.assert_array_equal(np.asarray(points[name])[c], cloud.attributes[name][a], err_msg=name)
    np.testing.assert_array_equal(np.asarray(points["Colors_2"])[c], cloud.attributes["Colors"][a, 2])
    assert {"big_class", "height"} <= dims  # no standard field holds 300: extra bytes


def test_copc_reader_keeps_every_dimension_of_foreign_files():
    path = DATA / "simple_with_page.copc.laz"
    source = CopcSource(path)
    camera = frame(source.center, source.bounding_radius, geospatial=True, size=(128, 128), view="top")
    cut, _ = source.select(camera, 1e-6)
    whole = load(path)
    assert_leaves_match(whole, cut, whole.attributes)
    assert cut.schema["classification"].kind == CATEGORICAL
