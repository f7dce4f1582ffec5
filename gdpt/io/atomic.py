"""The one way gdpt replaces a file: write a temporary file next to it, fsync, rename.

A reader (or a process that crashes and resumes) sees either the previous file or the complete
new one, never a torn one; on any failure the temporary file is removed and the previous file
is left as it was::

    with atomic_path("out/render.exr") as tmp:   # tmp: a new path in out/
        write_exr(tmp)
    atomic_write("out/config.json", json.dumps(config))
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path


def fsync_path(path: str | os.PathLike[str]) -> None:
    """Flush a file's data, or a directory's entries, to disk."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


@contextmanager
def atomic_path(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary path in ``path``'s folder; on a clean exit move it to ``path``.

    The caller writes the temporary file by name (any writer: OpenEXR, torch, safetensors).
    On exit it is fsync'ed and renamed over ``path`` (atomic on POSIX), and the folder entry is
    fsync'ed; if the block raises, the temporary file is removed and ``path`` is untouched.

    Raises:
        FileNotFoundError: the folder of ``path`` does not exist.
    """
    path = Path(path)
    fd, name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    tmp = Path(name)
    try:
        yield tmp
        fsync_path(tmp)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    fsync_path(path.parent)


def atomic_write(path: str | os.PathLike[str], data: bytes | str) -> Path:
    """Replace ``path`` by ``data`` (``str`` is written as UTF-8) atomically; returns ``path``."""
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_bytes(data.encode() if isinstance(data, str) else data)
    return path
