"""Issue 15, the input side: outputs that are not regular files, image sizes beyond what
OpenGL allows, files whose sizes lie, corrupt LOD containers, degenerate meshes and
coordinates at the edges of float range. Each refusal is one line naming the file or option,
exit status 2, nothing written."""

import json
import os
import socket
import stat
import struct
import tracemalloc
import warnings
from pathlib import Path

import numpy as np
import pytest

from conftest import assert_refused, invoke, requires_gl
from surfel.errors import InputError, SurfelError
from surfel.files import write_atomically
from surfel.io import load

DATA = Path(__file__).parent / "data"


# ---- 15.1: -o never replaces what is not a regular file ------------------------------------

def test_special_files_are_never_replaced(tmp_path):
    fifo = tmp_path / "pipe.png"
    os.mkfifo(fifo)
    with pytest.raises(SurfelError, match="pipe.png: cannot write: it exists and is a FIFO"):
        write_atomically(fifo, b"data")
    assert stat.S_ISFIFO(os.lstat(fifo).st_mode)
    (tmp_path / "folder.png").mkdir()
    with pytest.raises(SurfelError, match="is a directory"):
        write_atomically(tmp_path / "folder.png", b"data")
    with socket.socket(socket.AF_UNIX) as server:
        server.bind(str(tmp_path / "socket.png"))
        with pytest.raises(SurfelError, match="socket"):
            write_atomically(tmp_path / "socket.png", b"data")
    with pytest.raises(SurfelError, match="character device"):
        write_atomically("/dev/null", b"data")
    os.symlink(fifo, tmp_path / "to-pipe.png")
    with pytest.raises(SurfelError, match="FIFO"):
        write_atomically(tmp_path / "to-pipe.png", b"data")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["folder.png", "pipe.png", "socket.png", "to-pipe.png"]


def test_a_symbolic_link_is_written_through_and_kept(tmp_path):
    (tmp_path / "real").mkdir()
    target = tmp_path / "real" / "a.png"
    target.write_bytes(b"old")
    target.chmod(0o640)
    link = tmp_path / "link.png"
    os.symlink(target, link)
    write_atomically(link, b"new")
    assert link.is_symlink() and os.readlink(link) == str(target)
    assert target.read_bytes() == b"new" and stat.S_IMODE(target.stat().st_mode) == 0o640
    dangling = tmp_path / "dangling.png"
    os.symlink(tmp_path / "real" / "b.png", dangling)
    write_atomically(dangling, b"made")
    assert dangling.is_symlink() and (tmp_path / "real" / "b.png").read_bytes() == b"made"
    assert sorted(p.name for p in (tmp_path / "real").iterdir()) == ["a.png", "b.png"]  # no temporary left


def test_the_command_line_refuses_special_outputs_before_rendering(tmp_path):
    fifo = tmp_path / "out.png"
    os.mkfifo(fifo)
    assert_refused(invoke("render", "--demo", "-o", fifo, "--size", "32x32"), "out.png", "FIFO")
    assert_refused(invoke("render", "--demo", "-o", tmp_path / "x.png", "--stats", "/dev/null", "--size", "32x32"),
                   "/dev/null", "character device")
    assert not (tmp_path / "x.png").exists() and stat.S_ISFIFO(os.lstat(fifo).st_mode)
    (tmp_path / "real.lod").mkdir()
    os.symlink(tmp_path / "real.lod", tmp_path / "link.lod")
    source = tmp_path / "in.xyz"
    source.write_text("0 0 0\n1 0 0\n0 1 0\n1 1 0\n")
    assert_refused(invoke("lod", "build", source, "-o", tmp_path / "link.lod"), "link.lod", "symbolic link")
    assert (tmp_path / "link.lod").is_symlink()


# ---- 15.2: image sizes beyond what the backend can hold -------------------------------------

@requires_gl
@pytest.mark.parametrize("args", [["--size", "1x268435456"], ["--size", "16385x64", "--backend", "gl"],
                                  ["--size", "4096x4096", "--supersample", "4"],
                                  ["--size", "2048x2048", "--supersample", "8"],
                                  ["--size", "4096x64", "--method", "mesh", "--supersample", "8"]])
def test_render_targets_beyond_the_contexts_limits_are_refused(tmp_path, args):
    out = tmp_path / "x.png"
    assert_refused(invoke("render", "--demo", "-o", out, *args), "--size/--supersample")
    assert not out.exists()


@requires_gl
def test_each_side_is_checked_against_the_context():
    from surfel.gl.targets import check_target_size, max_target_side

    side = max_target_side()
    check_target_size(side, 1)
    for size in ((side + 1, 1), (1, side + 1)):
        with pytest.raises(SurfelError, match=f"limit of {side} pixels a side"):
            check_target_size(*size)


def test_a_default_supersampling_yields_to_the_sample_bounds():
    from surfel.options import fitting_supersample

    assert fitting_supersample(2, 4096, 4096) == 2 and fitting_supersample(2, 4097, 4096) == 1  # CPU bound
    assert fitting_supersample(2, 100, 100, side_limit=199) == 1 and fitting_supersample(3, 100, 100, 250) == 2


@requires_gl
def test_the_default_method_takes_fewer_samples_rather_than_fail(tmp_path):
    """phong's 2x2 samples are a default, not a request: an image whose 2x2 samples would
    outgrow the context's render targets is rendered at one sample; asked for, the same
    samples are refused."""
    from surfel.gl.targets import max_target_side

    size = f"{max_target_side() - 300}x64"
    out, stats = tmp_path / "x.png", tmp_path / "s.json"
    result = invoke("render", "--demo", "-o", out, "--size", size, "--backend", "gl", "--stats", stats)
    assert result.exit_code == 0, result.output
    assert json.loads(stats.read_text())["supersample"] == 1
    asked = invoke("render", "--demo", "-o", tmp_path / "y.png", "--size", size, "--backend", "gl",
                   "--supersample", "2")
    assert_refused(asked, "--size/--supersample")


def test_cpu_renders_have_their_own_bound(tmp_path):
    out = tmp_path / "x.png"
    assert_refused(invoke("render", "--demo", "-o", out, "--method", "ewa", "--backend", "cpu",
                          "--size", "8192x8192", "--supersample", "2"), "--size/--supersample", "CPU")
    assert_refused(invoke("render", "--demo", "-o", out, "--method", "mls", "--size", "4096x4096",
                          "--supersample", "3"), "--size/--supersample", "CPU")
    assert not out.exists()


# ---- 15.3: allocations bounded by what the file can really hold ------------------------------

def patched(source, target, offset, fmt, value):
    data = bytearray(source.read_bytes())
    struct.pack_into(fmt, data, offset, value)
    target.write_bytes(bytes(data))
    return target


def laszip_payload(data: bytes) -> int:
    """Where the LASzip VLR's payload starts."""
    offset, = struct.unpack_from("<H", data, 94)
    for _ in range(struct.unpack_from("<I", data, 100)[0]):
        if data[offset + 2:offset + 18].rstrip(b"\0") == b"laszip encoded":
            return offset + 54
        offset += 54 + struct.unpack_from("<H", data, offset + 20)[0]
    raise AssertionError("no LASzip VLR")


def test_a_laz_point_count_must_fit_its_chunk_table(tmp_path):
    source = DATA / "autzen_trim.laz"  # 110,000 points in three chunks of 50,000
    # 50 points a byte: what the old bound on LAZ allowed, 30 million points for this file
    lying = patched(source, tmp_path / "count.laz", 107, "<I", 50 * source.stat().st_size)
    with pytest.raises(InputError, match="claims 30167650 points, but its chunk table holds at most 150000"):
        load(lying)
    # a count the table allows but the chunks do not hold
    with pytest.raises(InputError, match="the point data ends before the 149999 points"):
        load(patched(source, tmp_path / "within.laz", 107, "<I", 149_999))
    # a chunk size that lies: decoding in pieces stops where the data does
    data = source.read_bytes()
    chunk_size = patched(source, tmp_path / "chunk.laz", laszip_payload(data) + 12, "<I", 1 << 31)
    patched(chunk_size, chunk_size, 107, "<I", 30_000_000)
    with pytest.raises(InputError, match="the point data ends before the 30000000 points"):
        load(chunk_size)


def test_a_laz_of_identical_points_packs_more_than_50_a_byte(tmp_path):
    laspy = pytest.importorskip("laspy")
    n = 500_000
    las = laspy.LasData(laspy.LasHeader(point_format=0, version="1.2"))
    las.x = las.y = las.z = np.zeros(n)
    las.write(tmp_path / "same.laz")
    assert n / (tmp_path / "same.laz").stat().st_size > 100  # LASzip's arithmetic coder on repeated points
    assert len(load(tmp_path / "same.laz")) == n


def ply_with_lists(path, rng, n, big_endian=False):
    """A binary PLY mesh: vertices with two list properties of varying lengths (skipped by the
    reader) and faces that are triangles and quads, with a per-face scalar and a second list."""
    order = ">" if big_endian else "<"
    positions = rng.normal(size=(n, 3)).astype(np.float32)
    sides = rng.integers(3, 5, size=n // 2)
    polygons = [rng.choice(n, size=k, replace=False) for k in sides]
    header = (f"ply\nformat binary_{'big' if big_endian else 'little'}_endian 1.0\nelement vertex {n}\n"
              "property float x\nproperty list uchar short tags\nproperty float y\nproperty float z\n"
              "property list ushort uint more\n"
              f"element face {len(polygons)}\nproperty uchar flag\nproperty list uchar int vertex_indices\n"
              "property list uchar float texcoord\nend_header\n").encode()
    body = bytearray()
    for i, (x, y, z) in enumerate(positions):
        tags, more = i % 3, (i * 7) % 4
        body += struct.pack(f"{order}fB{tags}hff", x, tags, *range(tags), y, z)
        body += struct.pack(f"{order}H{more}I", more, *range(more))
    for k, polygon in enumerate(polygons):
        body += struct.pack(f"{order}BB{len(polygon)}iB2f", k % 2, len(polygon), *polygon, 2, 0.5, 0.5)
    path.write_bytes(header + bytes(body))
    return positions, polygons


@pytest.mark.parametrize("big_endian", [False, True])
def test_ply_lists_of_varying_lengths_are_read_exactly(tmp_path, big_endian):
    from surfel.io.mesh import triangles_from_polygons

    rng = np.random.default_rng(5)
    positions, polygons = ply_with_lists(tmp_path / "m.ply", rng, 40, big_endian)
    cloud = load(tmp_path / "m.ply")
    lengths = np.array([len(p) for p in polygons])
    triangles = triangles_from_polygons(lengths, np.concatenate(polygons), 40, "m.ply")
    used = np.unique(triangles)
    np.testing.assert_array_equal(cloud.positions, positions[used])
    np.testing.assert_array_equal(used[cloud.faces], triangles)


def test_ply_lists_of_varying_lengths_use_memory_like_the_file(tmp_path):
    """A vertex element of small records, each with ten list properties, one of varying
    length: record by record in Python this took 60 times the file (issue 15.3)."""
    n = 300_000
    header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {n}\nproperty uchar x\nproperty uchar y\n"
              "property uchar z\n" + "".join(f"property list uchar int l{k}\n" for k in range(10))
              + "end_header\n").encode()
    records = np.zeros((n, 13), np.uint8)
    records[:, :3] = np.random.default_rng(0).integers(0, 255, (n, 3))
    body = records.tobytes()
    body = body[:3] + b"\x01\x00\x00\x00\x00" + body[4:]  # the first record's first list holds one item
    (tmp_path / "lists.ply").write_bytes(header + body)
    load(tmp_path / "lists.ply")  # compile the walks first: numba's own allocations are not the file's
    tracemalloc.start()
    try:
        cloud = load(tmp_path / "lists.ply")
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert len(cloud) == n
    assert peak < 6 * len(body)  # the packed scalars, then float64 positions (24 bytes a point)


def test_an_npz_decompression_bomb_is_refused_before_it_is_inflated(tmp_path):
    bomb = tmp_path / "bomb.npz"
    np.savez_compressed(bomb, positions=np.zeros((2_000_000, 3)))  # 48 MB of zeros in some 50 kB
    tracemalloc.start()
    try:
        with pytest.raises(InputError, match="bomb.npz: NPZ arrays would expand .* a decompression bomb"):
            load(bomb)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 1 << 20
    # an ignored member is never inflated: a grid with a bomb beside it loads
    g = np.stack(np.meshgrid(np.arange(300.0), np.arange(300.0)), -1).reshape(-1, 2)
    grid = np.column_stack([g, np.zeros(len(g))])  # the most compressible real layout, about 13 times
    np.savez_compressed(tmp_path / "grid.npz", positions=grid, notes=np.zeros((3000, 3000)))
    np.testing.assert_array_equal(load(tmp_path / "grid.npz").positions, grid)


# ---- 15.5: corrupt LOD containers ----------------------------------------------------------

@pytest.fixture(scope="module")
def hierarchies(tmp_path_factory):
    """A .lod directory and a .lod.npz file of 3,000 points on a sphere."""
    from surfel.lod import build_lod, save_lod
    from surfel.lod.outofcore import build_outofcore
    from surfel.preprocess import complete

    folder = tmp_path_factory.mktemp("lod")
    rng = np.random.default_rng(0)
    p = rng.normal(size=(3000, 3))
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    np.savetxt(folder / "sphere.xyz", p)
    build_outofcore(folder / "sphere.xyz", folder / "sphere.lod", progress=False)
    save_lod(build_lod(complete(load(folder / "sphere.xyz"))[0], progress=False), folder / "sphere.lod.npz")
    return folder


def _without(key):
    return lambda m, root: {k: v for k, v in m.items() if k != key}


def _partition(**changes):
    return lambda m, root: {**m, "partitions": [{**m["partitions"][0], **changes}]}


def _shorten(name, rows):
    def edit(m, root):
        array = np.load(root / "part-00000" / name)
        np.save(root / "part-00000" / name, array[:rows])
        return m
    return edit


def _move_outside(m, root):
    os.rename(root / "part-00000", root.parent / f"{root.name}-x")
    return {**m, "partitions": [{**m["partitions"][0], "name": f"../{root.name}-x"}]}


@pytest.mark.parametrize("case, edit, words", [
    ("list", lambda m, root: [m], "the LOD manifest is a JSON list, not an object"),
    ("no-partitions", _without("partitions"), "the LOD manifest lacks 'partitions'"),
    ("no-bounds", _without("bounds"), "the LOD manifest lacks 'bounds'"),
    ("no-colors", _without("colors"), "the LOD manifest lacks 'colors'"),
    ("empty", lambda m, root: {**m, "partitions": []}, "lists no partitions"),
    ("bounds", lambda m, root: {**m, "bounds": [[0, 0], [1, 1, "a"]]}, "'bounds' is not two corners"),
    ("count", lambda m, root: {**m, "top_nodes": "3"}, "'top_nodes' is not a whole number"),
    ("name", _partition(name=7), "partition 'name' is not a name: 7"),
    ("radius", _partition(max_radius="x"), "'max_radius' is not a number"),
    ("nodes", _partition(nodes=10 ** 9), "lod_emax.npy holds float32 (4738,); the manifest calls for float"),
    ("short", _shorten("positions.npy", 10), "positions.npy holds float64 (10, 3)"),
    ("outside", _move_outside, "names partition '../outside.lod-x', which is no directory of it"),
])
def test_a_corrupt_lod_directory_is_one_line(hierarchies, tmp_path, case, edit, words):
    import shutil

    root = tmp_path / f"{case}.lod"
    shutil.copytree(hierarchies / "sphere.lod", root)
    manifest = edit(json.loads((root / "manifest.json").read_text()), root)
    (root / "manifest.json").write_text(json.dumps(manifest))
    out = tmp_path / "x.png"
    assert_refused(invoke("render", root, "-o", out, "--size", "32x32"), f"{case}.lod", words)
    assert not out.exists()


@pytest.mark.parametrize("key, value, words", [
    ("lod_emin", lambda z: np.stack([z["lod_emin"]] * 2, 1), "lod_emin must have shape (4738,), got (4738, 2)"),
    ("lod_emax", lambda z: z["lod_emax"][:-1], "lod_emax must have shape (4738,), got (4737,)"),
    ("clip_lines", lambda z: np.zeros((len(z["positions"]), 3, 3), np.float32), "clip_lines must have shape"),
    ("lod_dsuffix", lambda z: np.array(["a"] * len(z["positions"])), "'lod_dsuffix' is not numeric"),
])
def test_wrongly_shaped_lod_arrays_are_one_line(hierarchies, tmp_path, key, value, words):
    with np.load(hierarchies / "sphere.lod.npz") as archive:
        arrays = dict(archive)
    arrays[key] = value(arrays)
    np.savez(tmp_path / "bad.lod.npz", **arrays)
    assert_refused(invoke("render", tmp_path / "bad.lod.npz", "-o", tmp_path / "x.png", "--lod-error", "1"),
                   "bad.lod.npz", words)


def copc_variant(path, entry_count):
    """The test COPC file with every node's point count replaced (hierarchy pages in its EVLR)."""
    data = bytearray((DATA / "simple_with_page.copc.laz").read_bytes())
    offset, count = struct.unpack_from("<QI", data, 235)
    for _ in range(count):
        user, record, length = data[offset + 2:offset + 18].rstrip(b"\0"), *struct.unpack_from("<HQ", data, offset + 18)
        if (user, record) == (b"copc", 1000):
            for entry in range(offset + 60, offset + 60 + length, 32):
                if struct.unpack_from("<i", data, entry + 28)[0] > 0:
                    struct.pack_into("<i", data, entry + 28, entry_count)
        offset += 60 + length
    path.write_bytes(bytes(data))
    return path


def test_corrupt_copc_hierarchies_are_one_line(tmp_path):
    out = tmp_path / "x.png"
    assert_refused(invoke("render", copc_variant(tmp_path / "empty.copc.laz", 0), "-o", out),
                   "empty.copc.laz", "no node holding points")
    assert_refused(invoke("render", copc_variant(tmp_path / "huge.copc.laz", 2 ** 31 - 1), "-o", out),
                   "huge.copc.laz", "claims 2147483647 points")
    assert not out.exists()


# ---- 15.8: one degenerate face does not reject a valid mesh ----------------------------------

def cube_mesh():
    """A unit cube as 12 counter-clockwise triangles (outward normals)."""
    v = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float)
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    return v, np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))])


def write_obj(path, vertices, faces):
    lines = [f"v {x:.17g} {y:.17g} {z:.17g}" for x, y, z in vertices]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in faces]
    path.write_text("\n".join(lines) + "\n")


def write_ply_mesh(path, vertices, faces):
    header = (f"ply\nformat ascii 1.0\nelement vertex {len(vertices)}\nproperty double x\nproperty double y\n"
              f"property double z\nelement face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n")
    body = [f"{x:.17g} {y:.17g} {z:.17g}" for x, y, z in vertices] + [f"3 {a} {b} {c}" for a, b, c in faces]
    path.write_text(header + "\n".join(body) + "\n")


@pytest.mark.parametrize("writer, suffix", [(write_obj, "obj"), (write_ply_mesh, "ply")])
@pytest.mark.parametrize("extra", [[[0.9, 0.9, 1.01]] * 3, [[0.2, 0.5, 1.01], [0.5, 0.5, 1.01], [0.8, 0.5, 1.01]]],
                         ids=["coincident", "collinear"])
def test_a_degenerate_face_apart_from_the_mesh_takes_its_neighbours_normals(tmp_path, writer, suffix, extra):
    vertices, faces = cube_mesh()
    writer(tmp_path / f"cube.{suffix}", vertices, faces)
    writer(tmp_path / f"odd.{suffix}", np.vstack([vertices, extra]), np.vstack([faces, [[8, 9, 10]]]))
    cube, odd = load(tmp_path / f"cube.{suffix}"), load(tmp_path / f"odd.{suffix}")
    np.testing.assert_array_equal(odd.normals[:8], cube.normals)  # the mesh's own normals are untouched
    # the extra vertices lie just above the top face; its nearest vertices' normals point up and out
    nearest = np.argmin(np.linalg.norm(vertices[None] - np.array(extra)[:, None], axis=2), axis=1)
    np.testing.assert_array_equal(odd.normals[8:], cube.normals[nearest])
    assert odd.is_mesh and len(odd.faces) == 13


def test_the_command_line_renders_and_compares_a_mesh_with_a_degenerate_face(tmp_path):
    vertices, faces = cube_mesh()
    write_obj(tmp_path / "odd.obj", np.vstack([vertices, [[0.5, 0.5, 0.5]] * 3]), np.vstack([faces, [[8, 9, 10]]]))
    for command in ("render", "compare"):
        result = invoke(command, tmp_path / "odd.obj", "-o", tmp_path / f"{command}.png", "--size", "32x32")
        assert result.exit_code == 0, result.output
        assert (tmp_path / f"{command}.png").exists()


# ---- 15.9: one policy for zero-length placeholder normals ------------------------------------

def test_render_and_every_lod_build_agree_on_placeholder_normals(tmp_path):
    from surfel.lod import load_lod

    rng = np.random.default_rng(0)
    p = rng.normal(size=(3000, 3))
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    records = np.zeros(len(p), [(k, "<f8") for k in "xyz"] + [(f"n{k}", "<f4") for k in "xyz"])
    for i, k in enumerate("xyz"):
        records[k], records[f"n{k}"] = p[:, i], p[:, i]
    placeholders = np.arange(0, len(p), 100)
    for k in "xyz":
        records[f"n{k}"][placeholders] = 0
    header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(p)}\n"
              + "".join(f"property double {k}\n" for k in "xyz") + "".join(f"property float n{k}\n" for k in "xyz")
              + "end_header\n")
    (tmp_path / "in.ply").write_bytes(header.encode() + records.tobytes())
    assert load(tmp_path / "in.ply").normals is None  # a file with placeholders has no normals: estimated
    for name in ("out.lod", "out.lod.npz", "out.copc.laz"):
        result = invoke("lod", "build", tmp_path / "in.ply", "-o", tmp_path / name)
        assert result.exit_code == 0, (name, result.output)
    leaves = {}
    seq = load_lod(tmp_path / "out.lod.npz")
    leaf = seq.attributes["lod_emin"] == 0
    leaves["lod.npz"] = (seq.positions[leaf], seq.normals[leaf])
    part = tmp_path / "out.lod" / "part-00000"
    positions, normals = np.load(part / "positions.npy"), np.load(part / "normals.npy")
    leaf = np.load(part / "lod_emin.npy") == 0
    leaves["lod"] = (positions[leaf], normals[leaf])
    for name, (positions, normals) in leaves.items():
        order = np.lexsort(positions.T)
        positions, normals = positions[order], normals[order]
        expected = p[np.lexsort(p.T)]
        np.testing.assert_array_equal(positions, expected)
        # estimated from the neighbours, every one (the placeholders too) along the sphere's normal
        assert np.abs(np.einsum("ij,ij->i", normals, expected)).min() > 0.99, name


# ---- 15.10: coordinates and scales at the edges of float range --------------------------------

def spot_at(scale: float, offset: float = 0.0, *, mesh: bool = False):
    from surfel.cloud import PointCloud
    from surfel.data import demo_cloud

    spot = demo_cloud()
    positions = spot.positions - spot.positions.mean(axis=0)
    return PointCloud(positions * scale + offset, normals=spot.normals, faces=spot.faces if mesh else None,
                      source=f"spot x{scale:g} + {offset:g}")


@requires_gl
@pytest.mark.parametrize("method", ["deferred", "object-space", "ewa", "mesh"])
def test_clouds_far_from_unit_scale_render_as_at_unit_scale(method):
    """Spot 1e-25 and 1e25 units across: every method's float32 arithmetic and tolerances
    (object-space EWA held only from 1e-7 to 1e9) work at unit scale, so the images match and
    depths scale with the cloud."""
    from surfel.rendering import Renderer, default_camera

    reference = None
    for scale in (1.0, 2.0 ** -80, 1e-25, 1e25):
        cloud = spot_at(scale, mesh=method == "mesh")
        result = Renderer().render(cloud, default_camera(cloud, (64, 64)), method)
        if reference is None:
            reference = result
            continue
        np.testing.assert_allclose(result.color, reference.color, atol=2e-3, err_msg=f"{scale:g}")
        covered = np.isfinite(reference.depth)
        np.testing.assert_array_equal(np.isfinite(result.depth), covered)
        np.testing.assert_allclose(result.depth[covered], reference.depth[covered] * np.float32(scale), rtol=1e-5)


@requires_gl
@pytest.mark.parametrize("color_range", [None, (-0.2, 0.3)])
def test_elevation_colours_do_not_change_with_scale(color_range):
    """Elevation is a length: a range given in the cloud's units, or the default percentiles,
    colour the same points the same at any scale, and the stats report the cloud's units."""
    from surfel.rendering import Renderer, default_camera

    reference = None
    for scale in (1.0, 1e-25, 1e25):
        cloud = spot_at(scale)
        given = None if color_range is None else (color_range[0] * scale, color_range[1] * scale)
        result = Renderer().render(cloud, default_camera(cloud, (64, 64)), "points", color="elevation",
                                   color_range=given, shading="none")
        lo, hi = result.stats["color_range"]
        if reference is None:
            reference, reference_range = result, (lo, hi)
            continue
        np.testing.assert_allclose((lo / scale, hi / scale), reference_range, rtol=1e-6)
        np.testing.assert_allclose(result.color, reference.color, atol=2e-3, err_msg=f"{scale:g}")


def test_clouds_beyond_float_range_are_refused_naming_the_file(tmp_path):
    from surfel.data import demo_cloud

    positions = demo_cloud().positions.astype(np.float64)
    out = tmp_path / "x.png"
    for name, coordinates, words in [
        ("huge.npz", positions * 1e50, "units across; surfel renders clouds"),
        ("tiny.npz", positions * 1e-40, "units across; surfel renders clouds"),
        ("far.npz", positions + 1e15, "are resolved only to 0.125 in float64"),
        ("point.npz", np.full((4, 3), 1e50), "its points coincide at coordinates as large as 1e+50"),
    ]:
        np.savez(tmp_path / name, positions=coordinates)
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # nothing leaks from numpy either
            result = invoke("render", tmp_path / name, "-o", out, "--size", "32x32")
        assert_refused(result, name, words)
    assert not out.exists()


def test_a_cloud_1e_minus_30_across_is_framed_and_drawn(tmp_path):
    """The fixed 1e-9 floor of the framing radius left such clouds blank."""
    np.savez(tmp_path / "small.npz", positions=spot_at(1e-30).positions)
    result = invoke("render", tmp_path / "small.npz", "-o", tmp_path / "small.png", "--size", "64x64",
                    "--method", "ewa", "--backend", "cpu")
    assert result.exit_code == 0, result.output
    from PIL import Image

    alpha = np.asarray(Image.open(tmp_path / "small.png"))[..., 3]
    assert 0.1 < (alpha > 127).mean() < 0.5
