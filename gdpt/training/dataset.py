"""Reading a training dataset (written by :mod:`gdpt.training.preprocess`) as a torch
``Dataset``: :class:`CropDataset`.

Only :mod:`gdpt.io.exr` and torch are needed, not Mitsuba. The files are described in
:mod:`gdpt.training.manifest`.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import OpenEXR
from torch.utils.data import Dataset

from gdpt.buffers import pool_primal
from gdpt.io.exr import load_buffers
from gdpt.training.manifest import MANIFEST_FILE, DatasetWarning, dataset_settings, read_manifest

#: Input kinds: element-name prefix and the buffers a network reads from them. ``pool`` is the
#: gradient-domain input with the path-traced input of the same crop and level pooled into its
#: primal (:func:`gdpt.buffers.pool_primal`), the features those of the path-traced input (as
#: ``gdpt.render(..., primal_spp=...)`` renders them). ``pt-variance`` is the path-traced input
#: with the variance of its mean (a dataset rendered with ``variance``).
INPUT_KINDS: dict[str, tuple[str, tuple[str, ...]]] = {
    "gdpt": ("in", ("primal", "dx", "dy", "albedo", "normal", "depth")),
    "pt": ("pt", ("primal", "albedo", "normal", "depth")),
    "pool": ("in", ("primal", "dx", "dy", "albedo", "normal", "depth")),
    "pt-variance": ("pt", ("primal", "albedo", "normal", "depth", "var_primal")),
}


class CropDataset(Dataset):
    """Elements of a dataset written by :func:`gdpt.training.preprocess.build_dataset`, as a
    torch ``Dataset``.

    Element ``i`` is input level ``i % levels`` of usable crop ``i // levels``. Crops whose
    files are missing, truncated (size differs from the manifest) or not EXR files are
    skipped at construction with one :class:`DatasetWarning` listing them; a shard that turns
    out unreadable when loaded is skipped with a warning and the next readable element is
    returned instead, so training never stops on one.

    Args:
        root: dataset directory.
        kind: ``"gdpt"`` (gradient-domain inputs ``in<k>``), ``"pt"`` (path-traced inputs
            ``pt<k>``, 2.5x the samples), ``"pool"`` (``in<k>`` with ``pt<k>`` pooled into
            its primal; the features of ``pt<k>``) or ``"pt-variance"`` (``pt<k>`` with
            ``var_primal``).
        scenes: keep only crops whose scene index satisfies this predicate (``None``: all).

    Raises:
        FileNotFoundError: ``root`` is not a directory.
        ValueError: unknown ``kind``; a kind reading ``var_primal`` on a dataset rendered
            without variances; no finished crop (empty dataset, or none selected, or all
            corrupt); crops of different sizes.
    """

    def __init__(
        self,
        root: str | os.PathLike[str],
        *,
        kind: str = "gdpt",
        scenes: Callable[[int], bool] | None = None,
    ) -> None:
        if kind not in INPUT_KINDS:
            raise ValueError(f"unknown input kind {kind!r}; valid: {', '.join(INPUT_KINDS)}")
        self.root = Path(root)
        if not self.root.is_dir():
            raise FileNotFoundError(f"dataset directory {self.root} does not exist")
        self.kind = kind
        self.prefix, self.features = INPUT_KINDS[kind]
        if "var_primal" in self.features and not dataset_settings(self.root).get("variance"):
            raise ValueError(
                f"{self.root}: rendered without variances, and input kind {kind!r} reads "
                "var_primal; render a dataset with 'gdpt dataset --variance' (the default)"
            )
        records, problems = read_manifest(self.root)
        if not records:
            raise ValueError(
                f"{self.root}: empty dataset (no finished crop in {MANIFEST_FILE}); "
                "render one with 'gdpt dataset --out DIR ...'"
            )
        if scenes is not None:
            records = [r for r in records if scenes(int(r["scene"]))]
            if not records:
                raise ValueError(f"{self.root}: no crop of the selected scenes")
        sizes = sorted({tuple(r["resolution"]) for r in records})
        if len(sizes) > 1:
            counts = {
                f"{w}x{h}": sum(tuple(r["resolution"]) == (w, h) for r in records) for w, h in sizes
            }
            raise ValueError(
                f"{self.root}: crops of different sizes (crops per size: {counts}); "
                "a dataset must have one crop size"
            )
        self.resolution: tuple[int, int] = (int(sizes[0][0]), int(sizes[0][1]))
        bad = list(problems)
        self.crops: list[dict[str, Any]] = []
        for record in records:
            broken = [
                msg
                for name in self._element_names(record)
                if (msg := self._check_file(record, name))
            ]
            if broken:
                bad.append(f"crop {record['crop']} skipped: {'; '.join(broken)}")
            else:
                self.crops.append(record)
        if bad:
            warnings.warn(
                f"{self.root}: skipped {len(bad)} corrupt/partial entries:\n  " + "\n  ".join(bad),
                DatasetWarning,
                stacklevel=2,
            )
        if not self.crops:
            raise ValueError(f"{self.root}: no usable crop (all {len(records)} are corrupt)")
        self.levels = min(len(r["spp"]) for r in self.crops)
        self._unreadable: set[int] = set()

    def _element_names(self, record: dict[str, Any]) -> list[str]:
        prefixes = ("in", "pt") if self.kind == "pool" else (self.prefix,)
        levels = range(len(record["spp"]))
        return ["target", *(f"{prefix}{k}" for prefix in prefixes for k in levels)]

    def _check_file(self, record: dict[str, Any], name: str) -> str | None:
        """``None`` if element ``name`` of ``record`` looks complete, else the reason."""
        rel = record["files"].get(name)
        if rel is None:
            return f"no '{name}' in the manifest"
        path = self.root / rel
        if not path.is_file():
            return f"{rel} missing"
        size, expected = path.stat().st_size, record.get("bytes", {}).get(name)
        if expected is not None and size != expected:
            return f"{rel} has {size} bytes, the manifest says {expected} (partial)"
        if not OpenEXR.isOpenExrFile(str(path)):
            return f"{rel} is not an OpenEXR file"
        return None

    def __len__(self) -> int:
        return len(self.crops) * self.levels

    def element(self, index: int) -> tuple[dict[str, Any], int]:
        """``(manifest record, input level)`` of element ``index``."""
        return self.crops[index // self.levels], index % self.levels

    def load(self, index: int) -> dict[str, Any]:
        """Load element ``index`` (no fallback; see :meth:`__getitem__`).

        Returns:
            ``{"inputs": {name: (H, W, C) float32 CPU tensor for each of self.features},
            "target": (H, W, 3) float32 CPU tensor, "spp": int, "crop": str, "level": int}``.

        Raises:
            ValueError: the shard is unreadable, lacks a buffer or has the wrong size.
        """
        record, level = self.element(index)
        name = f"{self.prefix}{level}"
        inputs = load_buffers(self.root / record["files"][name])
        if self.kind == "pool":
            pt = load_buffers(self.root / record["files"][f"pt{level}"])
            inputs = pool_primal(  # features from the plain render alone, as gdpt.render pools
                inputs.replace(spp=int(record["spp"][level]), albedo=None, normal=None, depth=None),
                pt.replace(spp=int(record["pt_spp"][level])),
            )
        target = load_buffers(self.root / record["files"]["target"]).primal
        width, height = self.resolution
        tensors = {}
        for feature in self.features:
            tensor = getattr(inputs, feature)
            if tensor is None:
                raise ValueError(f"{record['files'][name]}: no '{feature}' buffer")
            tensors[feature] = tensor
        for what, tensor in (("input", inputs.primal), ("target", target)):
            if tuple(tensor.shape[:2]) != (height, width):
                raise ValueError(
                    f"crop {record['crop']}: {what} is "
                    f"{tensor.shape[1]}x{tensor.shape[0]}, expected "
                    f"{width}x{height}"
                )
        spp = record["pt_spp" if self.kind == "pt" else "spp"][level]
        return {
            "inputs": tensors,
            "target": target,
            "spp": int(spp),
            "crop": record["crop"],
            "level": level,
        }

    def __getitem__(self, index: int) -> dict[str, Any]:
        """Element ``index`` as in :meth:`load`, or the next readable one (with a warning)."""
        n = len(self)
        for offset in range(n):
            i = (index + offset) % n
            if i in self._unreadable:
                continue
            try:
                return self.load(i)
            except (ValueError, OSError) as error:
                self._unreadable.add(i)
                warnings.warn(
                    f"skipping unreadable element {i}: {error}", DatasetWarning, stacklevel=2
                )
        raise RuntimeError(f"{self.root}: no readable element left")
