"""Out-of-core LOD: partitioned build within a memory budget, lazy selection and rendering."""

from __future__ import annotations

import errno
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from scipy.spatial import cKDTree

from models import SPOT
from surfel.camera import frame
from surfel.cli import main
from surfel.cloud import PointCloud
from surfel.errors import InputError, SurfelError
from surfel.io import load, write_ply
from surfel.lod import binning, outofcore, worker_warm_up
from surfel.lod.binning import bin_input, fine_cells, halo_pairs, lone_cells, piece_files
from surfel.lod.lazy import LazyHierarchy
from surfel.lod.outofcore import (
    BYTES_PER_POINT,
    MEMORY_OVERHEAD,
    WORKER_OVERHEAD,
    build_outofcore,
    parse_size,
)
from surfel.lod.source import is_source, open_source
from surfel.lod.streaming import open_inputs, read_ahead
from surfel.metrics import compare_results
from surfel.preprocess import complete
from surfel.rendering import render

POINTS = 60_000
# a budget that forces about eight partitions of at most 10,000 points
SMALL_MEMORY = MEMORY_OVERHEAD + 10_000 * BYTES_PER_POINT


def sample_surface(mesh: PointCloud, n: int, seed: int = 0) -> PointCloud:
    """n points uniformly on the mesh surface, normals interpolated from the vertices."""
    tri = mesh.positions[mesh.faces]
    area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    rng = np.random.default_rng(seed)
    face = rng.choice(len(area), n, p=area / area.sum())
    s, r = np.sqrt(rng.random(n)), rng.random(n)
    bary = np.stack([1 - s, s * (1 - r), s * r], axis=1)[:, :, None]
    normals = (mesh.normals[mesh.faces][face] * bary).sum(axis=1)
    return PointCloud((tri[face] * bary).sum(axis=1), normals=normals)


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """(input PLY, the completed in-memory cloud, the built .lod directory, build stats)."""
    root = tmp_path_factory.mktemp("outofcore")
    ply = root / "spot.ply"
    write_ply(sample_surface(load(SPOT), POINTS), ply)
    stats = build_outofcore(ply, root / "spot.lod", memory=SMALL_MEMORY, progress=False)
    cloud, _ = complete(load(ply))
    return ply, cloud, root / "spot.lod", stats


def test_build_partitions_within_budget(built):
    _, _, lod, stats = built
    manifest = json.loads((lod / "manifest.json").read_text())
    assert stats["points"] == manifest["total_points"] == POINTS
    assert stats["partitions"] >= 4
    assert all(p["points"] <= 10_000 for p in manifest["partitions"])
    assert sum(p["points"] for p in manifest["partitions"]) == POINTS
    assert stats["top_nodes"] >= 1
    assert not Path(str(lod) + ".partial").exists()
    # each partition is a sequential list: r_max non-increasing, its root (row 0) below the top
    for part in manifest["partitions"]:
        emax = np.load(lod / part["name"] / "lod_emax.npy")
        assert emax[0] < np.finfo(np.float32).max
        assert (np.diff(emax[1:]) <= emax[1:-1] * 2 ** -7).all()


def test_full_detail_matches_in_memory_render(built):
    _, cloud, lod, _ = built
    source = open_source(lod)
    assert is_source(source) and source.total_points == POINTS
    camera = frame(source.center, source.bounding_radius, size=(192, 192))
    reference = render(cloud, camera, "deferred", shading="lambert")
    result = render(source, camera, "deferred", shading="lambert", lod_error=1e-5)
    # every leaf and nothing else; leaves are the input points but crease points, which their
    # clip lines cut away whole (surfel.preprocess sharp features)
    assert 0.999 * POINTS <= result.stats["points_selected"] <= POINTS
    # a cut's splats are flat: no normal fields fitted to each frame's cut
    assert "normal_field" not in result.stats.get("estimated", {}), result.stats["estimated"]
    metrics = compare_results(reference, result)
    assert metrics["psnr"] > 35 and metrics["holes"] < 0.002, metrics


def test_coarse_cut_is_hole_free(built):
    _, cloud, lod, _ = built
    source = LazyHierarchy(lod)
    camera = frame(source.center, source.bounding_radius, view="iso", size=(192, 192))
    reference = render(cloud, camera, "deferred", shading="lambert")
    result = render(source, camera, "deferred", shading="lambert", lod_error=1.0)
    assert result.stats["splats"] < POINTS / 2
    metrics = compare_results(reference, result)
    assert metrics["holes"] < 0.002 and metrics["psnr"] > 28, metrics


def test_far_view_reads_a_fraction(built):
    _, _, lod, _ = built
    source = LazyHierarchy(lod)
    full = sum(f.stat().st_size for f in lod.rglob("*.npy"))
    camera = frame(source.center, source.bounding_radius, size=(128, 128), zoom=8)
    cut, stats = source.select(camera, 1.0)
    assert stats["bytes_read"] < 0.05 * full
    assert stats["nodes_loaded"] < 0.05 * source.nodes
    assert len(cut) == stats["points_selected"] < 2000


def test_frustum_culls_partitions(built):
    _, _, lod, _ = built
    source = LazyHierarchy(lod)
    lo, _ = source.bounds
    # standing at a corner of the bounds, looking away from the cloud
    eye = lo - 0.1 * (source.center - lo)
    camera = frame(lo, source.bounding_radius, eye=eye, target=2 * eye - source.center, size=(128, 128))
    _, stats = source.select(camera, 1.0)
    assert stats["partitions_visible"] < len(source.partitions) / 2


def test_point_budget_raises_epsilon(built):
    _, _, lod, _ = built
    source = LazyHierarchy(lod)
    camera = frame(source.center, source.bounding_radius, size=(256, 256))
    cut, stats = source.select(camera, 0.5, point_budget=3000)
    assert len(cut) <= 3000 and stats["epsilon_used"] > 0.5
    unlimited, _ = source.select(camera, stats["epsilon_used"] * 0.9)
    assert len(unlimited) > 3000 * 0.8


def leaf_splats(lod: Path, cloud: PointCloud) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(input index, radius, semi-axis lengths (m, 2)) of every leaf of the hierarchy directory:
    the leaves are the nodes at the input's positions."""
    manifest = json.loads((lod / "manifest.json").read_text())
    index, radii, semi = [], [], []
    tree = cKDTree(cloud.positions)
    for part in manifest["partitions"]:
        distance, nearest = tree.query(np.load(lod / part["name"] / "positions.npy"))
        leaf = distance == 0
        index.append(nearest[leaf])
        radii.append(np.load(lod / part["name"] / "radii.npy")[leaf])
        semi.append(np.linalg.norm(np.load(lod / part["name"] / "axes.npy")[leaf], axis=2))
    return np.concatenate(index), np.concatenate(radii), np.concatenate(semi)


def test_partition_borders_match_in_memory(built, tmp_path, monkeypatch):
    """With its halo, every partition's points get the radii and axes of the in-memory build,
    at the borders too, whether the partitions are built one after the other or by a pool of
    worker processes, planned from every point or from a sample; without the halo, border
    points lose neighbours and their radii differ."""
    ply, cloud, lod, _ = built
    monkeypatch.setattr(binning, "HISTOGRAM_SAMPLE", POINTS // 5)  # planned from every fifth point
    two_workers = MEMORY_OVERHEAD + 2 * WORKER_OVERHEAD + 2 * 10_000 * BYTES_PER_POINT
    pooled = build_outofcore(ply, tmp_path / "pooled.lod", memory=two_workers, progress=False, workers=2)
    assert pooled["workers"] == 2 and pooled["partitions"] >= 4 and pooled["points"] == POINTS
    manifest = json.loads((tmp_path / "pooled.lod" / "manifest.json").read_text())
    assert max(p["points"] for p in manifest["partitions"]) <= pooled["partition_cap"]
    for built_lod in (lod, tmp_path / "pooled.lod"):
        index, radii, semi = leaf_splats(built_lod, cloud)
        # every point is a leaf, once, but crease points (clipped away whole: not stored)
        assert len(np.unique(index)) == len(index) >= 0.999 * POINTS
        np.testing.assert_allclose(radii, cloud.radii[index], rtol=1e-4)
        np.testing.assert_allclose(semi, np.linalg.norm(cloud.axes[index], axis=2), rtol=1e-4, atol=1e-9)
    monkeypatch.setattr(binning, "HALO_SPACINGS", 0.0)
    build_outofcore(ply, tmp_path / "no_halo.lod", memory=SMALL_MEMORY, progress=False)
    index, radii, _ = leaf_splats(tmp_path / "no_halo.lod", cloud)
    assert (np.abs(radii / cloud.radii[index] - 1) > 1e-3).sum() > 100


def test_parallel_binning_writes_what_one_process_writes(built, tmp_path, monkeypatch):
    """A binary PLY binned by two worker processes, each a run of its chunks into pieces of
    its own, holds for every partition and halo the bytes one process writes: the same
    records in the same (the input's) order."""
    from concurrent.futures import ProcessPoolExecutor
    from multiprocessing import get_context

    ply = built[0]
    monkeypatch.setattr(binning, "CHUNK_POINTS", POINTS // 5 + 1)  # five chunks, split 3 + 2
    folders = [tmp_path / "one", tmp_path / "two"]
    for folder in folders:
        folder.mkdir()
    serial = bin_input(open_inputs(ply), folders[0], POINTS // 6, {}, False)
    with ProcessPoolExecutor(2, mp_context=get_context("spawn")) as pool:
        pooled = bin_input(open_inputs(ply), folders[1], POINTS // 6, {}, False, pool, 2)
    assert serial == pooled and len(serial["counts"]) >= 6
    pieces = 0
    for g in range(len(serial["counts"])):
        for suffix in ("bin", "halo"):
            one, two = (piece_files(folder / "bins", f"part-{g:05d}", suffix) for folder in folders)
            pieces += len(two)
            assert b"".join(f.read_bytes() for f in one) == b"".join(f.read_bytes() for f in two)
    assert pieces > 2 * len(serial["counts"])  # most partitions and halos came in two pieces


@pytest.mark.parametrize("halo", [0.3, 1.5])
@pytest.mark.parametrize("layout", ["scattered", "blocks"])
def test_halo_pairs_match_their_definition(halo, layout):
    """A point joins the halo of every other partition with a cell within Chebyshev distance
    h of it (binning.py), checked against every cell of a small grid: partitions scattered
    cell by cell, or blocks of cells (octants, one of them empty) where most cells are lone."""
    res = 8
    rng = np.random.default_rng(1)
    if layout == "scattered":
        lookup = rng.integers(-1, 5, res ** 3).astype(np.int32)
    else:
        octant = np.indices((res, res, res)) // (res // 2)
        lookup = (octant[0] * 4 + octant[1] * 2 + octant[2]).astype(np.int32).reshape(-1)
        lookup[lookup == 5] = -1
    points = rng.random((400, 3)) * res  # the cube [0, res]^3: cell widths of 1
    own = lookup[fine_cells(points, np.zeros(3), 1.0, res)]
    lone = lone_cells(lookup, res, halo)
    found = set(zip(*(a.tolist() for a in halo_pairs(points, np.zeros(3), 1.0, res, lookup, lone, own, halo)),
                    strict=True))
    # the lone cells only skip work: with none, the same pairs
    unskipped = halo_pairs(points, np.zeros(3), 1.0, res, lookup, np.zeros(res ** 3, bool), own, halo)
    assert found == set(zip(*(a.tolist() for a in unskipped), strict=True))
    corner = np.stack(np.meshgrid(*[np.arange(res)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    gap = np.maximum(np.maximum(corner[None] - points[:, None], points[:, None] - corner[None] - 1), 0).max(axis=2)
    near = (gap <= halo) & (lookup[None] >= 0) & (lookup[None] != own[:, None])
    expected = {(i, int(lookup[c])) for i, c in zip(*np.nonzero(near), strict=True)}
    assert found == expected and len(expected) > 50
    if layout == "blocks":
        assert lone.mean() > 0.1


def test_interrupted_build_leaves_no_output_and_resumes(built, tmp_path, monkeypatch):
    ply, _, reference, _ = built
    out = tmp_path / "cut.lod"
    real = outofcore._build_partition
    calls = []

    def failing(*args, **kwargs):
        calls.append(args[1])
        if len(calls) == 3:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(outofcore, "_build_partition", failing)
    with pytest.raises(KeyboardInterrupt):
        build_outofcore(ply, out, memory=SMALL_MEMORY, progress=False)
    assert not out.exists() and open_source(out) is None
    partial = tmp_path / "cut.lod.partial"
    assert partial.is_dir() and not (partial / "manifest.json").exists()
    monkeypatch.setattr(outofcore, "_build_partition", real)
    stats = build_outofcore(ply, out, memory=SMALL_MEMORY, resume=True, progress=False)
    assert stats["resumed_partitions"] == 2 and not partial.exists()
    assert json.loads((out / "manifest.json").read_text())["nodes"] == \
        json.loads((reference / "manifest.json").read_text())["nodes"]


KILLED_BUILD = """
import os, signal, sys
from surfel.lod import outofcore

def killed(partial, counts, dtype, schema, geospatial, pool, progress):
    print(*pool._processes, flush=True)  # the workers, started and warming up
    os.kill(os.getpid(), signal.SIGKILL)  # as a job scheduler ends a job: no clean-up

if __name__ == "__main__":
    outofcore._build_partitions = killed
    outofcore.build_outofcore(sys.argv[1], sys.argv[2], memory=int(sys.argv[3]), progress=False, workers=2)
"""


def test_a_killed_build_leaves_no_worker_behind(built, tmp_path):
    """Killed outright, a build cannot stop its pool; its workers end themselves instead of
    waiting on their queue for ever, each holding a partition's memory."""
    script = tmp_path / "killed_build.py"
    script.write_text(KILLED_BUILD)
    memory = MEMORY_OVERHEAD + 2 * WORKER_OVERHEAD + 2 * 10_000 * BYTES_PER_POINT
    output = tmp_path / "killed_build.out"
    with output.open("w") as out:  # a file, not a pipe: a worker left behind would hold a pipe open
        run = subprocess.run([sys.executable, script, built[0], tmp_path / "killed.lod", str(memory)],
                             stdout=out, stderr=subprocess.STDOUT, timeout=300)
    assert run.returncode == -9, output.read_text()
    workers = [int(pid) for pid in output.read_text().split()]
    assert len(workers) == 2

    def running(pid: int) -> bool:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return False
        try:  # an exited worker that its new parent has not reaped yet is a zombie (Linux: state Z)
            return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
        except FileNotFoundError:  # reaped meanwhile; without /proc, it exists
            return not Path("/proc").is_dir()

    deadline = time.monotonic() + 30
    while any(running(pid) for pid in workers) and time.monotonic() < deadline:
        time.sleep(0.2)
    alive = [pid for pid in workers if running(pid)]
    for pid in alive:
        os.kill(pid, 9)
    assert not alive


def test_a_file_system_without_fdatasync_gets_the_same_build(built, tmp_path, monkeypatch):
    """Writing partitions through to the disk is only a saving: where fdatasync fails (some FUSE
    mounts), the build writes the same arrays."""
    ply, _, reference, _ = built

    def unsupported(descriptor):
        raise OSError(errno.ENOSYS, "Function not implemented")

    monkeypatch.setattr(os, "fdatasync", unsupported)
    build_outofcore(ply, tmp_path / "fuse.lod", memory=SMALL_MEMORY, progress=False)
    manifest = json.loads((reference / "manifest.json").read_text())
    assert json.loads((tmp_path / "fuse.lod" / "manifest.json").read_text()) == manifest
    for part in manifest["partitions"]:
        for array in ("positions", "radii", "lod_emax"):
            assert np.array_equal(np.load(tmp_path / "fuse.lod" / part["name"] / f"{array}.npy"),
                                  np.load(reference / part["name"] / f"{array}.npy"))


def test_a_partial_build_of_another_layout_is_not_resumed(built, tmp_path):
    """A NAME.partial/ whose plan an older surfel wrote (other bin files) is refused in one
    line naming it, not read as if it were this version's."""
    ply, _, _, _ = built
    out = tmp_path / "old.lod"
    partial = tmp_path / "old.lod.partial"
    partial.mkdir()
    plan = {"signature": {"files": [[str(ply), ply.stat().st_size, ply.stat().st_mtime]], "memory": SMALL_MEMORY,
                          "workers": 1}, "counts": [1]}
    (partial / "plan.json").write_text(json.dumps(plan))
    with pytest.raises(SurfelError, match=r"old\.lod\.partial: left by another version of surfel"):
        build_outofcore(ply, out, memory=SMALL_MEMORY, resume=True, progress=False)
    assert not out.exists()


def test_cli_build_render_info(built, tmp_path):
    ply, _, _, _ = built
    runner = CliRunner()
    out = tmp_path / "cli.lod"
    result = runner.invoke(main, ["lod", "build", str(ply), "-o", str(out), "--memory", "1GB"])
    assert result.exit_code == 0, result.output
    png = tmp_path / "far.png"
    result = runner.invoke(main, ["render", str(out), "-o", str(png), "--size", "96x96", "--lod-error", "1",
                                  "--point-budget", "5000", "--stats", str(tmp_path / "s.json")])
    assert result.exit_code == 0, result.output
    stats = json.loads((tmp_path / "s.json").read_text())
    assert stats["points"] == POINTS and stats["splats"] <= 5000
    result = runner.invoke(main, ["info", str(out), "--json"])
    assert result.exit_code == 0 and json.loads(result.output)["points"] == POINTS
    gif = tmp_path / "orbit.gif"
    result = runner.invoke(main, ["turntable", str(out), "-o", str(gif), "--frames", "2", "--size", "64x64"])
    assert result.exit_code == 0, result.output
    from PIL import Image

    with Image.open(gif) as animation:
        assert animation.n_frames == 2
        assert np.asarray(animation.convert("RGB")).max() > 0  # the cloud is in the picture


def test_bad_inputs_are_one_line_errors(tmp_path):
    runner = CliRunner()
    missing = runner.invoke(main, ["lod", "build", str(tmp_path / "nope.ply"), "-o", str(tmp_path / "x.lod")])
    truncated = tmp_path / "short.ply"
    truncated.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 1000\nproperty float x\n"
                          b"property float y\nproperty float z\nend_header\n" + bytes(100))
    short = runner.invoke(main, ["lod", "build", str(truncated), "-o", str(tmp_path / "y.lod")])
    for result, what in ((missing, "no such file"), (short, "truncated")):
        assert result.exit_code == 2 and what in result.output
        assert len(result.output.strip().splitlines()) == 1
    assert not (tmp_path / "x.lod").exists() and not (tmp_path / "y.lod").exists()
    keep = tmp_path / "photos"
    (keep / "a.txt").parent.mkdir()
    (keep / "a.txt").write_text("not a hierarchy")
    refused = runner.invoke(main, ["lod", "build", str(truncated), "-o", str(keep)])
    assert refused.exit_code == 2 and (keep / "a.txt").exists()
    # an output named for no hierarchy format: an archive under that name would not read back
    named = runner.invoke(main, ["lod", "build", str(truncated), "-o", str(tmp_path / "tree.txt")])
    assert named.exit_code == 2 and "NAME.lod.npz" in named.output and len(named.output.strip().splitlines()) == 1
    assert not (tmp_path / "tree.txt").exists()
    with pytest.raises(InputError):
        LazyHierarchy(tmp_path)


def test_parse_size(tmp_path):
    assert parse_size("4GB") == 4 << 30 and parse_size("512mb") == 512 << 20 and parse_size("1000") == 1000
    with pytest.raises(SurfelError):
        parse_size("lots")
    result = CliRunner().invoke(main, ["lod", "build", "in.ply", "-o", str(tmp_path / "out.lod"), "--memory", "5XB"])
    assert result.exit_code == 2
    assert result.output == "surfel: error: --memory: cannot read the size '5XB' (use e.g. 512MB or 4GB)\n"
    assert not any(tmp_path.iterdir())


def test_read_ahead_keeps_order_raises_read_errors_and_stops_early():
    import threading

    assert list(read_ahead(iter(range(50)))) == list(range(50))

    def failing():
        yield 1
        raise InputError("x.ply", "truncated PLY body")

    with pytest.raises(InputError, match="truncated"):
        list(read_ahead(failing()))
    read = []

    def endless():
        for value in range(10**9):
            read.append(value)
            yield value

    chunks = read_ahead(endless())
    assert next(chunks) == 0
    chunks.close()  # the caller stops: the reader thread ends, having read at most a few ahead
    assert len(read) <= 4
    assert not any(t.name == "surfel-read-ahead" for t in threading.enumerate())


def _raw_ply(path: Path, records: np.ndarray) -> None:
    names = {"<f4": "float", "<f8": "double", "<u2": "ushort"}
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {len(records)}"]
    header += [f"property {names[records.dtype[name].str]} {name}" for name in records.dtype.names]
    path.write_bytes(("\n".join(header + ["end_header"]) + "\n").encode() + records.tobytes())


@pytest.mark.filterwarnings("ignore:overflow encountered in cast")
def test_ply_summaries_are_those_of_the_converted_chunks(tmp_path):
    """The scan pass summarises a binary PLY's chunks in one compiled pass over their records
    (streaming.ply_summaries) as it summarises them converted (corners, sample, zero normals,
    attributes), float and double columns alike, and refuses what converting them refuses:
    NaN positions, normals beyond float32."""
    from surfel.lod.streaming import summarise

    rng = np.random.default_rng(3)
    n = 10_000
    for kind in ("<f4", "<f8"):
        records = np.zeros(n, [(name, kind) for name in ("x", "y", "z", "nx", "ny", "nz")] + [("intensity", "<u2")])
        for name in ("x", "y", "z", "nx", "ny", "nz"):
            records[name] = rng.normal(size=n) * (100.0 if name in "xyz" else 1.0)
        records["intensity"] = rng.integers(0, 5, n)
        for name in ("nx", "ny", "nz"):
            records[name][4321] = 0.0  # a placeholder, in the second chunk
        _raw_ply(tmp_path / "in.ply", records)
        source = open_inputs(tmp_path / "in.ply")[0]
        fast = list(source.ply_summaries(7, 3_000))
        slow = [summarise(chunk, 7, "ply") for chunk in source.chunks(3_000)]
        assert len(fast) == len(slow) == 4 and [s.zero_normals for s in fast] == [False, True, False, False]
        for a, b in zip(fast, slow, strict=True):
            assert np.array_equal(a.lo, b.lo) and np.array_equal(a.hi, b.hi) and a.count == b.count
            assert a.sample.dtype == np.float64 and a.sample.tobytes() == b.sample.tobytes()
            assert a.attributes.keys() == b.attributes.keys() == {"intensity"}
            assert np.array_equal(a.attributes["intensity"], b.attributes["intensity"])
    for name, value in (("y", np.nan), ("nz", 1e300)):
        bad = records.copy()
        bad[name][5_000] = value
        _raw_ply(tmp_path / "bad.ply", bad)
        source = open_inputs(tmp_path / "bad.ply")[0]
        with pytest.raises(InputError) as fast_error:
            list(source.ply_summaries(7, 3_000))
        with pytest.raises(InputError) as slow_error:
            list(source.chunks(3_000))
        assert str(fast_error.value) == str(slow_error.value)


WARM_UP_THEN_PARTITION = """
import sys
import numpy as np
from numba.core.registry import CPUDispatcher
from surfel.attributes import Schema
from surfel.cloud import PointCloud
from surfel.lod import binning, outofcore
from surfel.preprocess import complete

bins, normals, geospatial = (arg == "1" for arg in sys.argv[1:])
tasks, after = outofcore.warm_up_tasks(bins, normals, geospatial)
assert (binning.warm_up in tasks) == bins
assert set(after.values()) == {0} and len(after) == 2  # the neighbour search comes first
for index in (0, *after):
    tasks[index]()


def signatures():
    return {(name, key, str(signature)) for name, module in list(sys.modules.items())
            if name.startswith("surfel.preprocess.") for key, value in vars(module).items()
            if isinstance(value, CPUDispatcher) for signature in value.signatures}


before = signatures()
records = np.zeros(3000, binning.record_dtype(normals, False, Schema()))
records["p"] = np.random.default_rng(2).random((3000, 3)) * [100.0, 100.0, 5.0]
if normals:
    records["n"] = [0.0, 0.0, 1.0]
complete(PointCloud(records["p"], normals=records["n"] if normals else None, geospatial=geospatial), progress=False)
print(sorted(signatures() - before))
"""


@pytest.mark.parametrize("needs", ["110", "001"], ids=["ply with normals", "las"])
def test_the_warm_up_compiles_what_a_partition_needs(needs):
    """The workers' warm-up follows the input: no binning where this process bins (LAS), and a
    completion that estimates normals where the input has none, so that building a partition
    afterwards needs no preprocessing kernel of its own (each a second or more to compile in
    every worker on the first build). In a fresh process, whose kernels come from numba's
    cache: the kernels a partition needs are exactly those the warm-up loaded."""
    import subprocess
    import sys

    run = subprocess.run([sys.executable, "-c", WARM_UP_THEN_PARTITION, *needs], capture_output=True, text=True,
                         timeout=600)
    assert run.returncode == 0, run.stderr
    assert run.stdout.strip() == "[]"


def test_workers_share_the_warm_up(monkeypatch):
    """Every warm-up task is run first by one worker alone, a task that needs another starts
    after it, both workers take tasks, and each worker, once it has finished (as before its
    first partition), has run every task once (the others' loading their kernels from numba's
    cache): what lets the pool compile each kernel once from an empty cache."""
    import threading
    import time
    from multiprocessing import get_context

    log = []
    lock = threading.Lock()

    def task(index):
        def run():  # the first run compiles (takes a while), later ones load from the cache
            with lock:
                fresh = all(entry[2] != index for entry in log)
                log.append(("start", threading.current_thread().name, index))
            time.sleep((0.3 if index in (0, 4) else 0.05) if fresh else 0.0)
            with lock:
                log.append(("end", threading.current_thread().name, index))
        return run

    monkeypatch.setattr(outofcore, "warm_up_tasks", lambda *needs: ([task(i) for i in range(5)], {3: 0, 4: 0}))
    context = get_context("spawn")
    taken, done = context.Value("i", 0), [context.Event() for _ in range(5)]
    def worker():
        outofcore._start_worker(taken, done, (True, True, False))
        worker_warm_up.finish()

    workers = [threading.Thread(target=worker, name=f"w{i}") for i in range(2)]
    for worker in workers:
        worker.start()
    for worker in workers:
        worker.join(30)
    runs = {(who, index) for kind, who, index in log if kind == "start"}
    assert len(runs) == 10 == len(log) // 2  # each worker ran each task once
    first = {}
    for at, (_, who, index) in enumerate(log):
        first.setdefault(index, (who, at))
    for index, (who, _) in first.items():
        other_start = next(i for i, e in enumerate(log) if e[0] == "start" and e[2] == index and e[1] != who)
        assert other_start > log.index(("end", who, index))  # never two fresh runs of one task
    end_of_0 = log.index(("end", first[0][0], 0))
    assert all(first[i][1] > end_of_0 for i in (3, 4))
    assert {who for who, _ in first.values()} == {"w0", "w1"}
