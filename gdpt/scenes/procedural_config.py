"""The knobs of the procedural scene generator (:func:`gdpt.scenes.random_scene`): one frozen
dataclass, read by the generator's lights and cameras (:mod:`.procedural`) and by its rooms and
objects (:mod:`.procedural_layout`)."""

from __future__ import annotations

from dataclasses import dataclass

from gdpt.scenes.elements import check_resolution


@dataclass(frozen=True)
class RandomSceneConfig:
    """Knobs of :func:`random_scene`. Probabilities are per scene unless stated otherwise.

    Attributes:
        p_room: probability of a room (else an open set-up on a ground plane).
        p_open_side: probability that a room has one wall missing (the camera may look in).
        p_window: probability that a room is lit by an environment through a wall opening.
        p_env_open: probability that an open set-up is lit by an environment (sky).
        p_bitmap_env: probability that an environment is a procedural sky ``envmap`` rather
            than a ``constant`` emitter.
        p_extra_light: probability of adding a second kind of light.
        num_objects: inclusive range of the number of top-level objects.
        p_thinlens: probability, per view, of a thin-lens camera with visible defocus.
        target_radiance: rough radiance of lit diffuse surfaces, which sets the light power
            (image means, shadows and dark backgrounds included, typically land between 0.1x
            and 2.5x this value).
        env_shape: ``(height, width)`` of the procedural sky bitmap.
    """

    p_room: float = 0.6
    p_open_side: float = 0.35
    p_window: float = 0.4
    p_env_open: float = 0.7
    p_bitmap_env: float = 0.65
    p_extra_light: float = 0.4
    num_objects: tuple[int, int] = (3, 7)
    p_thinlens: float = 0.25
    target_radiance: float = 0.5
    env_shape: tuple[int, int] = (32, 64)

    def __post_init__(self) -> None:
        for name in (
            "p_room",
            "p_open_side",
            "p_window",
            "p_env_open",
            "p_bitmap_env",
            "p_extra_light",
            "p_thinlens",
        ):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"{name} must lie in [0, 1], got {getattr(self, name)}")
        lo, hi = self.num_objects
        if not 1 <= lo <= hi:
            raise ValueError("num_objects must be a range (lo, hi) with 1 <= lo <= hi")
        if self.target_radiance <= 0:
            raise ValueError("target_radiance must be positive")
        check_resolution(self.env_shape)
