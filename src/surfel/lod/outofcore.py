"""Out-of-core construction of a sequential point tree (Dachsbacher et al. 2003, survey 2.2)
for clouds larger than memory: a hierarchy directory read lazily by `surfel.lod.lazy`.

The input (binary PLY read in chunks at file offsets, LAS/LAZ through laspy's chunk
iterator, a directory of such tiles as one cloud; other formats are loaded whole: see
streaming.py) is read twice and never held in memory, each chunk read by a background thread
while the one before is processed (`streaming.read_ahead`):

1. scan (a binary PLY's positions and normals summarised in one compiled pass over its
   records, not converted: streaming.ply_summaries): bounds, for LAS the colour range (8-bit
   values in 16-bit fields), the kinds of the attributes (streaming.KindVote), whether the
   normals hold zero placeholders (the input then counts as having none, as every reader
   has it: `cloud.file_normals`), and an
   even sample of HISTOGRAM_SAMPLE positions (every s-th point, s = ceil(N / HISTOGRAM_SAMPLE);
   all of them in smaller inputs). The sample's point counts of the 2^7 x 2^7 x 2^7 cells of
   the bounding cube, times N / (sample size), estimate the histogram; the cube is split
   octree-wise, a cell being split while it holds more than `cap` points, into partitions
   (the non-empty leaves of that octree), where
       cap = (memory - MEMORY_OVERHEAD - w WORKER_OVERHEAD) / (w (BYTES_PER_POINT + ATTRIBUTE_COPIES * a))
   (a: the bytes of one point's attributes; w: the partitions built at once, `worker_count`,
   WORKER_OVERHEAD only when w > 1) bounds the points the w partitions' processing holds at
   once; with w > 1, cap is at most N / (PARTITIONS_PER_WORKER w), so that no worker idles
   while another builds a large last partition (one partition in this process uses the
   cores far less well). A sampled histogram is planned with cap (1 - 3 sqrt(s / cap)),
   three standard errors of a sampled count, and cells where the sample has no point join the partition of
   the nearest cell that has one;
2. binning: each chunk's points, with all their attributes, are appended to their
   partition's file, and to the halo files of the partitions within the halo width h of
   them (binning.py): h = HALO_SPACINGS sample spacings, the spacing estimated from the
   median count m of the occupied histogram cells as of an evenly sampled surface,
   cell / sqrt(m), at most HALO_MAX_CELLS cells. With w > 1 workers a binary PLY input is
   binned by them, each a contiguous run of its chunks (binning.py's pieces).

Each partition is then loaded with its halo, each sorted by Morton code (`_in_morton_order`:
the completion and the tree then gather from nearby rows instead of the input's order, and
the tree's own sort of those codes finds them nearly sorted: the 20M-point build 5% faster, its
output byte-identical), completed (radii and tangent axes estimated as
for any cloud, `preprocess.complete`; normals from the input when it has them), stripped of
its halo, built (`build_lod`), sequentialised (`to_sequential_cloud`) and written as raw .npy
arrays in sequential order. With the halo, the neighbour queries of points at a partition
border find the neighbours across it, so their radii, axes and clip lines are those of the
in-memory build (where the halo reaches far enough: two hops of neighbours on an evenly
sampled surface). Inputs of PARALLEL_MIN_POINTS or more are built by a pool of w worker
processes, one partition each at a time on one core, largest first. The workers start with
the input's scan and load their numba kernels; the first build after an install compiles
them, each worker its share (worker_warm_up.py). A worker ends itself once the building
process has gone, however it went (`_exit_with_the_build`).

Top levels: the partition roots become the leaves of a small tree built by the same merge
rule (`build._merge_cells`, attributes by `build.aggregate_attributes` from the roots'), so
that a far view draws a few disks instead of every root. A
partition root enters it as a disk at the root's centre and normal whose radius R and
normal slab [lo, hi] bound all of the partition's leaf disks (with d_i = c_i - c, the leaf
disk of radius r_i and normal n_i, dn_i = d_i . n, s_i = |n_i x n|):

    R  = max_i |d_i - dn_i n| + r_i,     lo = min_i dn_i - r_i s_i,     hi = max_i dn_i + r_i s_i

(the merge rule's leaf case), with area weight sum_i |u_i| |v_i|. Every top node is then a
disk covering all leaf disks below it, e_g stays monotone along every path, and each
partition root's r_max becomes the e_g of its top-tree parent (instead of infinity) with
its d_parent to it: the partitions and the top tree together are one sequential point tree,
so the union of their selections is the cut of test (2) in sequential.py: no holes, no
double layers beyond that test's band.

Layout of NAME.lod/ (format "surfel-lod-dir", version 1):

    manifest.json      format, version, geospatial, total_points, nodes, bounds [lo, hi],
                       colors, attributes (the JSON schema of the stored attributes, see
                       surfel.attributes: the input's, and clip_lines when estimated),
                       top_nodes, and per partition: name, points, nodes, bounds (of its
                       leaves, hence of all its node centres), max_radius (its root's)
    part-NNNNN/*.npy   one partition in sequential order, the arrays of a .lod.npz file
                       (format.py: positions, normals, [colors], radii, axes, lod_emin,
                       lod_emax, lod_dparent, lod_dsuffix), and attribute i of the
                       manifest's schema as attribute-<i>.npy; row 0 is the partition root
    top/*.npy          the top-tree nodes (absent with one partition), likewise

Files: everything is written into NAME.partial/; a finished partition is a directory
renamed into place, its arrays dropped from the page cache once the disk has them (where the
OS can: pages.drop_when_written, while the worker goes on), so that the next partition's
writes reuse those pages:
the build's page cache stays about one partition per worker instead of the whole output, and
fresh pages cost far more than reused ones where memory is lent by a hypervisor (20M points
on 2 cores of a VM: the writes took 14.4 s of the workers' time, 13.2 of it in the kernel;
now 4.1 s). manifest.json is written last and NAME.partial/ is then renamed to NAME. An
interrupted build leaves only NAME.partial/ (never a complete-looking NAME); `resume=True`
reuses its binning and finished partitions when the input is unchanged.
"""

from __future__ import annotations

import functools
import json
import math
import os
import re
import shutil
import threading
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from contextlib import ExitStack
from multiprocessing import get_context, parent_process
from pathlib import Path

import numba
import numpy as np

from ..attributes import Schema
from ..cloud import PointCloud
from ..errors import SurfelError
from ..files import write_atomically, write_json
from ..pages import drop_when_written, keep_freed_memory, no_huge_pages
from ..preprocess import INACTIVE_CLIP
from . import binning, worker_warm_up
from .binning import bin_input, piece_files, progress_bar, record_dtype
from .build import (
    ROOT_PARENT_ERROR,
    _merge_cells,
    _next_level,
    aggregate_attributes,
    build_lod,
    morton_codes,
    morton_order,
)
from .sequential import EXTRAS, r_max_bucket, to_sequential_cloud
from .streaming import StreamInput, open_inputs

DIR_FORMAT = "surfel-lod-dir"
DIR_VERSION = 1
PARTIAL_LAYOUT = 2  # how NAME.partial/ holds bins and partitions: a resume needs the same
MANIFEST = "manifest.json"
# memory the process needs besides one partition: interpreter, numpy/numba/scipy, input chunks
MEMORY_OVERHEAD = 900 << 20
# peak bytes per point while a partition is completed, built and sequentialised (measured
# ~350: input, k-nearest-neighbour lists, 2n tree nodes, their sequential copy; with margin)
BYTES_PER_POINT = 500
# ... plus this many copies of each point's attributes (the input, up to 2n tree nodes,
# their sequential copy)
ATTRIBUTE_COPIES = 5
# memory of each worker process besides its partition (interpreter, numpy/numba/scipy)
WORKER_OVERHEAD = 400 << 20
# inputs of at least this many points are built by a pool of worker processes
PARALLEL_MIN_POINTS = 1_000_000
# ... in at least this many partitions per worker (largest first: the last ones are small)
PARTITIONS_PER_WORKER = 4
_SIZE = re.compile(r"^\s*([0-9]*\.?[0-9]+)\s*([kmgt]?)(i?b)?\s*$", re.IGNORECASE)


def parse_size(text: str) -> int:
    """Bytes of a size such as 512MB, 4GB, 1.5G, 300000000 (powers of 1024)."""
    match = _SIZE.match(str(text))
    if not match:
        raise SurfelError(f"cannot read the size {text!r} (use e.g. 512MB or 4GB)")
    value, unit = float(match.group(1)), match.group(2).lower()
    return int(value * 1024 ** " kmgt".index(unit or " "))


# --------------------------------------------------------------------------------------------
# planning


def partition_capacity(memory: int, attribute_bytes: int = 0, workers: int = 1) -> int:
    """Points one partition may hold under the memory budget, with `attribute_bytes` of
    attributes per point, while `workers` processes build one partition each (more than one:
    each is a process of its own, WORKER_OVERHEAD more)."""
    per_point = BYTES_PER_POINT + ATTRIBUTE_COPIES * attribute_bytes
    overhead = MEMORY_OVERHEAD + (workers * WORKER_OVERHEAD if workers > 1 else 0)
    cap = (memory - overhead) // (workers * per_point)
    if cap < 10_000:
        raise SurfelError(f"--memory {memory >> 20} MB is too small (need at least "
                          f"{(overhead + 10_000 * workers * per_point) >> 20} MB)")
    return int(cap)


def worker_count(points: int, memory: int, attribute_bytes: int = 0) -> int:
    """The partitions built at once: one per core when the input is large enough to pay for
    starting the worker processes (PARALLEL_MIN_POINTS) and the budget holds them."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    workers = cores if points >= PARALLEL_MIN_POINTS else 1
    while workers > 1:
        try:
            partition_capacity(memory, attribute_bytes, workers)
            return workers
        except SurfelError:
            workers -= 1
    return 1


# --------------------------------------------------------------------------------------------
# the build


def attribute_key(index: int) -> str:
    """The file name (without .npy) of attribute `index` of the manifest's schema in a
    partition or top/: by position, so that any attribute name is safe as a file name."""
    return f"attribute-{index}"


def _input_signature(inputs: list[StreamInput], memory: int, workers: int) -> dict:
    return {"files": [[i.path, os.path.getsize(i.path), os.path.getmtime(i.path)] for i in inputs],
            "memory": memory, "workers": workers, "layout": PARTIAL_LAYOUT}


def build_outofcore(in_path: str | os.PathLike, out_path: str | os.PathLike, *, memory: int = 4 << 30,
                    resume: bool = False, progress: bool | None = None,
                    stats_path: str | os.PathLike | None = None, workers: int | None = None) -> dict:
    """Build the hierarchy directory `out_path` from `in_path` within `memory` bytes, building
    `workers` partitions at once (None: `worker_count`).

    Stats: points, nodes, partitions, top_nodes, ms (wall time of the whole build),
    points_per_s, resumed_partitions.
    """
    start = time.perf_counter()
    out = Path(out_path)
    partial = out.with_name(out.name + ".partial")
    if out.is_symlink():  # replacing the hierarchy would replace the link, not what it names
        raise SurfelError(f"{out}: is a symbolic link; not replacing it (name the directory itself)")
    if out.exists() and not (out / MANIFEST).is_file():
        raise SurfelError(f"{out}: exists and is not a surfel LOD directory; not replacing it")
    inputs = open_inputs(in_path)
    attribute_bytes = sum(spec.dtype.itemsize * spec.components for spec in inputs[0].specs)
    if workers is None:
        workers = worker_count(sum(i.count for i in inputs), memory, attribute_bytes)
    cap = partition_capacity(memory, attribute_bytes, workers)
    if workers > 1:  # enough partitions for every worker to stay busy to the end
        cap = min(cap, -(-sum(i.count for i in inputs) // (PARTITIONS_PER_WORKER * workers)))
    signature = _input_signature(inputs, memory, workers)
    with ExitStack() as stack:
        pool = None
        if workers > 1:  # started now, so that the workers load their kernels while the input is scanned
            context = get_context("spawn")
            # as binning will find them (normals given as placeholders only are estimated too)
            needs = (binning.binned_by_workers(inputs), inputs[0].has_normals, any(i.geospatial for i in inputs))
            events = [context.Event() for _ in warm_up_tasks(*needs)[0]]
            pool = stack.enter_context(ProcessPoolExecutor(
                workers, mp_context=context, initializer=_start_worker,
                initargs=(context.Value("i", 0), events, needs)))
            for _ in range(workers):
                pool.submit(int)
        saved = _plan_and_bin(inputs, partial, cap, signature, resume, progress, pool, workers)
        has_normals, has_colors = saved["has_normals"], saved["has_colors"]
        schema = Schema.from_json(saved["schema"])
        dtype = record_dtype(has_normals, has_colors, schema)
        parts = _build_partitions(partial, saved["counts"], dtype, schema, saved["geospatial"], pool, progress)
        if pool is not None:  # the workers exit (their memory freed) while the top levels are built
            pool.shutdown(wait=False)
        stored = parts[0]["attributes"]
        if any(part["attributes"] != stored for part in parts):
            raise SurfelError(f"{partial}: partitions hold different attributes")
        top = _top_tree(partial, parts, has_colors, Schema.from_json(stored))
    total = sum(saved["counts"])
    geospatial = saved["geospatial"]
    resumed = sum(part.pop("resumed") for part in parts)
    nodes = sum(p["nodes"] for p in parts) + top
    lo = np.min([p["bounds"][0] for p in parts], axis=0)
    hi = np.max([p["bounds"][1] for p in parts], axis=0)
    manifest = {"format": DIR_FORMAT, "version": DIR_VERSION, "geospatial": geospatial,
                "total_points": total, "nodes": nodes, "bounds": [lo.tolist(), hi.tolist()],
                "colors": has_colors, "attributes": stored, "top_nodes": top,
                "partitions": [{"name": p["name"], "points": p["points"], "nodes": p["nodes"],
                                "bounds": p["bounds"], "max_radius": p["radius"]} for p in parts]}
    shutil.rmtree(partial / "bins", ignore_errors=True)
    (partial / "plan.json").unlink()
    write_json(partial / MANIFEST, manifest)
    _replace_dir(partial, out)
    ms = (time.perf_counter() - start) * 1000
    stats = {"points": total, "nodes": nodes, "partitions": len(parts), "top_nodes": top,
             "ms": round(ms, 3), "points_per_s": round(total / max(ms / 1000, 1e-9)),
             "resumed_partitions": resumed, "memory": memory, "partition_cap": cap, "workers": workers}
    if stats_path is not None:
        write_json(stats_path, stats)
    return stats


def _plan_and_bin(inputs: list[StreamInput], partial: Path, cap: int, signature: dict, resume: bool,
                  progress: bool | None, pool: ProcessPoolExecutor | None, workers: int) -> dict:
    """The plan (plan.json) of the build in `partial`: that of the interrupted build when
    resuming, else planned and binned now (passes 1 and 2 of the module docstring)."""
    plan_file = partial / "plan.json"
    saved = json.loads(plan_file.read_text()) if resume and plan_file.exists() else None
    if saved is not None and saved["signature"].get("layout") != PARTIAL_LAYOUT:
        raise SurfelError(f"{partial}: left by another version of surfel, whose bins and partitions this one "
                          "cannot reuse; rerun without --resume")
    if saved is not None and saved["signature"] != signature:
        raise SurfelError(f"{partial}: the input, --memory or the core count changed since the interrupted build; "
                          "rerun without --resume")
    if saved is None:
        if partial.exists():
            shutil.rmtree(partial)
        partial.mkdir(parents=True)
        try:
            saved = bin_input(inputs, partial, cap, signature, progress, pool, workers)
        except BaseException:  # binning cannot be resumed half way: leave nothing behind
            shutil.rmtree(partial, ignore_errors=True)
            raise
        write_json(plan_file, saved)
    return saved


def _build_partitions(partial: Path, counts: list[int], dtype: np.dtype, schema: Schema, geospatial: bool,
                      pool: ProcessPoolExecutor | None, progress: bool | None) -> list[dict]:
    """Build every partition not finished yet, in this process or by the pool's workers
    (module docstring); their root summaries, in partition order, each with "resumed"
    telling whether it was finished."""
    names = [f"part-{index:05d}" for index in range(len(counts))]
    finished = [(partial / name / "root.json").exists() for name in names]
    todo = [i for i in range(len(counts)) if not finished[i]]
    with progress_bar(sum(counts), "lod build", progress) as bar:
        bar.update(sum(c for c, done in zip(counts, finished, strict=True) if done))
        if pool is None or len(todo) < 2:  # one partition: this process, on every core
            from .format import warm_up

            warm_up()
            for i in todo:
                _build_partition(partial, names[i], dtype, schema, geospatial)
                bar.update(counts[i])
        else:
            # largest first: the last partitions to finish are small, so no core idles long
            todo.sort(key=lambda i: -counts[i])
            jobs = {pool.submit(_build_partition_in_worker, partial, names[i], dtype, schema, geospatial): i
                    for i in todo}
            try:
                for job in as_completed(jobs):
                    job.result()
                    bar.update(counts[jobs[job]])
            except BaseException:
                pool.shutdown(wait=True, cancel_futures=True)
                raise
    return [{**json.loads((partial / name / "root.json").read_text()), "resumed": done}
            for name, done in zip(names, finished, strict=True)]


def _start_worker(taken, done, needs: tuple[bool, bool, bool]) -> None:
    """A worker builds one partition at a time on one thread (the pool gives the parallelism);
    it loads its share of the kernels first, sharing their compiling with the other workers,
    and the others' before the first job that needs them (worker_warm_up.py: `taken` and
    `done` are its shared counter and events; `needs` are `warm_up_tasks`' arguments)."""
    _exit_with_the_build()
    numba.set_num_threads(1)
    no_huge_pages()  # as the command line sets it; also when called from Python
    # each chunk binned and each partition built reuses the pages of the one before (binning
    # two halves of a 20M-point input at once: 1.2 s each instead of 1.3-1.45 s)
    keep_freed_memory()
    worker_warm_up.share(*warm_up_tasks(*needs), taken, done)


def _exit_with_the_build() -> None:
    """In a pool's worker: exit as soon as the building process has gone. Killed (a job
    scheduler's SIGKILL, a plain SIGTERM) it cannot stop its pool, whose workers would wait on
    their call queue for ever, each holding its last partition's memory. The parent's sentinel
    (a pipe only it holds open) becomes readable when it exits."""
    parent = parent_process()
    if parent is not None:
        threading.Thread(target=lambda: (parent.join(), os._exit(1)), daemon=True).start()


def _warm_up_tree() -> None:
    """The kernels that build and sequentialise a tree and summarise its root."""
    from . import format

    _root_summary(format.warm_up())


def warm_up_tasks(bins: bool, normals: bool, geospatial: bool) -> tuple[list, dict[int, int]]:
    """The workers' first tasks, in the order they are taken, and {task: the task whose kernels
    it calls} (that one is compiled first, not twice): the binning's if the workers bin
    (`binning.binned_by_workers`), the completion of partitions with or without `normals`.

    From an empty cache they compile in 12, 3, 3, 9 and 9 s (20M points with normals, on a
    2-core AMD EPYC: each worker's share ends after about 21 s; one waits 6 s of it for the
    search, while the main process scans the input on that core); the completion reaches the
    kernels of the borders last, when the other worker has them cached.
    After a render (the demo) only the binning and the tree are left to compile, by one worker
    each."""
    completion = functools.partial(worker_warm_up.completion, normals, geospatial)
    tasks = [worker_warm_up.neighbours, *([binning.warm_up] if bins else []), _warm_up_tree, completion,
             worker_warm_up.borders]
    after = {tasks.index(completion): 0, tasks.index(worker_warm_up.borders): 0}
    return tasks, after


def _build_partition_in_worker(*args) -> None:
    """`_build_partition` in a pool's worker, once it has the kernels of the other workers'
    warm-up tasks (the tree's: before the tree)."""
    worker_warm_up.finish(but=_warm_up_tree)
    _build_partition(*args)


def _replace_dir(partial: Path, out: Path) -> None:
    """Rename the finished partial/ to out, replacing an older out (a directory or a file)."""
    old = out.with_name(out.name + ".old")
    if out.exists() or out.is_symlink():
        if old.exists():
            shutil.rmtree(old)
        os.replace(out, old)
    os.replace(partial, out)
    if old.is_dir():
        shutil.rmtree(old)
    elif old.exists():
        old.unlink()


def _build_partition(partial: Path, name: str, dtype: np.dtype, schema: Schema, geospatial: bool) -> None:
    """Complete, build, sequentialise and write one partition; its root summary last. The
    partition's points are completed together with its halo (module docstring), which is
    then dropped."""
    from ..preprocess import complete

    files = {suffix: piece_files(partial / "bins", name, suffix) for suffix in ("bin", "halo")}
    own = [np.fromfile(file, dtype) for file in files["bin"]]
    count = sum(len(piece) for piece in own)
    records = np.concatenate(own + [np.fromfile(file, dtype) for file in files["halo"]])
    del own
    records = _in_morton_order(records, count)
    cloud = PointCloud(records["p"], normals=records["n"] if "n" in dtype.names else None,
                       colors=records["c"] if "c" in dtype.names else None, geospatial=geospatial,
                       attributes={spec.name: records[f"a{i}"] for i, spec in enumerate(schema.values())},
                       kinds=schema.kinds, source=name)
    del records
    cloud, _ = complete(cloud, progress=False)
    if len(cloud) > count:
        cloud = cloud.take(slice(0, count))
    cloud, _ = complete(cloud, progress=False)
    points = len(cloud)
    lo, hi = cloud.bounds
    worker_warm_up.finish(_warm_up_tree)  # in a pool's worker: the other may still compile them
    tree = build_lod(cloud, progress=False)
    del cloud
    root = _root_summary(tree)
    seq = to_sequential_cloud(tree)
    del tree
    work = partial / f".{name}.tmp"
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir()
    stored = Schema(spec for spec in seq.schema.values() if spec.name not in EXTRAS)
    arrays = {"positions": seq.positions, "normals": seq.normals, "colors": seq.colors,
              "radii": seq.radii, "axes": seq.axes, **{name: seq.attributes[name] for name in EXTRAS},
              **{attribute_key(i): seq.attributes[name] for i, name in enumerate(stored)}}
    for key, value in arrays.items():
        if value is not None:
            _save_array(work / f"{key}.npy", value)
    summary = {"name": name, "points": points, "nodes": len(seq), "bounds": [lo.tolist(), hi.tolist()],
               "radius": float(seq.radii[0]), "attributes": stored.to_list(), **root}
    write_json(work / "root.json", summary)
    del seq, arrays
    final = partial / name
    shutil.rmtree(final, ignore_errors=True)
    os.replace(work, final)
    for file in files["bin"] + files["halo"]:
        file.unlink(missing_ok=True)


def _in_morton_order(records: np.ndarray, count: int) -> np.ndarray:
    """The partition's own records[:count], then its halo's, each in `morton_order`."""
    order = [morton_order(np.ascontiguousarray(part["p"])) + start
             for start, part in ((0, records[:count]), (count, records[count:])) if len(part)]
    return binning._gather(records, np.concatenate(order)).view(records.dtype)


def _save_array(path: Path, value: np.ndarray) -> None:
    """`value` as .npy, dropped from the page cache once the disk has it (module docstring)."""
    def write(file) -> None:
        np.save(file, value, allow_pickle=False)
        file.flush()
        drop_when_written(file)

    write_atomically(path, write)


def _root_summary(tree) -> dict:
    """The partition root as a leaf of the top tree: centre, normal, colour, e_g, and the
    enclosing radius, normal slab and area weight of all its leaf disks (module docstring)."""
    root = tree.root
    c, n = tree.positions[root], tree.normals[root].astype(np.float64)
    leaves = tree.n_leaves
    facing = tree.screen_facing[:leaves] if tree.screen_facing is not None else np.zeros(0, np.float32)
    enclosing, low, high, weight = _leaf_bounds(tree.positions[:leaves], tree.normals[:leaves], tree.radii[:leaves],
                                                tree.axes[:leaves], facing, c, n)
    return {"center": c.tolist(), "normal": n.tolist(),
            "color": None if tree.colors is None else tree.colors[root].tolist(),
            "e_g": float(tree.e_g[root]), "enclosing": float(max(enclosing, tree.radii[root])),
            "slab": [low, high], "weight": weight}


@numba.njit(cache=True)
def _leaf_bounds(positions, normals, radii, axes, facing, c, n):  # pragma: no cover - compiled
    """(max_i |d_i - dn_i n| + r_i, min_i dn_i - r_i s_i, max_i dn_i + r_i s_i, sum_i |u_i| |v_i|)
    over the leaf disks (module docstring; s_i = 1 for a disk facing the camera)."""
    enclosing, low, high, weight = 0.0, np.inf, -np.inf, 0.0
    for i in range(len(positions)):
        dx, dy, dz = positions[i, 0] - c[0], positions[i, 1] - c[1], positions[i, 2] - c[2]
        dn = dx * n[0] + dy * n[1] + dz * n[2]
        r = np.float64(radii[i])
        mx, my, mz = np.float64(normals[i, 0]), np.float64(normals[i, 1]), np.float64(normals[i, 2])
        cx, cy, cz = my * n[2] - mz * n[1], mz * n[0] - mx * n[2], mx * n[1] - my * n[0]
        sine = 1.0 if len(facing) and facing[i] > 0.5 else math.sqrt(cx * cx + cy * cy + cz * cz)
        rx, ry, rz = dx - dn * n[0], dy - dn * n[1], dz - dn * n[2]
        enclosing = max(enclosing, math.sqrt(rx * rx + ry * ry + rz * rz) + r)
        low = min(low, dn - r * sine)
        high = max(high, dn + r * sine)
        u = math.sqrt(np.float64(axes[i, 0, 0]) ** 2 + np.float64(axes[i, 0, 1]) ** 2 + np.float64(axes[i, 0, 2]) ** 2)
        v = math.sqrt(np.float64(axes[i, 1, 0]) ** 2 + np.float64(axes[i, 1, 1]) ** 2 + np.float64(axes[i, 1, 2]) ** 2)
        weight += u * v
    return enclosing, low, high, weight


def _top_tree(partial: Path, parts: list[dict], has_colors: bool, stored: Schema) -> int:
    """Build the top levels over the partition roots, write them (top/*.npy, sequential
    order) and give each partition root its r_max and d_parent. Returns the top node count.
    The top nodes' attributes are aggregated from the roots' as in build_lod; their clip
    lines cut nothing, and they face the camera by build_lod's rule."""
    p = len(parts)
    top_dir = partial / "top"
    shutil.rmtree(top_dir, ignore_errors=True)
    if p == 1:
        _patch_root(partial / parts[0]["name"], ROOT_PARENT_ERROR, 0.0)
        return 0

    def root_values(index: int) -> np.ndarray:  # row 0 of each partition: its root
        return np.stack([np.load(partial / part["name"] / f"{attribute_key(index)}.npy", mmap_mode="r")[0]
                         for part in parts])

    capacity = 2 * p - 1
    pos = np.zeros((capacity, 3))
    nrm = np.zeros((capacity, 3), np.float32)
    col = np.zeros((capacity if has_colors else 1, 3), np.float32)
    rad = np.zeros(capacity, np.float32)
    axes = np.zeros((capacity, 2, 3), np.float32)
    weight = np.zeros(capacity)
    lo = np.zeros(capacity)
    hi = np.zeros(capacity)
    e_p = np.zeros(capacity, np.float32)
    e_t = np.zeros(capacity, np.float32)
    e_g = np.zeros(capacity, np.float32)
    parent = np.full(capacity, -1, np.int64)
    d_parent = np.zeros(capacity, np.float32)
    representative = np.arange(capacity)
    facing = np.zeros(capacity if "screen_facing" in stored else 0, np.float32)
    if len(facing):
        facing[:p] = root_values(list(stored).index("screen_facing"))
    for i, part in enumerate(parts):
        pos[i], nrm[i], rad[i] = part["center"], part["normal"], part["enclosing"]
        weight[i], (lo[i], hi[i]), e_g[i] = part["weight"], part["slab"], part["e_g"]
        if has_colors:
            col[i] = part["color"]
    codes = morton_codes(pos[:p])
    active = np.argsort(codes)
    active_codes = codes[active]
    count = p
    child_lists, child_counts = [], []
    while len(active) > 1:  # as in build_lod: one octree level up per step
        next_active, active_codes, starts, sizes, children = _next_level(active, active_codes, count)
        if len(starts):
            _merge_cells(starts, sizes, active, count, pos, nrm, col, rad, axes, weight, lo, hi,
                         e_p, e_t, e_g, parent, d_parent, representative, has_colors, facing)
            child_lists.append(children)
            child_counts.append(sizes)
            count += len(starts)
        active = next_active
    child_start = np.zeros(count + 1, np.int64)
    child_start[p + 1:] = np.cumsum(np.concatenate(child_counts))
    scanner = {i: spec for i, spec in enumerate(stored.values()) if not spec.derived}
    roots = {spec.name: root_values(i) for i, spec in scanner.items()}
    attributes = aggregate_attributes(roots, {spec.name: spec.kind for spec in scanner.values()}, child_start,
                                      np.concatenate(child_lists), weight[:count], representative[:count])
    if "clip_lines" in stored:
        attributes["clip_lines"] = np.broadcast_to(np.float32(INACTIVE_CLIP), (count, *stored["clip_lines"].shape))
    if len(facing):
        attributes["screen_facing"] = facing[:count]
    for i, part in enumerate(parts):
        _patch_root(partial / part["name"], float(e_g[parent[i]]), float(d_parent[i]))
    inner = np.arange(p, count)
    emax = np.where(parent[inner] >= 0, e_g[np.maximum(parent[inner], 0)], ROOT_PARENT_ERROR).astype(np.float32)
    order = inner[np.argsort(~r_max_bucket(emax), kind="stable")]
    emax_sorted = np.where(parent[order] >= 0, e_g[np.maximum(parent[order], 0)],
                           ROOT_PARENT_ERROR).astype(np.float32)
    dpar = d_parent[order]
    arrays = {"positions": pos[order], "normals": nrm[order], "radii": rad[order], "axes": axes[order],
              "lod_emin": e_g[order], "lod_emax": emax_sorted, "lod_dparent": dpar,
              "lod_dsuffix": np.maximum.accumulate(dpar[::-1])[::-1].copy()}
    if has_colors:
        arrays["colors"] = col[order]
    arrays.update({attribute_key(i): attributes[name][order] for i, name in enumerate(stored)})
    top_dir.mkdir()
    for key, value in arrays.items():
        _save_array(top_dir / f"{key}.npy", value)
    return len(inner)


def _patch_root(part_dir: Path, emax: float, dparent: float) -> None:
    """Row 0 (the partition root) gets r_max / k = emax and its d_parent; dsuffix follows."""
    arrays = {name: np.load(part_dir / f"{name}.npy", mmap_mode="r+")
              for name in ("lod_emax", "lod_dparent", "lod_dsuffix")}
    arrays["lod_emax"][0] = emax
    arrays["lod_dparent"][0] = dparent
    rest = float(arrays["lod_dsuffix"][1]) if len(arrays["lod_dsuffix"]) > 1 else 0.0
    arrays["lod_dsuffix"][0] = max(dparent, rest)
    for array in arrays.values():
        array.flush()
