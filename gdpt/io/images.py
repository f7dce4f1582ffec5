"""Tone mapping and 8-bit PNG previews of HDR images.

Previews are for looking at results, never for measuring them: metrics work on the linear HDR
data. The pipeline is ``exposure -> tone map -> sRGB encoding (colour-science) -> 8 bit``.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

import colour
import numpy as np
import torch
from PIL import Image, ImageDraw, ImageFont

from gdpt.io.exr import check_writable

PathLike = str | os.PathLike[str]
ImageLike = torch.Tensor | np.ndarray

#: Tone-mapping operators on linear, non-negative ``(H, W, 3)`` float arrays -> ``[0, 1]``.
TONEMAPS: dict[str, Callable[[np.ndarray], np.ndarray]] = {
    "clip": lambda x: np.clip(x, 0.0, 1.0),
    "reinhard": lambda x: x / (1.0 + x),
}

_LABEL_HEIGHT = 16
_GAP = 4


def to_srgb8(hdr: ImageLike, *, exposure: float = 0.0, tonemap: str = "clip") -> np.ndarray:
    """Tone-map a linear HDR image to 8-bit sRGB.

    Non-finite values are shown as black; negative values are clipped to zero.

    Args:
        hdr (torch.Tensor | np.ndarray): ``(H, W, 3)`` or ``(H, W, 1)`` linear radiance, any
            real dtype and device.
        exposure (float): scale by ``2**exposure`` before tone mapping (in stops).
        tonemap (str): a key of :data:`TONEMAPS` (``'clip'`` or ``'reinhard'``).

    Returns:
        ``(H, W, 3)`` uint8 numpy array.

    Raises:
        ValueError: wrong shape or unknown ``tonemap``.
    """
    if tonemap not in TONEMAPS:
        raise ValueError(f"unknown tonemap {tonemap!r}; valid: {', '.join(TONEMAPS)}")
    if isinstance(hdr, torch.Tensor):
        hdr = hdr.detach().to("cpu", torch.float64).numpy()
    x = np.asarray(hdr, dtype=np.float64)
    if x.ndim != 3 or x.shape[2] not in (1, 3):
        raise ValueError(f"image must have shape (H, W, 3) or (H, W, 1), got {x.shape}")
    if x.shape[2] == 1:
        x = np.repeat(x, 3, axis=2)
    x = np.nan_to_num(x * 2.0**exposure, nan=0.0, posinf=0.0, neginf=0.0)
    x = TONEMAPS[tonemap](np.maximum(x, 0.0))
    encoded = colour.cctf_encoding(x, function="sRGB")
    return np.round(np.clip(encoded, 0.0, 1.0) * 255.0).astype(np.uint8)


def save_png(
    path: PathLike,
    hdr: ImageLike,
    *,
    exposure: float = 0.0,
    tonemap: str = "clip",
    force: bool = False,
) -> Path:
    """Write a tone-mapped 8-bit sRGB PNG preview (see :func:`to_srgb8` for the arguments).

    Raises:
        FileExistsError: ``path`` exists and ``force`` is false.
    """
    check_writable(path, force=force)
    image = Image.fromarray(to_srgb8(hdr, exposure=exposure, tonemap=tonemap))
    image.save(path, format="PNG")
    return Path(path)


def load_mask(path: PathLike) -> np.ndarray:
    """A pixel mask from an image: ``(H, W)`` bool, set where any colour channel is above half
    its range (PNG: 1, 8 or 16 bit, grey, palette or RGB, alpha ignored; EXR: channels ``R``,
    ``G``, ``B`` above 0.5).

    Raises:
        FileNotFoundError: ``path`` does not exist.
        ValueError: not a ``.png`` or ``.exr`` file, or an unreadable one.
    """
    from gdpt.io.exr import load_image

    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".png", ".exr"):
        raise ValueError(
            f"{path}: a mask must be a .png or .exr image, got '{suffix or path.name}'"
        )
    if not path.is_file():
        raise FileNotFoundError(f"mask file not found: {path}")
    if suffix == ".exr":
        return (load_image(path) > 0.5).any(-1).numpy()
    with Image.open(path) as image:
        if image.mode.startswith("I"):  # 16- or 32-bit grey (a 16-bit PNG)
            pixels, half = np.asarray(image).astype(np.int64), 65535 / 2
        else:  # 1-bit, grey, palette, RGB(A): as 8-bit RGB, alpha dropped
            pixels, half = np.asarray(image.convert("RGB")), 255 / 2
    above = pixels > half
    return above if above.ndim == 2 else above.any(-1)


def preview_path(exr_path: PathLike) -> Path:
    """The PNG preview that belongs next to an EXR: ``out/x.exr`` -> ``out/x.png``."""
    return Path(exr_path).with_suffix(".png")


def side_by_side(
    images: dict[str, ImageLike],
    path: PathLike,
    *,
    exposure: float = 0.0,
    tonemap: str = "clip",
    scale: int = 1,
    force: bool = False,
) -> Path:
    """Write a labelled horizontal montage of images (e.g. noisy / L1 / L2 / reference).

    Args:
        images (dict[str, torch.Tensor | np.ndarray]): label -> ``(H, W, 3)`` or
            ``(H, W, 1)`` linear image; sizes may differ (tiles are top-aligned).
        path (str | os.PathLike): the PNG to write.
        exposure, tonemap: as for :func:`to_srgb8`, applied to every image.
        scale (int): integer nearest-neighbour upscaling for small renders.
        force (bool): overwrite an existing file.

    Returns:
        The written path.

    Raises:
        ValueError: ``images`` is empty or ``scale`` < 1.
        FileExistsError: ``path`` exists and ``force`` is false.
    """
    if not images:
        raise ValueError("side_by_side needs at least one image")
    if scale < 1:
        raise ValueError(f"scale must be >= 1, got {scale}")
    check_writable(path, force=force)
    font = ImageFont.load_default()
    tiles = []
    for label, hdr in images.items():
        tile = Image.fromarray(to_srgb8(hdr, exposure=exposure, tonemap=tonemap))
        tile = tile.resize((tile.width * scale, tile.height * scale), Image.Resampling.NEAREST)
        text_width = int(np.ceil(font.getlength(label)))
        tiles.append((label, tile, max(tile.width, text_width + 2 * _GAP)))
    width = sum(w for _, _, w in tiles) + _GAP * (len(tiles) + 1)
    height = _LABEL_HEIGHT + max(t.height for _, t, _ in tiles) + 2 * _GAP
    canvas = Image.new("RGB", (width, height), (32, 32, 32))
    draw = ImageDraw.Draw(canvas)
    x = _GAP
    for label, tile, tile_width in tiles:
        draw.text((x + _GAP, _GAP), label, fill=(255, 255, 255), font=font)
        canvas.paste(tile, (x + (tile_width - tile.width) // 2, _LABEL_HEIGHT + _GAP))
        x += tile_width + _GAP
    canvas.save(path, format="PNG")
    return Path(path)
