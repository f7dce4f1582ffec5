"""A dataset directory on disk: its layout, ``dataset.json`` and the crash-safe manifest.

Written by :mod:`gdpt.training.preprocess`, read by :mod:`gdpt.training.dataset`::

    DIR/dataset.json                  {"format", "config"}: the content-defining settings
    DIR/manifest.jsonl                one JSON line per finished crop (see below)
    DIR/crops/s00012-v003/in0.exr     noisy G-PT input, lowest spp (in0 .. in4, spp ascending)
    DIR/crops/s00012-v003/pt0.exr     path-traced input at 2.5x the samples of in0 (pt0 .. pt4)
    DIR/crops/s00012-v003/target.exr  target: ``primal`` = L1 Poisson reconstruction of the
                                      high-spp render; dx, dy and features of that render
                                      (``target="pt"``: the path-traced render, no dx/dy)

Every EXR is written by :func:`gdpt.io.exr.save_buffers`. The crop id is
``s<scene:05d>-v<view:03d>`` (:func:`crop_id`). A manifest line holds ``crop``, ``scene``,
``view``, ``scene_seed``, ``resolution`` ``[width, height]``, ``spp`` (list), ``pt_spp``,
``target_spp``, ``seeds`` (render seeds), ``files`` (element name -> path relative to ``DIR``),
``bytes`` (element name -> file size) and ``render_seconds``.

Crash safety: the shards of a crop are written (atomically, then fsync'ed) before its manifest
line, and the line is appended with one ``write`` + ``fsync`` on an ``O_APPEND`` descriptor
(:func:`append_manifest`), so the manifest only ever lists complete crops; a torn last line
(e.g. out of disk) is ignored by :func:`read_manifest` and dropped by
:func:`rewrite_manifest`.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from gdpt.io.atomic import atomic_write

#: Value of the ``format`` key of ``dataset.json``.
DATASET_FORMAT = "gdpt-dataset/1"
#: The content-defining settings of a dataset (``{"format", "config"}``).
CONFIG_FILE = "dataset.json"
#: One JSON line per finished crop.
MANIFEST_FILE = "manifest.jsonl"
#: Folder of the crops' EXR files (one subfolder per crop id).
CROPS_DIR = "crops"


class DatasetWarning(UserWarning):
    """A corrupt or partial shard was skipped, or a torn manifest line dropped."""


def crop_id(scene: int, view: int) -> str:
    """The id (and directory name) of the crop of ``scene`` seen from ``view``."""
    return f"s{scene:05d}-v{view:03d}"


def dataset_settings(root: str | os.PathLike[str]) -> dict[str, Any]:
    """The ``config`` of ``dataset.json`` in ``root`` (``{}`` when missing or unreadable)."""
    try:
        config = json.loads((Path(root) / CONFIG_FILE).read_text())["config"]
    except (OSError, KeyError, TypeError, ValueError):
        return {}
    return config if isinstance(config, dict) else {}


def append_manifest(root: str | os.PathLike[str], record: dict[str, Any]) -> None:
    """Append one record to ``manifest.jsonl`` with a single ``write`` + ``fsync``.

    If the file does not end with a newline (a torn line from an earlier crash), the record
    starts on a new line, so the torn line stays an isolated invalid line that readers skip.

    Raises:
        OSError: the write failed or was short (e.g. out of disk); the manifest then holds at
            most a torn last line, never a corrupt complete one.
    """
    path = Path(root) / MANIFEST_FILE
    data = (json.dumps(record, sort_keys=True) + "\n").encode()
    fd = os.open(path, os.O_RDWR | os.O_APPEND | os.O_CREAT, 0o644)
    try:
        size = os.fstat(fd).st_size
        if size and os.pread(fd, 1, size - 1) != b"\n":
            data = b"\n" + data
        written = os.write(fd, data)
        if written != len(data):
            raise OSError(f"{path}: short write ({written} of {len(data)} bytes), disk full?")
        os.fsync(fd)
    finally:
        os.close(fd)


def read_manifest(root: str | os.PathLike[str]) -> tuple[list[dict[str, Any]], list[str]]:
    """The records of ``manifest.jsonl`` and the problems found in it.

    Args:
        root: dataset directory.

    Returns:
        ``(records, problems)``: one record per crop id (the last line wins), in file order,
        and a description of every line that is not a complete record (torn or invalid).
        A missing manifest gives ``([], [])``.
    """
    path = Path(root) / MANIFEST_FILE
    if not path.is_file():
        return [], []
    records: dict[str, dict[str, Any]] = {}
    problems = []
    for number, line in enumerate(path.read_bytes().split(b"\n"), start=1):
        if not line.strip():
            continue
        try:
            record = json.loads(line)
            if not isinstance(record, dict) or not {"crop", "files", "resolution"} <= set(record):
                raise ValueError("not a crop record")
        except ValueError as error:
            problems.append(f"{path.name}:{number}: invalid line ignored ({error})")
            continue
        records.pop(record["crop"], None)
        records[record["crop"]] = record
    return list(records.values()), problems


def rewrite_manifest(root: str | os.PathLike[str], records: list[dict[str, Any]]) -> None:
    """Atomically replace the manifest by ``records`` (drops torn and duplicate lines)."""
    text = "".join(json.dumps(record, sort_keys=True) + "\n" for record in records)
    atomic_write(Path(root) / MANIFEST_FILE, text)
