"""The learning-rate schedule of NGPT (Kettunen et al. 2019; its learning-rate options in
``reconstruct/config.py`` of the public code, ``github.com/mkettune/ngpt``).

Base learning rate ``5e-4``, geometric warm-up from ``lr / 1e4`` and an exponential ramp-down
(:func:`learning_rate`). The reference warms up over 10 k minibatches and halves the rate every
70 k after 50 k, for runs of ~600 k minibatches; CPU runs are ~1000x shorter, so by default the
schedule is scaled to the run length (:meth:`~gdpt.training.config.TrainConfig.resolved`):
warm-up over 2 % of the steps, ramp-down from 25 % of the steps with a half-life of 25 % of the
steps (the rate ends at 1/8 of the base). The resolved values are stored in ``config.json``.
The reference's "no learning for 100 minibatches after a restart" is not needed: the Adam state
is checkpointed.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from gdpt.training.config import TrainConfig


def learning_rate(step: int, config: TrainConfig) -> float:
    """Learning rate of update ``step`` (0-based) for a :meth:`TrainConfig.resolved` config.

    ``lr * 1e-4 * 1e4 ** min(1, (1 + step) / warmup_steps) * 0.5 ** (max(0, step - decay_start)
    / half_life)`` (reference formula with scaled lengths; no warm-up if ``warmup_steps == 0``).
    """
    warm = config.warmup_steps
    factor = 1.0 if not warm else 1e-4 * 1e4 ** min(1.0, (1 + step) / warm)
    return config.lr * factor * 0.5 ** (max(0, step - config.decay_start) / config.half_life)
