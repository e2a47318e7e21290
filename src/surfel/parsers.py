"""Option parsers: the text of one command-line option (or batch-job value) to its value, or
ValueError(the problem), which `request.parse_values` turns into one line naming the flag."""

from __future__ import annotations

import math
from collections.abc import Callable

MAX_PIXELS = 16384 * 16384  # the largest image --size allows

def number(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise ValueError(f"needs a number, got {text!r}") from None
    if not math.isfinite(value):
        raise ValueError(f"needs a finite number, got {text!r}")
    return value


def positive_number(text: str) -> float:
    value = number(text)
    if value <= 0:
        raise ValueError(f"must be positive, got {text!r}")
    return value


def integer(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise ValueError(f"needs an integer, got {text!r}") from None


def integer_in(low: int, high: int) -> Callable[[str], int]:
    def parse(text: str) -> int:
        value = integer(text)
        if not low <= value <= high:
            raise ValueError(f"must be in {low}..{high}, got {text!r}")
        return value

    return parse


def numbers(count: int) -> Callable[[str], tuple[float, ...]]:
    def parse(text: str) -> tuple[float, ...]:
        try:
            values = tuple(float(v) for v in text.split(","))
        except ValueError:
            raise ValueError(f"needs {count} comma-separated numbers, got {text!r}") from None
        if len(values) != count or not all(map(math.isfinite, values)):
            raise ValueError(f"needs {count} comma-separated finite numbers, got {text!r}")
        return values

    return parse


def direction(text: str) -> tuple[float, float, float]:
    values = numbers(3)(text)
    if not any(values):
        raise ValueError("must not be the zero vector")
    return values


def size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise ValueError(f"must look like 512x512, got {text!r}") from None
    if w <= 0 or h <= 0 or w * h > MAX_PIXELS:
        raise ValueError(f"{text!r} is out of range (each side positive, at most {MAX_PIXELS} pixels)")
    return w, h


def choice(*values: str) -> Callable[[str], str]:
    def parse(text: str) -> str:
        if text not in values:
            raise ValueError(f"must be one of {', '.join(values)}, got {text!r}")
        return text

    return parse


def text(value: str) -> str:
    if not value:
        raise ValueError("must not be empty")
    return value


def integers(text: str) -> tuple[int, ...]:
    try:
        return tuple(int(v) for v in text.split(","))
    except ValueError:
        raise ValueError(f"needs comma-separated integers, got {text!r}") from None


def words(text: str) -> tuple[str, ...]:
    return tuple(v.strip().lower() for v in text.split(","))


def ortho_height(text: str) -> float | str:
    """--ortho: a view height in world units, or `auto` (the auto-framing's extent)."""
    return "auto" if text == "auto" else positive_number(text)


def field_of_view(text: str) -> float:
    value = number(text)
    if not 0 < value < 180:
        raise ValueError(f"must be in (0, 180) degrees, got {text!r}")
    return value
