"""``gdpt train``: train a network of any family (:mod:`gdpt.reconstruct.families`).

:func:`train` finds the family of ``config.model`` (a design), checks ``config.loss`` against
the family's losses, and runs the family's plan (:data:`PLANS`) in the one training loop
(:func:`gdpt.training.loop.training_loop`: run directory, exact resume, ``torchrun``).

The families themselves (designs, losses, checkpoints) are declared in
:data:`gdpt.reconstruct.families.FAMILIES`, which imports torch only; how a family trains needs
the dataset and the run directory of :mod:`gdpt.training`, so its plan builder is registered
here, under the family's name (imports point one way: ``gdpt.training`` -> ``gdpt.reconstruct``).
"""

from __future__ import annotations

from pathlib import Path

from gdpt.reconstruct.families import family_of_design
from gdpt.reconstruct.registry import Registry
from gdpt.training.combiner import combiner_plan
from gdpt.training.config import TrainConfig
from gdpt.training.dense_unet import dense_plan
from gdpt.training.kpcn import kpcn_plan
from gdpt.training.loop import PlanBuilder, training_loop
from gdpt.training.oidn_finetune import finetune_plan

__all__ = ["PLANS", "train"]

#: Family name -> its plan builder; one for every family of
#: :data:`gdpt.reconstruct.families.FAMILIES`.
PLANS: Registry[PlanBuilder] = Registry("training plan")
PLANS.register("dense-unet", dense_plan)
PLANS.register("oidn-finetune", finetune_plan)
PLANS.register("combiner", combiner_plan)
PLANS.register("kpcn", kpcn_plan)


def train(config: TrainConfig, *, resume: bool = False, progress: bool = True) -> Path:
    """Train (or continue training) the design ``config.model``.

    Args:
        config: the run settings.
        resume: continue the run in ``config.out`` from its newest checkpoint (starts afresh
            if the directory holds no run yet).
        progress: show a progress bar (rank 0).

    Returns:
        Path of the final network (``RUN_DIR/model.safetensors``).

    Raises:
        FileExistsError: ``config.out`` holds a run and ``resume`` is false.
        ConfigMismatchError: resuming with other training settings.
        ValueError: an unknown design, a loss of another family, unusable data, or settings
            the family refuses (each named); raised before the run directory is written.
    """
    family = family_of_design(config.model)
    if config.loss not in family.losses:
        raise ValueError(
            f"loss {config.loss!r} does not apply to {config.model} ({family.name} family); "
            f"use one of {', '.join(family.losses)}"
        )
    return training_loop(
        config, PLANS[family.name], resume=resume, progress=progress, desc=family.name
    )
