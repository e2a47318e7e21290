"""Binary PLY elements whose list properties vary in length from record to record.

Their record boundaries can only be found record by record (each list's length comes before
its items), so two compiled walks do it: the first finds where the element ends and the
length of the one list the reader keeps (a face's vertex indices) in every record; the
second copies every record's scalar properties into one packed structured array and the kept
list's items into one flat array, skipping the other lists. Memory stays within the size of
the element's bytes, where Python lists of per-record offsets took 60 times the file.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numba
import numpy as np

TRUNCATED, NEGATIVE = -1, -2  # a walk's end when the records run past the data, or a length is negative


@dataclass(frozen=True)
class RecordLayout:
    """A binary record's properties as the compiled walks read them: byte order, item sizes,
    list length sizes (0 for scalars) and signedness, each scalar's offset in the packed
    scalar record, and the index of the one list kept (-1: none)."""

    big_endian: bool
    sizes: np.ndarray
    length_sizes: np.ndarray
    length_signed: np.ndarray
    scalar_offsets: np.ndarray
    kept: int
    kept_size: int
    scalar_dtype: np.dtype

    @classmethod
    def of(cls, props, order: str, kept: str | None) -> RecordLayout:
        """The layout of PLY properties (`surfel.io.ply.Property`) in byte order `order`."""
        scalar_dtype = np.dtype([(p.name, order + p.type) for p in props if not p.is_list])
        offsets = [scalar_dtype.fields[p.name][1] if not p.is_list else -1 for p in props]
        index = next((k for k, p in enumerate(props) if p.name == kept), -1)
        return cls(order == ">", np.array([np.dtype(p.type).itemsize for p in props], np.int64),
                   np.array([np.dtype(p.length_type).itemsize if p.is_list else 0 for p in props], np.int64),
                   np.array([p.is_list and p.length_type[0] == "i" for p in props], np.bool_),
                   np.array(offsets, np.int64), index,
                   np.dtype(props[index].type).itemsize if index >= 0 else 0, scalar_dtype)


class Walk(NamedTuple):
    lengths: np.ndarray  # the kept list's length in each record (empty without one)
    end: int  # offset after the records; TRUNCATED or NEGATIVE when they cannot be read


def walk_records(codes: np.ndarray, offset: int, count: int, layout: RecordLayout) -> Walk:
    """The first walk over `count` records of the bytes `codes` from `offset`."""
    lengths, end = _walk(codes, offset, count, layout.sizes, layout.length_sizes, layout.length_signed,
                         layout.kept, layout.big_endian)
    return Walk(lengths, int(end))


def gather_records(codes: np.ndarray, offset: int, count: int, layout: RecordLayout,
                   walk: Walk) -> tuple[np.ndarray | None, np.ndarray]:
    """The second walk: the records' scalars as one structured array (None without
    scalars), and the kept list's items as raw bytes (each record's in turn)."""
    packed = np.empty((count, layout.scalar_dtype.itemsize), np.uint8)
    items = np.empty(int(walk.lengths.sum()) * layout.kept_size, np.uint8)
    _copy_records(codes, offset, count, layout.sizes, layout.length_sizes, layout.scalar_offsets, layout.kept,
                  layout.big_endian, packed, items)
    scalars = packed.view(layout.scalar_dtype).reshape(count) if layout.scalar_dtype.itemsize else None
    return scalars, items


@numba.njit(cache=True)
def _read_length(codes, at, size, signed, big_endian):  # pragma: no cover - compiled
    value = 0
    for b in range(size):
        byte = codes[at + (size - 1 - b if big_endian else b)]
        value |= np.int64(byte) << (8 * b)
    if signed and value >= np.int64(1) << (8 * size - 1):
        value -= np.int64(1) << (8 * size)
    return value


@numba.njit(cache=True)
def _walk(codes, offset, count, sizes, length_sizes, length_signed, kept, big_endian):  # pragma: no cover
    lengths = np.zeros(count if kept >= 0 else 0, np.uint32)
    end = len(codes)
    for r in range(count):
        for p in range(len(sizes)):
            if length_sizes[p] == 0:
                offset += sizes[p]
                continue
            if offset + length_sizes[p] > end:
                return lengths, TRUNCATED
            length = _read_length(codes, offset, length_sizes[p], length_signed[p], big_endian)
            if length < 0:
                return lengths, NEGATIVE
            if p == kept:
                lengths[r] = length
            offset += length_sizes[p] + length * sizes[p]
        if offset > end:
            return lengths, TRUNCATED
    return lengths, offset


@numba.njit(cache=True)
def _copy_records(codes, offset, count, sizes, length_sizes, scalar_offsets, kept, big_endian, packed,
                  items):  # pragma: no cover - compiled
    at = 0
    for r in range(count):
        for p in range(len(sizes)):
            if length_sizes[p] == 0:
                packed[r, scalar_offsets[p]:scalar_offsets[p] + sizes[p]] = codes[offset:offset + sizes[p]]
                offset += sizes[p]
                continue
            length = _read_length(codes, offset, length_sizes[p], False, big_endian)
            offset += length_sizes[p]
            if p == kept:
                items[at:at + length * sizes[p]] = codes[offset:offset + length * sizes[p]]
                at += length * sizes[p]
            offset += length * sizes[p]
