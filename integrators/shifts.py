"""The shift mappings of ``gdpt``'s hybrid shift that have a Jacobian, as pure functions.

The integrator composes them per vertex (:mod:`gdpt.integrators.gdpt`); they are public so that
their Jacobians can be tested against finite differences of the mappings themselves. Inputs are
Dr.Jit arrays of the active variant (any width); outputs have the same width.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from .common import safe_div


def reconnection_jacobian(
    n: mi.Normal3f, d_x: mi.Vector3f, dist2_x: mi.Float, d_y: mi.Vector3f, dist2_y: mi.Float
) -> mi.Float:
    """|d w_y / d w_x| of a reconnection to the vertex z with normal ``n``: the base arrives
    along the unit direction ``d_x`` over squared distance ``dist2_x``, the offset along ``d_y``
    over ``dist2_y``. The ratio of the solid-angle-to-area factors, |n.d_y| d_x^2 / (|n.d_x| d_y^2),
    0 where it is not finite."""
    return safe_div(dr.abs(dr.dot(n, d_y)) * dist2_x, dr.abs(dr.dot(n, d_x)) * dist2_y)


def half_vector_shift(
    wi_x: mi.Vector3f, wo_x: mi.Vector3f, eta_x: mi.Float, wi_y: mi.Vector3f
) -> tuple[mi.Vector3f, mi.Float, mi.Bool]:
    """Copy the base's half vector to the offset (Kettunen et al. 2015; the refraction
    Jacobian follows from Walter et al. 2007's d omega_h / d omega_o).

    ``wi_x, wo_x``: the base's local directions at x_i, ``eta_x``: its sample's relative IOR
    (``bs.eta``, 1 for reflection), ``wi_y``: the offset's local incident direction. Returns the
    offset's local outgoing direction, the Jacobian |d wo_y / d wo_x| and a validity mask
    (refraction: eta != 1, both on the same side, no total internal reflection of the offset).
    """
    reflect = mi.Frame3f.cos_theta(wi_x) * mi.Frame3f.cos_theta(wo_x) > 0
    eta = dr.select(reflect, 1.0, eta_x)
    # Mitsuba's generalised half vector wi + eta wo, turned into the upper hemisphere
    h = dr.normalize(wi_x + eta * wo_x)
    h = dr.mulsign(h, mi.Frame3f.cos_theta(h))
    cos_xi, cos_xo, cos_yi = dr.dot(wi_x, h), dr.dot(wo_x, h), dr.dot(wi_y, h)
    # The offset refracts through the same interface: fresnel() takes the interior / exterior
    # IOR and orients itself by the sign of cos_yi, which must match the base's side.
    eta_int = dr.select(mi.Frame3f.cos_theta(wi_x) > 0, eta, dr.rcp(eta))
    F, cos_t, _, eta_ti = mi.fresnel(cos_yi, eta_int)
    wo_y = dr.select(reflect, mi.reflect(wi_y, h), mi.refract(wi_y, h, cos_t, eta_ti))
    cos_yo = dr.dot(wo_y, h)
    J_reflect = safe_div(dr.abs(cos_yo), dr.abs(cos_xo))
    J_refract = safe_div(
        dr.square(cos_yi + eta * cos_yo) * dr.abs(cos_xo),
        dr.square(cos_xi + eta * cos_xo) * dr.abs(cos_yo),
    )
    same_side = (cos_xi * cos_yi > 0) & (
        mi.Frame3f.cos_theta(wi_x) * mi.Frame3f.cos_theta(wi_y) > 0
    )
    ok = reflect | ((eta != 1) & same_side & (F < 1))
    return wo_y, dr.select(reflect, J_reflect, J_refract), ok
