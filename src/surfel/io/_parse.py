"""Helpers shared by the readers: numbers in text, ragged index lists, colour ranges.

The text formats (ascii PLY, OBJ, XYZ/PTS) hold millions of lines; a Python loop over
lines would dominate load time, so text is tokenised with numpy byte operations instead.
"""

from __future__ import annotations

import re
import warnings
from typing import NamedTuple

import numpy as np
import numpy.typing as npt

from ..errors import InputError

_SPACE = ord(" ")
_NEWLINE = ord("\n")
# For error messages only: the first token holding a character no number can contain.
_NOT_FLOAT = re.compile(rb"\S*[^\s0-9.eE+\-nNaAiIfFtTyY]\S*")
_NOT_INTEGER = re.compile(rb"\S*[^\s0-9+\-]\S*")


class Numbers(NamedTuple):
    values: np.ndarray  # every number, in order
    per_line: np.ndarray  # how many numbers each line holds (blank lines included, as 0)
    starts: np.ndarray  # the byte offset where each number starts


def numbers_by_line(text: bytes, dtype: npt.DTypeLike, path: str) -> Numbers:
    """Every whitespace-separated number in `text`, with how many each line holds.

    Lines end at b"\\n". A token that is not a number of `dtype` raises InputError.
    """
    codes = np.frombuffer(text, dtype=np.uint8)
    # Every control byte counts as a separator here; fromstring only accepts whitespace,
    # so any other control byte shows up below as a count mismatch.
    space = codes <= _SPACE
    token_starts = np.flatnonzero(space[:-1] > space[1:]) + 1
    if len(codes) and not space[0]:
        token_starts = np.concatenate(([0], token_starts))
    line_ends = np.flatnonzero(codes == _NEWLINE)
    tokens_before_line_end = np.searchsorted(token_starts, line_ends)
    per_line = np.diff(tokens_before_line_end, prepend=0, append=len(token_starts))
    if not len(token_starts):  # blank (or comments only): fromstring refuses an empty text
        return Numbers(np.empty(0, dtype), per_line, token_starts)
    with warnings.catch_warnings():
        # Older numpy only warns (newer raises) when it meets a token it cannot parse.
        warnings.simplefilter("error", DeprecationWarning)
        try:
            values = np.fromstring(text, dtype=dtype, sep=" ")
        except (ValueError, DeprecationWarning):
            values = None
    if values is None or len(values) != len(token_starts):
        integer = np.dtype(dtype).kind in "iu"
        bad = (_NOT_INTEGER if integer else _NOT_FLOAT).search(text)
        what = f"{bad.group().decode('latin-1')[:40]!r}" if bad else "a value"
        raise InputError(path, f"{what} is not {'an integer' if integer else 'a number'}")
    return Numbers(values, per_line, token_starts)


def ragged_arange(counts: np.ndarray) -> np.ndarray:
    """0..c-1 for each c in `counts`, concatenated: the positions inside ragged lists."""
    counts = np.asarray(counts, dtype=np.int64)
    total = int(counts.sum())
    starts = np.cumsum(counts) - counts
    return np.arange(total, dtype=np.int64) - np.repeat(starts, counts)


def unit_colors(values: np.ndarray) -> np.ndarray:
    """Colours written as 0..1, 0..255 or 0..65535 numbers, as floats clipped to [0, 1].

    The range is inferred from the largest value: above 255 means 16-bit, above 1 8-bit.
    """
    values = np.asarray(values, dtype=np.float64)
    largest = values.max() if values.size else 0.0
    if largest > 255:
        values = values / 65535
    elif largest > 1:
        values = values / 255
    return np.clip(values, 0.0, 1.0)
