"""Writing files so that a reader never sees half of one: every output surfel writes goes
through `write_atomically`."""

from __future__ import annotations

import contextlib
import json
import os
import secrets
from collections.abc import Callable
from typing import BinaryIO

from .errors import SurfelError


def write_atomically(path: str | os.PathLike, write_body: Callable[[BinaryIO], object] | bytes) -> None:
    """Write `path` through a temporary file beside it, renamed over it only when complete.

    write_body: the bytes, or a function writing them to the open file (opened for reading
    too, for formats that patch a header afterwards). The file gets the permissions a plain
    open() would (0o666 less the umask). An OSError (a missing folder, no permission, a full
    disk) becomes a one-line SurfelError naming the file; a failure leaves nothing behind.
    """
    target = os.path.abspath(os.fspath(path))
    directory, name = os.path.split(target)
    temporary = os.path.join(directory, f".{name}.{os.getpid()}.{secrets.token_hex(4)}.tmp")
    try:
        descriptor = os.open(temporary, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o666)
        with os.fdopen(descriptor, "w+b") as file:
            if isinstance(write_body, (bytes, bytearray)):
                file.write(write_body)
            else:
                write_body(file)
        os.replace(temporary, target)
    except BaseException as error:
        with contextlib.suppress(OSError):
            os.unlink(temporary)
        if isinstance(error, OSError):
            raise SurfelError(f"{os.fspath(path)}: cannot write: {error.strerror or error}") from error
        raise


def write_json(path: str | os.PathLike, data) -> None:
    """`data` as indented JSON (values JSON lacks, such as paths, as their strings), atomically."""
    write_atomically(path, (json.dumps(data, indent=2, default=str) + "\n").encode())
