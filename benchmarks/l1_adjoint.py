"""How far the adjoint solve of ``l1-fast`` gets in its iteration cap, at the render's size.

Runs the ``fast`` IRLS schedule on a render's primal and gradients (``--buffers``: a file of
``gdpt.save_buffers``, else ``builtin:cbox-demo`` rendered at ``--size`` with 4 gradient spp),
prints the spread of its last weights and of the system's diagonal, then solves the adjoint
system ``A lam = g`` of that solve (:class:`gdpt.reconstruct.poisson.adjoint.System`: Jacobi-PCG,
``tol`` 1e-5 relative to ``||g||``, at most :data:`~gdpt.reconstruct.poisson.ADJOINT_MAX_ITER`
iterations) for a random ``g``, and compares it with a solve of ``--reference-iterations``
iterations: iterations used, the relative residual the recursion reports, the true one
(``||g - A lam|| / ||g||``, and in the Jacobi norm ``sqrt(r^T D^-1 r)``) and the relative error
of ``lam`` (2-norm and ``A``-norm) against the reference. No timing::

    .venv/bin/python benchmarks/l1_adjoint.py --buffers /tmp/cbox720.exr \\
        --reference-iterations 3000
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch
from gdpt.reconstruct.poisson import ADJOINT_MAX_ITER, cg, dct, l1, precond, problem

import gdpt
from gdpt.scenes import builtin_scene


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--buffers", type=Path)
    parser.add_argument("--size", default="1280x720")
    parser.add_argument("--alpha", type=float, default=problem.DEFAULT_ALPHA)
    parser.add_argument("--reference-iterations", type=int, default=3000)
    args = parser.parse_args()
    gdpt.set_variant()
    if args.buffers:
        b = gdpt.load_buffers(args.buffers)
    else:
        width, height = (int(v) for v in args.size.split("x"))
        scene = gdpt.load_scene(builtin_scene("cbox-demo", resolution=(width, height)))
        b = gdpt.render(scene, spp=4, primal_spp=10)
    prob = problem.prepare(b.primal, b.dx, b.dy, args.alpha)
    laplace = dct.LaplaceDCT(*prob.p.shape[-2:], prob.p)
    _, its, _, weights = l1.irls(prob, l1.get_l1_preset("fast"), laplace, None)
    print(f"{tuple(b.primal.shape)}: fast, {its} CG iterations")
    for name in ("p", "x", "y"):
        w = getattr(weights, name)
        print(f"  weights {name}: {float(w.min()):.3g} .. {float(w.max()):.3g}")
    op = cg.Operator(prob, weights)
    jacobi = precond.make_precond("jacobi", prob, weights, laplace, op)
    print(f"  diagonal: {float(op.diag.min()):.3g} .. {float(op.diag.max()):.3g}")
    g = torch.rand(prob.p.shape, generator=torch.Generator().manual_seed(0))
    tol = cg.default_tol(g.dtype)

    def solve(cap: int) -> tuple[torch.Tensor, int, float]:
        return cg.pcg(op, g, torch.zeros_like(g), max_iter=cap, tol=tol, precond=jacobi)

    def true_residuals(lam: torch.Tensor) -> tuple[float, float]:
        r = g - op(lam)
        euclid = float((cg._dot(r, r) / cg._dot(g, g)).sqrt().max())
        scaled = float((cg._dot(r, jacobi(r)) / cg._dot(g, jacobi(g))).sqrt().max())
        return euclid, scaled

    ref, ref_its, ref_res = solve(args.reference_iterations)
    print(
        f"reference: {ref_its} iterations, recursion {ref_res:.2e}, true "
        "(Euclidean, Jacobi norm) {:.2e}, {:.2e}".format(*true_residuals(ref))
    )
    lam, lam_its, lam_res = solve(ADJOINT_MAX_ITER)
    e = lam - ref
    err_a = float((cg._dot(e, op(e)) / cg._dot(ref, op(ref))).sqrt().max())
    print(
        f"adjoint (cap {ADJOINT_MAX_ITER}, tol {tol:g}): {lam_its} iterations, recursion "
        f"{lam_res:.2e}, true (Euclidean, Jacobi norm) "
        "{:.2e}, {:.2e}".format(*true_residuals(lam))
    )
    err_2 = float(e.norm() / ref.norm())
    print(f"  error against the reference: 2-norm {err_2:.3f}, A-norm {err_a:.3f}")


if __name__ == "__main__":
    main()
