"""The planning and binning passes of the out-of-core build (outofcore.py's docstring,
passes 1 and 2), and their kernels: fine cells, halos, grouping.

The bounding cube lo + [0, size]^3 is cut into res^3 fine cells (res = 2^HISTOGRAM_BITS); a
point p falls in cell q = clamp(floor((p - lo) res / size), 0, res - 1) per axis, flattened
x-major, (q_x res + q_y) res + q_z. Each partition is a union of fine cells (an octree cell).

Halo (the points a partition borrows from its neighbours, so that the neighbour queries of its
border points find what the whole cloud would give them): point p is in the halo of every
partition P other than its own that holds a fine cell within Chebyshev distance h of p, i.e.
whose box meets the cube [p - h, p + h]^3. With f = (p - lo) res / size - q the offset of p in
its cell (in cell widths) and h in cell widths, the cell q + d (d in {-H..H}^3, H = ceil(h))
meets that cube when along every axis

    d < 0:  f + (-d - 1) <= h,     d = 0: always,     d > 0:  (1 - f) + (d - 1) <= h,

so a point farther than h from every face of its cell is in no halo, nor is a point of a lone
cell (`lone_cells`: one whose H-neighbourhood holds no cell of another partition), which most
cells of a partition are.

Pieces: binary PLY inputs are binned by the worker processes of the build in parallel, each a
contiguous run of the input's chunks into files of its own (piece p of partition g:
part-g.p.bin, part-g.p.halo); a partition's points are its pieces in piece order, the input's
order, as one process binning every chunk would write them.

Grouping: a stable counting sort of small integer keys (partition indices), the order and the
start of each key's run, so that each partition's points are written in one piece.
"""

from __future__ import annotations

import math
import os
import sys
from collections.abc import Iterable
from concurrent.futures import Executor, as_completed, wait
from dataclasses import dataclass, replace
from pathlib import Path

import numba
import numpy as np
from scipy.ndimage import distance_transform_edt
from tqdm import tqdm

from ..attributes import Schema
from ..cloud import framing_sphere
from ..threads import over_rows
from . import worker_warm_up
from .streaming import CHUNK_POINTS, Chunk, KindVote, StreamInput, all_chunks, read_ahead, summarise

HISTOGRAM_BITS = 7
# points of the input sampled evenly for the histogram (all of them in smaller inputs)
HISTOGRAM_SAMPLE = 2_000_000
# halo width: this many sample spacings (two hops of 16 nearest neighbours, about 2.3 spacings
# each on an evenly sampled surface, and a margin: radii depend on the neighbours' own
# neighbourhoods through the outlier cap and the sharp features), at most this many fine cells
HALO_SPACINGS = 8.0
HALO_MAX_CELLS = 4.0


@numba.njit(parallel=True, cache=True)
def fine_cells(positions, lo, scale, res):  # pragma: no cover - compiled
    """Flattened fine cell (int64) of each position; scale = res / size."""
    n = len(positions)
    cells = np.empty(n, np.int64)
    for i in numba.prange(n):
        flat = 0
        for axis in range(3):
            q = min(max(np.int64(math.floor((positions[i, axis] - lo[axis]) * scale)), 0), res - 1)
            flat = flat * res + q
        cells[i] = flat
    return cells


@numba.njit(cache=True)
def halo_reach(halo):  # pragma: no cover - compiled
    """H of the module docstring: the cells scanned on each side, for a halo of `halo` cell widths."""
    return max(1, math.ceil(halo))


def lone_cells(lookup: np.ndarray, res: int, halo: float) -> np.ndarray:
    """(res^3,) bool, flattened as lookup: the cells whose H-neighbourhood (H = halo_reach(halo))
    holds no cell of a partition other than their own (lookup[cell]; empty cells, -1, belong
    to none)."""
    from scipy.ndimage import maximum_filter, minimum_filter

    table = lookup.reshape(res, res, res)
    size = 2 * halo_reach(halo) + 1
    highest = maximum_filter(table, size, mode="constant", cval=-1)
    lowest = minimum_filter(np.where(table < 0, np.iinfo(np.int32).max, table), size, mode="constant",
                            cval=np.iinfo(np.int32).max)
    return ((highest <= table) & (lowest >= table)).reshape(-1)


@numba.njit(cache=True)  # called, not inlined: inlined in both loops it doubled their compile time
def _halo_of(position, lo, scale, res, lookup, lone, own, halo, reach, found):  # pragma: no cover - compiled
    """The partitions (other than `own`) whose cells lie within `halo` cell widths of the
    position, into found[:count]; returns count."""
    x = (position[0] - lo[0]) * scale
    y = (position[1] - lo[1]) * scale
    z = (position[2] - lo[2]) * scale
    qx = min(max(np.int64(math.floor(x)), 0), res - 1)
    qy = min(max(np.int64(math.floor(y)), 0), res - 1)
    qz = min(max(np.int64(math.floor(z)), 0), res - 1)
    if lone[(qx * res + qy) * res + qz]:
        return 0  # every cell within reach is the point's own partition's, or empty
    fx = min(max(x - qx, 0.0), 1.0)
    fy = min(max(y - qy, 0.0), 1.0)
    fz = min(max(z - qz, 0.0), 1.0)
    if min(fx, 1.0 - fx, fy, 1.0 - fy, fz, 1.0 - fz) > halo:
        return 0  # the cube [p - h, p + h]^3 stays inside p's own cell
    count = 0
    for dx in range(-reach, reach + 1):
        cx = qx + dx
        gx = 0.0 if dx == 0 else (fx - dx - 1.0 if dx < 0 else dx - fx)
        if cx < 0 or cx >= res or gx > halo:
            continue
        for dy in range(-reach, reach + 1):
            cy = qy + dy
            gy = 0.0 if dy == 0 else (fy - dy - 1.0 if dy < 0 else dy - fy)
            if cy < 0 or cy >= res or gy > halo:
                continue
            for dz in range(-reach, reach + 1):
                cz = qz + dz
                gz = 0.0 if dz == 0 else (fz - dz - 1.0 if dz < 0 else dz - fz)
                if cz < 0 or cz >= res or gz > halo or (dx == 0 and dy == 0 and dz == 0):
                    continue
                part = lookup[(cx * res + cy) * res + cz]
                if part < 0 or part == own:
                    continue
                seen = False
                for j in range(count):
                    seen = seen or found[j] == part
                if not seen:
                    found[count] = part
                    count += 1
    return count


def halo_pairs(positions, lo, scale, res, lookup, lone, own, halo):
    """(point index, partition) of every halo membership (module docstring), halo in cell
    widths; lone: `lone_cells(lookup, res, halo)`."""
    n = len(positions)
    counts = np.empty(n, np.int32)  # the second pass revisits only the few points in a halo
    over_rows(_halo_counts, n, positions, lo, scale, res, lookup, lone, own, halo, counts, grain=4096)
    ends = np.cumsum(counts)
    points = np.empty(ends[-1] if n else 0, np.int64)
    parts = np.empty(len(points), np.int32)
    over_rows(_halo_rows, n, positions, lo, scale, res, lookup, lone, own, halo, counts, ends - counts, points,
              parts, grain=4096)
    return points, parts


@numba.njit(cache=True, nogil=True)
def _halo_counts(first, stop, positions, lo, scale, res, lookup, lone, own, halo,
                 counts):  # pragma: no cover - compiled
    """The number of halos each point first:stop lies in."""
    reach = halo_reach(halo)
    found = np.empty((2 * reach + 1) ** 3, np.int32)
    for i in range(first, stop):
        counts[i] = _halo_of(positions[i], lo, scale, res, lookup, lone, own[i], halo, reach, found)


@numba.njit(cache=True, nogil=True)
def _halo_rows(first, stop, positions, lo, scale, res, lookup, lone, own, halo, counts, offsets, points,
               parts):  # pragma: no cover - compiled
    """The halo memberships of points first:stop, the counts[i] of point i from offsets[i] on."""
    reach = halo_reach(halo)
    found = np.empty((2 * reach + 1) ** 3, np.int32)
    for i in range(first, stop):
        if counts[i] == 0:
            continue
        out = offsets[i]
        count = _halo_of(positions[i], lo, scale, res, lookup, lone, own[i], halo, reach, found)
        for j in range(count):
            points[out] = i
            parts[out] = found[j]
            out += 1


@numba.njit(cache=True)
def group_by(keys, groups):  # pragma: no cover - compiled
    """Stable counting sort of keys in [0, groups): (order, starts), key g's items being
    order[starts[g]:starts[g + 1]]."""
    starts = np.zeros(groups + 1, np.int64)
    for key in keys:
        starts[key + 1] += 1
    for g in range(groups):
        starts[g + 1] += starts[g]
    cursor = starts[:-1].copy()
    order = np.empty(len(keys), np.int64)
    for i in range(len(keys)):
        order[cursor[keys[i]]] = i
        cursor[keys[i]] += 1
    return order, starts


# --------------------------------------------------------------------------------------------
# the passes


@dataclass
class Plan:
    """The partitions: cells (level, ix, iy, iz) of the octree over the cube lo + [0, size]^3."""

    lo: np.ndarray
    size: float
    cells: list[tuple[int, int, int, int]]

    def lookup(self, complete: bool = False) -> np.ndarray:
        """Partition index of each histogram cell (flattened x-major), -1 where empty; with
        `complete`, empty cells take the partition of the nearest cell of a partition (the
        plan of a sample: points may lie where the sample has none)."""
        res = 1 << HISTOGRAM_BITS
        table = np.full((res, res, res), -1, np.int32)
        for index, (level, x, y, z) in enumerate(self.cells):
            s = 1 << (HISTOGRAM_BITS - level)
            table[x * s:(x + 1) * s, y * s:(y + 1) * s, z * s:(z + 1) * s] = index
        if complete:
            nearest = distance_transform_edt(table < 0, return_distances=False, return_indices=True)
            table = table[tuple(nearest)]
        return table.reshape(-1)


def plan_partitions(histogram: np.ndarray, lo: np.ndarray, size: float, cap: int) -> Plan:
    """Split the cube octree-wise while a cell holds more than cap points (outofcore.py's docstring)."""
    pyramid = [histogram]
    while len(pyramid[-1]) > 1:
        h = pyramid[-1]
        r = len(h) // 2
        pyramid.append(h.reshape(r, 2, r, 2, r, 2).sum(axis=(1, 3, 5)))
    pyramid.reverse()  # pyramid[level]: counts of the 2^level cells per axis
    cells = []
    stack = [(0, 0, 0, 0)]
    while stack:
        level, x, y, z = stack.pop()
        count = int(pyramid[level][x, y, z])
        if count == 0:
            continue
        if count <= cap or level == HISTOGRAM_BITS:
            cells.append((level, x, y, z))
            continue
        for child in range(7, -1, -1):
            stack.append((level + 1, 2 * x + (child >> 2), 2 * y + (child >> 1 & 1), 2 * z + (child & 1)))
    return Plan(lo, size, cells)


def progress_bar(total: int, desc: str, progress: bool | None) -> tqdm:
    """A points/s progress bar with ETA (None: only on a terminal)."""
    show = sys.stderr.isatty() if progress is None else progress
    return tqdm(total=total, desc=f"surfel: {desc}", unit="pt", unit_scale=True, disable=not show, leave=False)


def record_dtype(has_normals: bool, has_colors: bool, schema: Schema) -> np.dtype:
    """A binned point: position, normal, colour, and attribute i as field a<i>."""
    fields = [("p", "<f8", (3,))]
    if has_normals:
        fields.append(("n", "<f4", (3,)))
    if has_colors:
        fields.append(("c", "<f4", (3,)))
    fields += [(f"a{i}", spec.dtype, spec.shape) for i, spec in enumerate(schema.values())]
    return np.dtype(fields)


@dataclass(frozen=True, eq=False)
class Bins:
    """What pass 2 needs to bin chunks into partial/bins/ (`folder`): the plan's partition of
    each fine cell (lookup), its lone cells, the halo width, the records' layout. A process
    bins its chunks into its own piece p of the files, part-g.p.bin and part-g.p.halo."""

    folder: Path
    lo: np.ndarray
    scale: float
    res: int
    lookup: np.ndarray
    lone: np.ndarray
    halo: float
    groups: int
    dtype: np.dtype
    has_normals: bool
    has_colors: bool
    schema: Schema

    def add(self, chunks: Iterable[Chunk], piece: int, bar: tqdm | None = None) -> np.ndarray:
        """Append the chunks' points to their partitions' and halos' files of piece `piece`;
        returns the points per partition."""
        counts = np.zeros(self.groups, np.int64)
        for chunk in read_ahead(iter(chunks)):
            part = self.lookup[fine_cells(chunk.positions, self.lo, self.scale, self.res)]
            order, starts = group_by(part, self.groups)
            counts += np.diff(starts)
            records = _records(chunk, self.dtype, self.has_normals, self.has_colors, self.schema)
            _append_runs(self.folder, f"{piece}.bin", _gather(records, order), starts)
            if self.groups > 1:
                points, owners = halo_pairs(chunk.positions, self.lo, self.scale, self.res, self.lookup, self.lone,
                                            part, self.halo)
                order, starts = group_by(owners, self.groups)
                _append_runs(self.folder, f"{piece}.halo", _gather(records, points[order]), starts)
            del records
            if bar is not None:
                bar.update(len(chunk.positions))
        return counts

    def add_ply(self, inputs: list[StreamInput], chunks: list[tuple[int, int]], size: int, piece: int) -> np.ndarray:
        """`add` of the binary PLY chunks (input, chunk index) of `size` points, in order."""
        read = (chunk for source, index in chunks for chunk in inputs[source].ply_chunks(size, index, index + 1))
        return self.add(read, piece)


def _add_ply_in_worker(bins: Bins, *args) -> np.ndarray:
    """`Bins.add_ply` in a pool's worker, once it has the binning's kernels (worker_warm_up.py)."""
    worker_warm_up.finish(warm_up)
    return bins.add_ply(*args)


def piece_files(folder: Path, name: str, suffix: str) -> list[Path]:
    """The pieces of partition `name`'s file (suffix "bin" or "halo"), in piece order: their
    concatenation holds the points in input order."""
    return sorted(folder.glob(f"{name}.*.{suffix}"), key=lambda path: int(path.name.split(".")[1]))


def bin_input(inputs: list[StreamInput], partial: Path, cap: int, signature: dict,
              progress: bool | None, pool: Executor | None = None, workers: int = 1) -> dict:
    """Passes 1 and 2 of the out-of-core build (outofcore.py's docstring) into partial/bins/:
    the pieces of part-g.bin and part-g.halo (`piece_files`), the records (`record_dtype`) of
    partition g and of its halo; returns the plan as saved in plan.json (`signature`
    included). Binary PLY inputs are binned by the `workers` processes of `pool`, each a
    contiguous run of their chunks into its own piece (other inputs by this process, read
    chunk after chunk)."""
    total = sum(i.count for i in inputs)
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    vote = KindVote(inputs)
    placeholders = False  # zero normals: the input counts as having none (cloud.file_normals)
    stride = max(1, -(-total // HISTOGRAM_SAMPLE))
    samples = []
    for source in inputs:  # colour ranges of LAS files are needed before the colours are scaled
        color_max = 0.0
        parts = (read_ahead(source.ply_summaries(stride)) if source.kind == "ply"
                 else (summarise(chunk, stride, source.kind) for chunk in read_ahead(source.chunks())))
        with progress_bar(source.count, f"scan {os.path.basename(source.path)}", progress) as bar:
            for part in parts:
                lo, hi = np.minimum(lo, part.lo), np.maximum(hi, part.hi)
                samples.append(part.sample)
                vote.add(part.attributes)
                placeholders = placeholders or part.zero_normals
                color_max = max(color_max, part.color_max)
                bar.update(part.count)
        if source.kind == "las" and source.has_colors:
            # chunks were scaled by 1: 8-bit values in 16-bit fields, or real 16-bit ones
            source.color_scale = 255.0 if color_max <= 255 else 65535.0
            source.has_colors = color_max > 0
    size = (float((hi - lo).max()) or 2 * framing_sphere(lo, hi)[1]) * (1 + 1e-9)  # one point: its framing
    res = 1 << HISTOGRAM_BITS
    scale = res / size
    sample = np.concatenate(samples)
    del samples
    histogram = np.bincount(fine_cells(sample, lo, scale, res), minlength=res ** 3)
    if stride > 1:  # counts estimated from the sample, planned with a margin for its error
        histogram = np.ceil(histogram * (total / len(sample))).astype(np.int64)
        cap = max(cap // 2, int(cap * (1 - 3 * np.sqrt(stride / cap))))
    del sample
    plan = plan_partitions(histogram.reshape(res, res, res), lo, size, cap)
    halo = halo_width(histogram)
    del histogram
    lookup = plan.lookup(complete=stride > 1)
    lone = lone_cells(lookup, res, halo)
    has_normals, has_colors = inputs[0].has_normals and not placeholders, any(i.has_colors for i in inputs)
    kinds = vote.kinds
    schema = Schema(replace(spec, kind=kinds[spec.name]) for spec in vote.specs)
    dtype = record_dtype(has_normals, has_colors, schema)
    bins = Bins(partial / "bins", lo, scale, res, lookup, lone, halo, len(plan.cells), dtype, has_normals,
                has_colors, schema)
    bins.folder.mkdir()
    chunks = [(source, index) for source, i in enumerate(inputs) for index in range(-(-i.count // CHUNK_POINTS))]
    with progress_bar(total, "partition", progress) as bar:
        if pool is not None and workers > 1 and len(chunks) > 1 and binned_by_workers(inputs):
            cuts = np.linspace(0, len(chunks), min(workers, len(chunks)) + 1).round().astype(int)
            jobs = {pool.submit(_add_ply_in_worker, bins, inputs, chunks[a:b], CHUNK_POINTS, piece): b - a
                    for piece, (a, b) in enumerate(zip(cuts[:-1], cuts[1:], strict=True))}
            counts = np.zeros(bins.groups, np.int64)
            try:
                for job in as_completed(jobs):
                    counts += job.result()
                    bar.update(min(total, jobs[job] * CHUNK_POINTS))
            finally:
                wait(jobs)  # no worker still writes into bins/ when an error removes it
        else:
            counts = bins.add(all_chunks(inputs), 0, bar)
    return {"signature": signature, "lo": lo.tolist(), "size": size, "cells": plan.cells,
            "counts": counts.tolist(), "has_normals": has_normals, "has_colors": has_colors,
            "schema": schema.to_list(), "geospatial": any(i.geospatial for i in inputs)}


def binned_by_workers(inputs: list[StreamInput]) -> bool:
    """Whether a pool's workers bin `inputs` (binary PLY files, read at offsets) rather than
    this process (LAS chunks are decoded in order)."""
    return all(i.kind == "ply" for i in inputs)


def warm_up() -> None:
    """Load (or compile) the kernels that bin a chunk, on two points of a chunk's types."""
    positions = np.zeros((2, 3))
    lookup = np.zeros(8, np.int32)
    part = lookup[fine_cells(positions, np.zeros(3), 1.0, 2)]
    group_by(part, 1)
    halo_pairs(positions, np.zeros(3), 1.0, 2, lookup, np.zeros(8, bool), part, 1.0)


def halo_width(histogram: np.ndarray) -> float:
    """The halo width h in fine-cell widths (outofcore.py's docstring, pass 2)."""
    occupied = histogram[histogram > 0]
    return float(min(HALO_MAX_CELLS, HALO_SPACINGS / np.sqrt(np.median(occupied))))


def _records(chunk, dtype: np.dtype, has_normals: bool, has_colors: bool, schema: Schema) -> np.ndarray:
    """The binned records (record_dtype) of the chunk's points, in its order."""
    records = np.empty(len(chunk.positions), dtype)
    records["p"] = chunk.positions
    if has_normals:
        records["n"] = chunk.normals
    if has_colors:
        records["c"] = chunk.colors if chunk.colors is not None else 1.0
    for i, name in enumerate(schema):
        records[f"a{i}"] = chunk.attributes[name]
    return records


def _gather(records: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """records[rows], copied as opaque bytes by np.take: numpy gathers those several times
    faster than the fields of a structured array."""
    return np.take(records.view(np.dtype((np.void, records.dtype.itemsize))), rows)


def _append_runs(bins: Path, suffix: str, records: np.ndarray, starts: np.ndarray) -> None:
    """Append run g = records[starts[g]:starts[g + 1]] to partition g's file part-g.suffix."""
    for group in np.flatnonzero(np.diff(starts)):
        # appended chunk by chunk, so not through write_atomically: scratch files in
        # the build's own NAME.partial/, which is published only by its final rename
        with open(bins / f"part-{group:05d}.{suffix}", "ab") as file:
            records[starts[group]:starts[group + 1]].tofile(file)
