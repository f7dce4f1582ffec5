"""Differentiable rendering and reconstruction: a loss on the reconstructed image drives
Mitsuba scene parameters (``gdpt.render_differentiable``).

:func:`render_differentiable` is a drop-in for :func:`mitsuba.render` in an inverse-rendering
loop: it renders the primal with a differentiable Mitsuba integrator (``prb``, path replay
backpropagation, Vicini et al. 2021) and reconstructs it with a gdpt method in torch, joined by
Dr.Jit's framework bridge (``dr.wrap(source="drjit", target="torch")``, Dr.Jit's
``docs/interop.rst``). The result is a Dr.Jit tensor in the AD graph of the scene parameters::

    scene = gdpt.load_scene("builtin:cbox-demo")
    params = mi.traverse(scene)
    opt = mi.ad.Adam(lr=0.5)
    opt["light.emitter.radiance.value"] = mi.Color3f(8.0, 8.0, 8.0)
    params.update(opt)
    for it in range(100):
        image = gdpt.render_differentiable(scene, params, spp=4, seed=it + 1)  # oidn-tuned
        loss = dr.mean(dr.square(image - reference), axis=None)
        dr.backward(loss)  # torch backward through the denoiser, then prb's
        opt.step()
        params.update(opt)

Seeds of the adjoint pass. :func:`mitsuba.render` traces the adjoint pass with other random
numbers than the primal pass (its ``seed_grad``): for a loss such as the squared error of the
image, the product of two independent estimates is an unbiased gradient of the noise-free
loss. Through a nonlinear reconstruction it is not: the
adjoint image ``J_D^T dloss/dD`` of one sample set, weighted by another set's path derivatives,
has the expectation ``E[J_D^T dloss/dD] . dE[I]/dtheta`` instead of the derivative of the
expected loss, and the fine-tuned OIDN network's adjoint image is largest at pixels the
low-sample render left black, where independent paths find light
(``examples/inverse_denoised.py``: its optimisation stalls). Replaying the primal's paths in
the adjoint pass (``seed_grad == seed``, the default when a method reconstructs) gives the
derivative of the estimator that was evaluated, an unbiased gradient of the expected loss of
the reconstructed image; there path derivatives vanish where the render found no light.

What is differentiated: the primal only. The gradient-domain integrators (``gdpt``,
``gdpt_rr``) are forward-only (they have no adjoint pass), so methods that read ``dx``/``dy``
are refused. The feature buffers a network reads (albedo, normal, depth) are rendered by
``gdpt`` with ``gradients=False`` for every call, with the same ``max_depth``, and enter as
constants: the gradient omits the path through them. That path is zero for parameters the
features do not depend on (an emitter's radiance); for a diffuse albedo the
albedo feature moves with the parameter and its share of the derivative is dropped.

Both frameworks work on the variant's device: on CUDA the primal, the features and the
reconstruction stay on the GPU (DLPack views, no host copy).
"""

from __future__ import annotations

import warnings
from functools import cache, partial
from typing import Any

#: Mixed into the seed of the features render (independent of the primal's samples).
FEATURE_SEED_SALT = 0x5BD1E995


class NonFiniteGradientWarning(RuntimeWarning):
    """The gradient w.r.t. the rendered image had NaN/Inf entries (passed on unchanged)."""


def render_differentiable(
    scene: Any,
    params: Any = None,
    *,
    spp: int,
    method: str | None = "oidn-tuned",
    seed: int = 0,
    seed_grad: int | None = None,
    spp_grad: int = 0,
    integrator: str | Any = "prb",
    max_depth: int = 6,
    rr_depth: int = 5,
    alpha: float = 0.2,
    **options: Any,
):
    """Render with a differentiable integrator and reconstruct with ``method``, differentiably.

    Args:
        scene: an ``mi.Scene`` (that ``params`` come from), or any source of
            :func:`gdpt.load_scene`.
        params: ``mi.traverse(scene)`` with gradients enabled on the parameters to optimise
            (``dr.enable_grad``), as for :func:`mitsuba.render`; ``None``: none.
        spp (int): samples per pixel of the primal (and of the features).
        method (str | None): a differentiable reconstruction method that reads no gradients
            (:data:`gdpt.methods.METHODS`; ``"oidn-tuned"``, the OIDN U-Net fine-tuned here),
            or ``None`` for the integrator's image itself.
        seed (int): seed of the primal render; the features use ``seed ^ FEATURE_SEED_SALT``.
        seed_grad (int | None): seed of the integrator's adjoint pass: ``seed`` (nonzero)
            replays the primal's paths (see the module docstring), another value
            decorrelates as in :func:`mitsuba.render` (0: derived from ``seed``); ``None``:
            replay when ``method`` reconstructs, 0 for ``method=None``.
        spp_grad (int): samples per pixel of the adjoint pass (0: ``spp``; a replay needs
            ``spp``).
        integrator: a Mitsuba AD integrator plugin name (``"prb"``, ``"prb_projective"``
            for visibility-dependent parameters, ...), created with ``max_depth`` and
            ``rr_depth``, or an integrator instance.
        max_depth (int): longest path, Mitsuba's convention (the features use it too).
        rr_depth (int): depth at which Russian roulette starts.
        alpha (float): passed to the reconstruction (methods without it ignore it).
        **options: method options, as for :func:`gdpt.reconstruct_image`.

    Returns:
        ``(H, W, 3)`` float32 ``mi.TensorXf`` on the variant's device, attached to the AD
        graph of ``params``: ``dr.backward`` of a loss on it propagates through the
        reconstruction (torch autograd) and the integrator's adjoint pass into ``params``.
        A backward pass whose gradient w.r.t. the rendered image holds NaN/Inf entries warns
        (:class:`NonFiniteGradientWarning`, with the count) and passes them on unchanged
        (Mitsuba's adjoint pass then drops non-finite adjoint pixels).

    Raises:
        ValueError: ``spp < 1``; a replay with ``spp_grad != spp``; the active variant has no
            automatic differentiation (the message names ``llvm_ad_rgb`` and ``cuda_ad_rgb``);
            ``integrator`` is not differentiable; ``method`` is unknown, cannot run here, reads
            gradients or is not differentiable (named).
    """
    import drjit as dr
    import mitsuba as mi

    from gdpt.scenes.loading import load_scene

    if spp < 1:
        raise ValueError(f"spp must be >= 1, got {spp}")
    _check_variant(mi.variant())
    name = _check_method(method)
    scene = load_scene(scene, check=False)  # rendered by Mitsuba's own integrators
    if isinstance(integrator, str):
        integrator = mi.load_dict(
            {"type": integrator, "max_depth": int(max_depth), "rr_depth": int(rr_depth)}
        )
    if not isinstance(integrator, mi.CppADIntegrator):
        raise ValueError(
            f"integrator {type(integrator).__name__} is not differentiable; use a Mitsuba AD "
            "integrator such as 'prb'"
        )
    replay = name is not None if seed_grad is None else seed_grad == seed != 0
    if replay:
        if spp_grad not in (0, spp):
            raise ValueError(f"a replay traces the primal's spp={spp}, not spp_grad={spp_grad}")
        sensor = scene.sensors()[0]
        primal = dr.custom(
            _replay_op(), scene, sensor, dict(params or {}), params, integrator, seed, spp
        )
    else:
        primal = mi.render(
            scene, params, integrator=integrator, seed=seed, seed_grad=seed_grad or 0, spp=spp,
            spp_grad=spp_grad,
        )  # fmt: skip
    if primal.shape[2] != 3:
        raise ValueError(
            f"the film renders {primal.shape[2]} channels; gdpt reconstructs RGB "
            "(hdrfilm pixel_format 'rgb')"
        )
    if name is None:
        return primal
    with dr.suspend_grad():
        features = _features(scene, spp, seed, max_depth, rr_depth)
    reconstruct = _reconstruction(name, features, alpha, options)
    if not dr.grad_enabled(primal):
        import torch

        with torch.no_grad():
            return mi.TensorXf(reconstruct(primal.torch()))
    return dr.wrap(source="drjit", target="torch")(reconstruct)(primal)


@cache
def _replay_op() -> type:
    """A Dr.Jit custom operation: ``integrator.render`` whose derivative passes
    (``render_forward``, ``render_backward``) use the primal's seed and spp, i.e. replay its
    paths. Made on first use: its base class needs Dr.Jit, which :mod:`gdpt` imports only
    after :func:`gdpt.set_variant` located libLLVM."""
    import drjit as dr

    class Replay(dr.CustomOp):
        def eval(self, scene, sensor, _detached, params, integrator, seed, spp):
            self.args = scene, params, sensor, seed, spp
            self.integrator = integrator
            with dr.suspend_grad():
                return integrator.render(
                    scene=scene, sensor=sensor, seed=seed, spp=spp, develop=True, evaluate=False
                )

        def forward(self):
            self.set_grad_out(self.integrator.render_forward(*self.args))

        def backward(self):
            scene, params, sensor, seed, spp = self.args
            self.integrator.render_backward(scene, params, self.grad_out(), sensor, seed, spp)

        def name(self):
            return "gdpt replayed render"

    return Replay


def _check_variant(variant: str | None) -> None:
    """Raise unless ``variant`` has automatic differentiation."""
    if variant is None or "_ad_" not in variant:
        raise ValueError(
            f"the Mitsuba variant {variant!r} has no automatic differentiation; call "
            f"gdpt.set_variant('llvm_ad_rgb') (CPU) or gdpt.set_variant('cuda_ad_rgb') (GPU)"
        )


def _check_method(method: str | None) -> str | None:
    """The current name of ``method`` if it can run here, is differentiable and reads no
    gradients; ``None`` for ``None``."""
    if method is None:
        return None
    from gdpt.methods import METHODS

    name = METHODS.resolve(method, stacklevel=4)
    METHODS.check([name])
    usable = ", ".join(n for n, m in METHODS.items() if m.differentiable and not m.gradients)
    if METHODS[name].gradients:
        raise ValueError(
            f"method {name!r} reads the gradients dx/dy, which only the gdpt integrator renders "
            "and it is forward-only (it has no adjoint pass); differentiable methods that read "
            f"the primal alone: {usable}"
        )
    if not METHODS[name].differentiable:
        raise ValueError(
            f"method {name!r} is not differentiable w.r.t. its input buffers; differentiable "
            f"methods that read the primal alone: {usable}"
        )
    return name


def _features(scene: Any, spp: int, seed: int, max_depth: int, rr_depth: int) -> Any:
    """Albedo, normal and depth from ``gdpt`` without gradients (constants of the AD graph)."""
    from gdpt.rendering import render

    return render(
        scene,
        spp=spp,
        seed=(int(seed) ^ FEATURE_SEED_SALT) & 0xFFFFFFFF,
        gradients=False,
        features=True,
        max_depth=int(max_depth),
        rr_depth=int(rr_depth),
    )


def _reconstruction(name: str, features: Any, alpha: float, options: dict[str, Any]):
    """``f(primal) -> image`` on torch ``(H, W, 3)`` float32 tensors: ``method`` on ``primal``
    and the ``features`` render's albedo, normal and depth; a backward pass through it warns
    about the non-finite entries of the gradient that reaches ``primal``."""
    from gdpt.methods import reconstruct_image

    def reconstruct(primal):
        if primal.requires_grad:
            primal.register_hook(partial(_warn_non_finite, name))
        buffers = features.replace(primal=primal, metadata={})
        return reconstruct_image(buffers, name, alpha=alpha, **options)

    return reconstruct


def _warn_non_finite(method: str, grad) -> None:
    """Warn (:class:`NonFiniteGradientWarning`) with the count of NaN/Inf entries of ``grad``,
    the gradient w.r.t. the rendered image; ``grad`` is left unchanged."""
    import torch

    bad = int((~torch.isfinite(grad)).sum())
    if bad:
        warnings.warn(
            f"{bad} of {grad.numel()} entries of the gradient w.r.t. the rendered image are NaN "
            f"or Inf (method {method!r}); they are passed on to the scene parameters unchanged",
            NonFiniteGradientWarning,
            stacklevel=2,
        )
