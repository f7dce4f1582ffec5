"""Screened-Poisson reconstruction of gradient-domain renders (L2 closed form, weighted CG, L1).

Given a noisy primal image ``p`` and noisy forward-difference gradients ``dx``, ``dy`` (the G-PT
buffers), find the image ``x`` that best agrees with all three. With the constraint operator
``P x = [alpha * x ; Dx x ; Dy x]`` and data ``b = [alpha * p ; dx ; dy]`` the energies are::

    L2:  E2(x) = alpha^2 ||x - p||^2 + ||Dx x - dx||^2 + ||Dy x - dy||^2
    L1:  E1(x) = sum_i alpha |x_i - p_i| + sum_i |(Dx x - dx)_i| + sum_i |(Dy x - dy)_i|

where in ``E1`` every ``|.|`` is the Euclidean norm of one constraint's channel vector (RGB),
as in the reference solver of Kettunen et al. 2015 / Manzi et al. (``poisson/src`` of
``mkettune/ngpt``). Default ``alpha = 0.2``.

Conventions shared with the rest of gdpt (``gdpt.buffers``)::

    dx[y, x] = I[y, x + 1] - I[y, x]      (last column unused)
    dy[y, x] = I[y + 1, x] - I[y, x]      (last row unused, y grows downward)

The forward-difference rows at the last column / last row do not exist (Neumann boundary), so
the supplied ``dx[:, W-1]`` and ``dy[H-1, :]`` have no effect on any result or energy here.
``Dx^T Dx + Dy^T Dy`` is then the reflecting-boundary graph Laplacian ``L``, which the
orthonormal 2-D DCT-II diagonalises with eigenvalues ``(2 - 2cos(pi k/W)) + (2 - 2cos(pi l/H))``.

Solvers (:mod:`.solvers`):

* :func:`solve_l2`: exact L2 minimiser, ``x = IDCT(DCT(rhs) / lambda)`` (FFT based, :mod:`.dct`).
* :func:`solve_weighted_cg`: (preconditioned) conjugate gradients on
  ``P^T W P x = P^T W b`` with per-constraint weights ``W`` (:mod:`.cg`).
* :func:`solve_l1`: IRLS for ``E1`` (:mod:`.l1`). Presets are registered by name in
  :data:`L1_PRESETS`: ``"l1"`` reproduces the reference ``L1D`` schedule, ``"fast"`` is a
  preconditioned variant that reaches an equal or lower ``E1`` several times faster.
* :func:`solve`: one solver by name (:data:`SOLVERS`: ``"l2"``, ``"l2-cg"``, ``"l1"``,
  ``"l1-fast"``).

The energies are in :mod:`.energy`, input checks and the internal layout in :mod:`.problem`,
the preconditioners in :mod:`.precond` (the multigrid V-cycle in :mod:`.multigrid`), the
backward pass in :mod:`.adjoint`.

Layout, dtype, device: images are ``(..., H, W, C)`` tensors (the project's HWC layout, any
leading batch dimensions, any channel count) or ``(H, W)`` single-channel images. All inputs must
be on one device; computation happens on that device. The compute and output dtype is
``torch.float64`` if any input is float64, else ``torch.float32`` (half/bfloat16/integer inputs
are promoted to float32). Leading batch entries are solved independently.

Non-finite inputs: a constraint (the channel vector of one primal pixel or one gradient) with any
NaN/Inf channel is treated as *missing*: it gets weight zero (a missing primal sample keeps a tiny
weight ``MISSING_PRIMAL_WEIGHT`` towards 0 so that the system stays non-singular). The number of
dropped constraints is reported through a :class:`NonFiniteInputWarning` and in
:class:`SolveInfo` (``return_info=True``). Results are always finite: values beyond the dtype's
range are clamped to its largest finite value.

Gradients: the solvers are differentiable w.r.t. ``primal``, ``dx`` and ``dy`` in torch
autograd. The result solves ``A x = P^T W b`` with ``A = P^T W P`` symmetric positive definite,
so the backward pass solves the adjoint system ``A lam = g`` for the incoming gradient ``g``
(the same solver: the DCT closed form for uniform weights, else preconditioned CG; the forward
iterations are not unrolled) and returns ``alpha^2 Wp lam``, ``Wx Dx lam`` and ``Wy Dy lam``
(zero at the unused last column / row and at missing constraints; :mod:`.adjoint`); the adjoint
method of e.g. Giles and Pierce 2000, *An introduction to the adjoint approach to design*. This is
exact for :func:`solve_l2` and for :func:`solve_weighted_cg` (its weights are constants and get
no gradient). For :func:`solve_l1` it is an approximation: the last IRLS weights are held
fixed, i.e. it is the derivative of the weighted least-squares problem the last round solved,
not of the reweighting itself.

Only ``torch`` and ``numpy`` are imported here (layering rule of ``gdpt.reconstruct``).
"""

from .adjoint import ADJOINT_MAX_ITER
from .cg import default_tol
from .dct import dct2, idct2
from .energy import l1_energy, l2_energy
from .l1 import L1_PRESETS, L1Preset, get_l1_preset
from .precond import Precondition
from .problem import DEFAULT_ALPHA, MISSING_PRIMAL_WEIGHT, NonFiniteInputWarning, SolveInfo
from .solvers import SOLVERS, solve, solve_l1, solve_l2, solve_weighted_cg

__all__ = [
    "ADJOINT_MAX_ITER",
    "DEFAULT_ALPHA",
    "L1_PRESETS",
    "MISSING_PRIMAL_WEIGHT",
    "SOLVERS",
    "L1Preset",
    "NonFiniteInputWarning",
    "Precondition",
    "SolveInfo",
    "dct2",
    "default_tol",
    "get_l1_preset",
    "idct2",
    "l1_energy",
    "l2_energy",
    "solve",
    "solve_l1",
    "solve_l2",
    "solve_weighted_cg",
]
