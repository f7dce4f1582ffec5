"""The output of ``mi.render(scene)`` with the ``gdpt`` / ``gdpt_rr`` plugin as buffers.

With ``<integrator type="gdpt">`` in a scene, ``mi.render(scene, spp=N, seed=S)`` returns one
``(H, W, C)`` ``mi.TensorXf``: the primal, the gradients and the features side by side, named
channel by channel by the integrator's ``aov_names()`` (``primal.R``, ..., ``dx.R``, ...,
``normal.X``, ``depth.Y``, ...; which buffers are there depends on the plugin's properties).
:func:`buffers_from_aovs` cuts it into a :class:`~gdpt.buffers.GradientBuffers` (views of the
same memory), as :func:`gdpt.render` does with the tensor it renders.
"""

from __future__ import annotations

from typing import Any

import torch

from gdpt.buffers import GradientBuffers


def buffers_from_aovs(
    tensor: Any, integrator: Any, *, seed: int | None = None, spp: int | None = None
) -> GradientBuffers:
    """Split the tensor a ``gdpt`` / ``gdpt_rr`` integrator rendered into buffers.

    Args:
        tensor: ``(H, W, C)`` ``mi.TensorXf`` (or a torch tensor) returned by ``mi.render`` or
            ``integrator.render`` with this ``integrator``, ``C = len(integrator.aov_names())``.
        integrator: the scene's integrator (``scene.integrator()``), after that render: its
            ``aov_names()`` name the channels, and its sample counts and guard counts of the
            last render fill ``spp`` and the metadata.
        seed (int | None): the render's seed, stored in ``metadata["seed"]`` when given.
        spp (int | None): the render's samples per pixel; ``None`` takes the integrator's
            count of its last render.

    Returns:
        GradientBuffers: float32 HWC views of ``tensor`` on its device (an ``llvm_*``
        variant: CPU; ``cuda_*``: the GPU, zero-copy through DLPack), with ``spp`` and
        ``metadata`` (integrator, max depth, variant, guard counts, half-buffer sample counts
        with ``halves``, and the seed) and, after a render with a gradient mask, the
        ``gradient_mask`` of the gradients it traced.

    Raises:
        TypeError: ``integrator`` is not a ``gdpt`` / ``gdpt_rr`` integrator.
        ValueError: the tensor is not ``(H, W, C)`` with the integrator's channel count.
    """
    import mitsuba as mi

    from gdpt.integrators.common import GradientIntegratorBase

    if not isinstance(integrator, GradientIntegratorBase):
        raise TypeError(
            f"integrator must be gdpt or gdpt_rr (scene.integrator() of a scene with "
            f'<integrator type="gdpt">), got {type(integrator).__name__}'
        )
    if not isinstance(tensor, torch.Tensor):
        tensor = tensor.torch()  # zero-copy (DLPack) view of the Dr.Jit tensor
    names = integrator.aov_names()
    if tensor.dim() != 3 or tensor.shape[2] != len(names):
        raise ValueError(
            f"expected an (H, W, {len(names)}) tensor for this {integrator.plugin_name} "
            f"integrator's channels ({', '.join(names)}), got {tuple(tensor.shape)}"
        )
    views: dict[str, torch.Tensor] = {}
    offset = 0
    for name, count in _buffer_channels(names):
        views[name] = tensor[..., offset : offset + count]
        offset += count
    metadata: dict[str, Any] = {
        "integrator": integrator.plugin_name,
        "max_depth": int(min(integrator.max_depth, 2**31 - 1)),
        "variant": mi.variant(),
        "guard_counts": dict(integrator.guard_counts),
    }
    if seed is not None:
        metadata["seed"] = int(seed)
    if integrator.halves:
        metadata["half_spp"] = list(integrator.half_spp)
    spp = int(sum(integrator.half_spp)) if spp is None else int(spp)
    mask = integrator.rendered_gradient_mask
    if mask is not None and integrator.gradients:
        from gdpt.integrators.common import traced_gradients

        views["gradient_mask"] = torch.from_numpy(traced_gradients(mask)).to(tensor.device)
    return GradientBuffers(**views, spp=spp, metadata=metadata)


def _buffer_channels(names: list[str]) -> list[tuple[str, int]]:
    """``["primal.R", "primal.G", "primal.B", "depth.Y"]`` -> ``[("primal", 3), ("depth", 1)]``."""
    out: list[tuple[str, int]] = []
    for name in names:
        buffer = name.rpartition(".")[0]
        if out and out[-1][0] == buffer:
            out[-1] = (buffer, out[-1][1] + 1)
        else:
            out.append((buffer, 1))
    return out
