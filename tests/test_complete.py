"""Completing a cloud: prepare fills exactly what is missing."""

from __future__ import annotations

import numpy as np

from samples import sphere
from surfel.cloud import PointCloud
from surfel.preprocess import prepare


def test_prepare_fills_exactly_what_is_missing():
    p = sphere(3_000)
    bare, report = prepare(PointCloud(p))
    assert bare.normals is not None and bare.radii is not None and bare.axes is not None
    assert report["ambiguous_normals"] == 0 and "normals" in report and "radii" in report and "axes" in report
    assert np.allclose(np.cross(bare.axes[:, 0], bare.axes[:, 1]), bare.normals * bare.radii[:, None] ** 2, atol=1e-6)

    given = PointCloud(p, normals=-p)  # inward on purpose: kept as given
    filled, report = prepare(given)
    assert np.array_equal(filled.normals, given.normals)
    assert "normals" not in report and "ambiguous_normals" not in report and "radii" in report

    complete = filled
    same, report = prepare(complete)
    assert same is complete and report == {}

    ellipses, report = prepare(PointCloud(p, normals=p, radii=np.full(len(p), 0.05)), elliptical=True,
                               normal_field=True)
    assert np.array_equal(ellipses.radii, np.full(len(p), 0.05, np.float32))
    assert report["axes"].startswith("fitted ellipses") and "normal_field" in report and "radii" not in report
    assert ellipses.attributes["phong_alpha"].shape == (len(p),) and (ellipses.attributes["phong_alpha"] > 0).all()

    axes_only, report = prepare(PointCloud(p, axes=bare.axes))
    assert np.allclose(axes_only.normals, bare.normals, atol=1e-5) and np.array_equal(axes_only.axes, bare.axes)


def test_prepare_geospatial_faces_up():
    rng = np.random.default_rng(11)
    xy = rng.uniform(0, 100, (5_000, 2))
    cloud = PointCloud(np.c_[xy, 0.1 * xy[:, 0] + 400] + [636_000, 849_000, 0], geospatial=True)
    prepared, report = prepare(cloud, progress=True)
    assert (prepared.normals[:, 2] > 0).all() and "up" in report["normals"]


def test_tiny_clouds():
    for n in (1, 2, 3):
        cloud, report = prepare(PointCloud(np.arange(3 * n, dtype=float).reshape(n, 3) ** 1.5))
        assert (cloud.radii > 0).all() and report["ambiguous_normals"] == n

