"""Where a method's trained checkpoint is found and how it is loaded.

A checkpoint is ``<name>.safetensors`` with its card ``<name>.json`` next to it; the shipped ones
are in :data:`MODEL_DIR`. Its network family (:func:`gdpt.reconstruct.families.family_of`,
recognised by the card's ``"format"``) builds the reconstructor.
"""

from __future__ import annotations

import importlib.util
import os
from functools import lru_cache
from pathlib import Path
from typing import Any

from gdpt.deprecated import MODEL_ENV_DEPRECATED, warn

#: Folder of the models shipped with the package (``<name>.safetensors`` + ``<name>.json``).
MODEL_DIR = Path(__file__).parent / "models"

#: Environment variable: a checkpoint that replaces the shipped one of ``oidn-grad``.
MODEL_ENV = "GDPT_OIDN_GRAD_MODEL"


def _model_from_environment() -> str | None:
    """``$GDPT_OIDN_GRAD_MODEL``, else ``$GDPT_NGPT_MODEL`` (with a ``DeprecationWarning``), else
    ``None``."""
    if (model := os.environ.get(MODEL_ENV)) is None:
        model = os.environ.get(MODEL_ENV_DEPRECATED)
        if model is not None:
            warn(MODEL_ENV_DEPRECATED, f"set {MODEL_ENV}")
    return model


def model_path(name: str, model: str | os.PathLike | None = None) -> Path:
    """The checkpoint to use: ``model``, else ``$GDPT_OIDN_GRAD_MODEL`` (for ``oidn-grad``),
    else the shipped ``gdpt/models/<name>.safetensors``.

    Raises:
        FileNotFoundError: no such checkpoint; the message says what to provide.
    """
    if model is None and name == "oidn-grad":
        model = _model_from_environment()
    path = Path(model) if model is not None else MODEL_DIR / f"{name}.safetensors"
    if not path.is_file():
        raise FileNotFoundError(
            f"checkpoint not found: {path}. Pass model=PATH (a checkpoint written by "
            f"'gdpt train'), or set {MODEL_ENV} for 'oidn-grad'"
        )
    return path


@lru_cache(maxsize=4)
def load_reconstructor(path: Path) -> Any:
    """The reconstructor of a checkpoint (cached), built by its network family
    (:func:`gdpt.reconstruct.families.family_of`); it is called with a buffer mapping or
    ``GradientBuffers`` and exposes ``features``.

    Raises:
        FileNotFoundError: a file of the checkpoint is missing.
        ValueError: the card's format is no known family's (the message lists them).
    """
    from gdpt.reconstruct.families import family_of

    return family_of(path).reconstructor(path)


def oidn_weights_missing(name: str, path: Path) -> str | None:
    """Why the model at ``path``, when its family builds on OIDN's weights (a fine-tuned OIDN
    network, a combiner's base network), cannot load them, or ``None``.

    Raises:
        FileNotFoundError: a file of the checkpoint is missing.
        ValueError: the card's format is no known family's.
    """
    from gdpt.reconstruct.families import family_of

    if not family_of(path).oidn_weights:
        return None
    if importlib.util.find_spec("mitsuba_oidn") is None:
        return (
            f"method {name!r} fine-tunes Intel Open Image Denoise, whose weights are read from "
            "the 'mitsuba-oidn' package at run time: pip install mitsuba-oidn"
        )
    from gdpt.reconstruct.tza import OIDNWeightsError, builtin_weights

    try:
        builtin_weights()
    except OIDNWeightsError as err:
        return f"method {name!r}: {err}"
    return None


def primal_spp_factor(name: str, model: str | os.PathLike | None = None, **_: Any) -> float:
    """The model card's ``sampling.primal_spp_factor`` (0 when the card has none or the
    checkpoint is missing)."""
    from gdpt.reconstruct.cards import read_card

    try:
        _, _, card = read_card(model_path(name, model))
    except FileNotFoundError:
        return 0.0
    return float(card.get("sampling", {}).get("primal_spp_factor", 0.0))


def network_check(name: str) -> str | None:
    """``None`` when the shipped network ``name`` (and what it builds on) can be found, else
    why not."""
    try:
        return oidn_weights_missing(name, model_path(name))
    except (FileNotFoundError, ValueError) as err:
        return str(err)
