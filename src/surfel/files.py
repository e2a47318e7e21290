"""Writing files so that a reader never sees half of one: every output surfel writes goes
through `write_atomically`, and every output location is checked (`check_output`) before
the work that fills it, so that a command writes all it was asked for or nothing."""

from __future__ import annotations

import contextlib
import json
import os
import secrets
import stat
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import BinaryIO

from .errors import SurfelError


def destination(path: str | os.PathLike) -> str:
    """The file that writing `path` replaces: `path` itself, or, when it is a symbolic link,
    the file the link names (the link is kept: writing through it changes its target).

    Refused with a one-line SurfelError naming `path`: a destination that exists and is not
    a regular file (a directory, FIFO, socket or device: renaming a file over it would
    destroy it), and one whose folder is missing or not writable.
    """
    name = os.fspath(path)
    target = os.path.realpath(name)  # through every link; a dangling one names the file it would create
    folder = os.path.dirname(target)
    if not os.path.isdir(folder):
        raise SurfelError(f"{name}: cannot write: no such directory {os.path.dirname(name) or folder}")
    try:
        mode = os.stat(target).st_mode
    except FileNotFoundError:
        mode = None
    except OSError as exc:
        raise SurfelError(f"{name}: cannot write: {exc.strerror or exc}") from None
    if mode is not None and not stat.S_ISREG(mode):
        kind = "a directory" if stat.S_ISDIR(mode) else f"a {_special_kind(mode)}, not a regular file"
        raise SurfelError(f"{name}: cannot write: it exists and is {kind}")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise SurfelError(f"{name}: cannot write: permission denied in {os.path.dirname(name) or folder}")
    return target


def _special_kind(mode: int) -> str:
    for test, kind in ((stat.S_ISFIFO, "FIFO"), (stat.S_ISSOCK, "socket"), (stat.S_ISCHR, "character device"),
                       (stat.S_ISBLK, "block device"), (stat.S_ISLNK, "symbolic link")):
        if test(mode):
            return kind
    return "special file"


@contextlib.contextmanager
def replaced_atomically(path: str | os.PathLike, suffix: str = "") -> Iterator[str]:
    """A temporary path beside `destination(path)`, for a writer that needs a file name
    (ending in `suffix`, for writers that choose a format by it); renamed over the destination
    when the block completes, removed if it fails. The new file keeps the replaced file's
    permissions, else gets those a plain open() would (0o666 less the umask). An OSError (no
    permission, a full disk) becomes a one-line SurfelError naming the file."""
    target = destination(path)
    directory, name = os.path.split(target)
    temporary = os.path.join(directory, f".{name}.{os.getpid()}.{secrets.token_hex(4)}.tmp{suffix}")
    try:
        descriptor = os.open(temporary, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o666)
        os.close(descriptor)
        with contextlib.suppress(FileNotFoundError):
            os.chmod(temporary, stat.S_IMODE(os.stat(target).st_mode))
        yield temporary
        # Checked again just before the rename: something other than a regular file may have
        # appeared there while the body was written.
        if destination(path) != target:
            raise SurfelError(f"{os.fspath(path)}: changed while it was written; not replacing it")
        os.replace(temporary, target)
    except BaseException as error:
        with contextlib.suppress(OSError):
            os.unlink(temporary)
        if isinstance(error, OSError):
            raise SurfelError(f"{os.fspath(path)}: cannot write: {error.strerror or error}") from error
        raise


def write_atomically(path: str | os.PathLike, write_body: Callable[[BinaryIO], object] | bytes) -> None:
    """Write `path` through a temporary file beside it, renamed over it only when complete
    (`replaced_atomically`: a symbolic link is written through, never replaced; an existing
    directory, FIFO, socket or device is refused; a failure leaves nothing behind).

    write_body: the bytes, or a function writing them to the open file (opened for reading
    too, for formats that patch a header afterwards).
    """
    with replaced_atomically(path) as temporary, open(temporary, "r+b") as file:
        if isinstance(write_body, (bytes, bytearray)):
            file.write(write_body)
        else:
            write_body(file)


def write_json(path: str | os.PathLike, data) -> None:
    """`data` as indented JSON (values JSON lacks, such as paths, as their strings), atomically."""
    write_atomically(path, (json.dumps(data, indent=2, default=str) + "\n").encode())


def check_output(path: str, label: str, formats: tuple[str, ...] | None = None) -> None:
    """Refuse, before anything is rendered, an output that cannot be written (`destination`:
    its folder missing or not writable, the path an existing directory or other non-regular
    file), or (with `formats`) one whose extension is not one of them."""
    if formats is not None and Path(path).suffix.lower() not in formats:
        named = " or ".join(f or "no extension" for f in formats)
        raise SurfelError(f"{path}: {label} must be named {named}")
    destination(path)


def check_folder(path: str, label: str) -> None:
    """A folder an option writes into, created if missing: its parent must exist."""
    if os.path.exists(path):
        if not os.path.isdir(path):
            raise SurfelError(f"{path}: {label} needs a folder, and this is a file")
        return
    parent = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(parent):
        raise SurfelError(f"{path}: cannot write: no such directory {os.path.dirname(path) or parent}")
