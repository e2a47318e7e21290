"""Writing files so that a reader never sees half of one: every output surfel writes goes
through `write_atomically`, and every output location is checked (`check_output`) before
the work that fills it, so that a command writes all it was asked for or nothing."""

from __future__ import annotations

import contextlib
import json
import os
import secrets
import stat
from collections.abc import Callable
from pathlib import Path
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


def check_output(path: str, label: str, formats: tuple[str, ...] | None = None) -> None:
    """Refuse, before anything is rendered, an output that cannot be written: its folder
    missing or not writable, the path an existing directory or other non-regular file, or
    (with `formats`) an extension that is not one of them."""
    if formats is not None and Path(path).suffix.lower() not in formats:
        named = " or ".join(f or "no extension" for f in formats)
        raise SurfelError(f"{path}: {label} must be named {named}")
    target = os.path.abspath(path)
    folder = os.path.dirname(target)
    if not os.path.isdir(folder):
        raise SurfelError(f"{path}: cannot write: no such directory {os.path.dirname(path) or folder}")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise SurfelError(f"{path}: cannot write: permission denied in {os.path.dirname(path) or folder}")
    if os.path.lexists(target):
        try:
            mode = os.stat(target).st_mode
        except OSError as exc:
            raise SurfelError(f"{path}: cannot write: {exc.strerror}") from None
        if not stat.S_ISREG(mode):
            kind = "a directory" if stat.S_ISDIR(mode) else "not a regular file"
            raise SurfelError(f"{path}: cannot write: it exists and is {kind}")


def check_folder(path: str, label: str) -> None:
    """A folder an option writes into, created if missing: its parent must exist."""
    if os.path.exists(path):
        if not os.path.isdir(path):
            raise SurfelError(f"{path}: {label} needs a folder, and this is a file")
        return
    parent = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(parent):
        raise SurfelError(f"{path}: cannot write: no such directory {os.path.dirname(path) or parent}")
