"""How exact ``gdpt.render_differentiable``'s gradients are, per parameter kind.

On the built-in ``cbox-demo`` (``--size`` px, ``--spp`` samples, ``oidn-tuned``), the
derivative of a squared-error loss w.r.t. each RGB channel of a parameter, by autograd (the
network in torch, ``prb``'s adjoint pass replaying the primal's paths) and by a central
difference of the whole pipeline at the same seeds (render, features, network, loss). Both
differentiate one estimator, so they agree where the gradient is complete:

* ``light.emitter.radiance.value``: the features (albedo, normal, depth) do not depend on it;
* ``left.bsdf.reflectance.value``: the albedo feature does, and the features enter the
  gradient as constants, so autograd omits that share while the difference includes it.

It prints autograd, the difference and their ratio per channel. Then, on the scene of
``examples/inverse_denoised.py`` (the light hidden from the camera), the adjoint image, i.e.
the gradient of the loss w.r.t. the rendered image, with and without the network: its
largest entry, the rendered value there and the share of black pixels, and the network's
mean output against the reference's at the true parameters (over ``--seeds`` renders)::

    .venv/bin/python benchmarks/differentiable_gradients.py [--size 64] [--spp 4]
"""

from __future__ import annotations

import argparse

import drjit as dr
import mitsuba as mi
import numpy as np

import gdpt

PARAMETERS = {
    "light.emitter.radiance.value": 0.05,  # difference step (radiance ~10-20)
    "left.bsdf.reflectance.value": 0.01,  # (albedo in [0, 1])
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--size", type=int, default=64)
    parser.add_argument("--spp", type=int, default=4)
    parser.add_argument("--method", default="oidn-tuned")
    parser.add_argument("--seeds", type=int, default=8, help="renders for the mean output")
    args = parser.parse_args()

    gdpt.set_variant()
    scene = gdpt.load_scene("builtin:cbox-demo", long_side=args.size)
    params = mi.traverse(scene)
    prb = mi.load_dict({"type": "prb"})
    target = 0.8 * mi.render(scene, integrator=prb, spp=256, seed=77)

    def loss(key: str, value: np.ndarray, grad: bool = False):
        params[key] = mi.Color3f(*[float(v) for v in value])
        if grad:
            dr.enable_grad(params[key])
        params.update()
        image = gdpt.render_differentiable(scene, params, spp=args.spp, seed=3, method=args.method)
        return dr.mean(dr.square(image - target), axis=None)

    print(f"cbox-demo {args.size} px, {args.spp} spp, {args.method}; per channel R G B")
    for key, step in PARAMETERS.items():
        value = np.array(params[key].numpy()).ravel()
        dr.backward(loss(key, value, grad=True))
        autograd = dr.grad(params[key]).numpy().ravel()
        dr.disable_grad(params[key])
        central = np.empty(3)
        for c in range(3):
            e = np.zeros(3)
            e[c] = step
            up, down = loss(key, value + e).array[0], loss(key, value - e).array[0]
            central[c] = (up - down) / (2 * step)
        params[key] = mi.Color3f(*[float(v) for v in value])
        params.update()
        print(f"{key}")
        print(f"  autograd   {np.array2string(autograd, precision=5)}")
        print(f"  difference {np.array2string(central, precision=5)}")
        print(f"  ratio      {np.array2string(autograd / central, precision=3)}")
    adjoint_images(scene, args)


def adjoint_images(scene, args) -> None:
    """The adjoint image of the squared error with and without ``args.method`` (hidden light,
    ``max_depth`` 6 as in the example), and the network's mean output against the reference."""
    hidden = mi.load_dict({"type": "prb", "max_depth": 6, "hide_emitters": True})
    reference = mi.render(scene, integrator=hidden, spp=1024, seed=5).torch()
    means = []
    for seed in range(args.seeds):
        primal = mi.render(scene, integrator=hidden, spp=args.spp, seed=seed + 1).torch()
        features = gdpt.render(scene, spp=args.spp, seed=seed + 100, gradients=False)
        image = primal.clone().requires_grad_(True)
        out = gdpt.reconstruct_image(features.replace(primal=image), args.method)
        (out - reference).square().mean().backward()
        means.append(float(out.detach().mean()))
        if seed == 0:
            plain = (2 * (primal - reference) / primal.numel()).abs()
            adjoint = image.grad.abs()
            where = np.unravel_index(int(adjoint.argmax()), adjoint.shape)
            black = float((primal.amax(-1) == 0).float().mean())
            print(f"hidden light, {args.spp} spp: adjoint image largest entry")
            print(f"  plain image   {float(plain.max()):.3g}")
            there, truth = primal[where[:2]].max(), reference[where[:2]].max()
            print(
                f"  {args.method:<13} {float(adjoint.max()):.3g}, at a pixel rendered "
                f"{float(there):.3g} (reference {float(truth):.3g}); {black:.0%} of pixels black"
            )
    mean_ref = float(reference.mean())
    mean_out = float(np.mean(means))
    print(f"  {args.method} mean output / reference mean over {args.seeds} renders: "
          f"{mean_out / mean_ref:.3f}")  # fmt: skip


if __name__ == "__main__":
    main()
