"""Jacobians of the shift mappings (half-vector copy, reconnection) against finite differences
of the mappings themselves.

Estimator tests cannot see a wrong Jacobian on neighbouring pixels: there J is close to 1 and
the two MIS halves of a pixel pair absorb a constant error. Here the mapping wo_x -> wo_y is
differentiated numerically: directions around wo_x are parametrised by an orthonormal tangent
basis (unit solid-angle density at the centre), so |d wo_y/du x d wo_y/dv| is the solid-angle
Jacobian |d wo_y / d wo_x| that the shift must return.
"""

from __future__ import annotations

import numpy as np
import pytest

STEP = 1e-3
#: The half-vector mapping runs in float32 (Mitsuba), so its central differences carry rounding
#: of about 2^-24 / STEP = 6e-5 per component, more where refraction near total internal
#: reflection magnifies it (measured max relative differences: reflect 1.9e-4, refract outside
#: 6.3e-5, inside 1.2e-3; larger steps are worse there: 1.2e-2 at 3e-3).
RTOL_HALF_VECTOR = 2e-3
#: The reconnection mapping is differenced in float64, the Jacobian is float32 (measured max
#: relative difference 5.4e-6).
RTOL_RECONNECTION = 2e-5


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _tangents(w):
    helper = np.where(np.abs(w[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
    t1 = _unit(np.cross(w, helper))
    return t1, np.cross(w, t1)


def _configurations(kind: str, n: int = 256, seed: int = 7):
    """Base (wi_x, wo_x, eta_x) produced by a microfacet normal m, and a nearby wi_y; only the
    configurations a BSDF could sample (wo on the lobe's side of the surface, no TIR)."""
    import drjit as dr
    import mitsuba as mi

    rng = np.random.default_rng(seed)
    m = _unit(rng.normal(size=(n, 3)) * [0.3, 0.3, 0] + [0, 0, 1])
    wi = _unit(rng.normal(size=(n, 3)) * [0.5, 0.5, 0] + [0, 0, 1])
    if kind == "refract-inside":
        wi[:, 2] *= -1
    wi_y = _unit(wi + rng.normal(size=(n, 3)) * 0.08)
    wi_j, m_j = mi.Vector3f(wi.T), mi.Vector3f(m.T)
    if kind == "reflect":
        wo, eta = mi.reflect(wi_j, m_j), np.ones(n)
    else:
        F, cos_t, eta_it, eta_ti = mi.fresnel(dr.dot(wi_j, m_j), 1.5)
        wo, eta = mi.refract(wi_j, m_j, cos_t, eta_ti), np.array(eta_it)
    wo = np.array(wo).T
    lobe = np.sign(wo[:, 2] * wi[:, 2]) == (1 if kind == "reflect" else -1)
    # grazing and total internal reflection (refract() then returns no unit vector) excluded
    keep = lobe & (np.abs(wo[:, 2]) > 0.05) & (np.abs(np.linalg.norm(wo, axis=-1) - 1) < 1e-4)
    return wi[keep], wo[keep], eta[keep], wi_y[keep]


@pytest.mark.parametrize("kind", ["reflect", "refract-outside", "refract-inside"])
def test_half_vector_jacobian_matches_finite_differences(variant, kind):
    import mitsuba as mi
    from gdpt.integrators.shifts import half_vector_shift

    wi, wo, eta, wi_y = _configurations(kind)
    t1, t2 = _tangents(wo)

    def shift(d):
        out, J, ok = half_vector_shift(
            mi.Vector3f(wi.T), mi.Vector3f(_unit(d).T), mi.Float(eta), mi.Vector3f(wi_y.T)
        )
        return np.array(out).T.astype(np.float64), np.array(J), np.array(ok)

    wo_y, J, ok = shift(wo)
    du = (shift(wo + STEP * t1)[0] - shift(wo - STEP * t1)[0]) / (2 * STEP)
    dv = (shift(wo + STEP * t2)[0] - shift(wo - STEP * t2)[0]) / (2 * STEP)
    J_fd = np.linalg.norm(np.cross(du, dv), axis=-1)

    assert ok.sum() >= len(ok) // 2, f"only {ok.sum()} of {len(ok)} shifts valid"
    np.testing.assert_allclose(np.linalg.norm(wo_y[ok], axis=-1), 1.0, atol=1e-5)
    np.testing.assert_allclose(J[ok], J_fd[ok], rtol=RTOL_HALF_VECTOR)
    # the offset keeps the base's lobe on the shared microfacet: reflected or transmitted
    h = _unit(wi + np.where(kind == "reflect", 1.0, eta)[:, None] * wo)
    side = np.sign(np.sum(wo_y * h, -1) * np.sum(wi_y * h, -1))[ok]
    assert np.all(side == (1 if kind == "reflect" else -1))


def test_half_vector_shift_is_identity_on_the_base(variant):
    """wi_y = wi_x maps wo_x to itself with Jacobian 1 (the base is its own offset)."""
    import mitsuba as mi
    from gdpt.integrators.shifts import half_vector_shift

    for kind in ("reflect", "refract-outside", "refract-inside"):
        wi, wo, eta, _ = _configurations(kind)
        wo_y, J, ok = half_vector_shift(
            mi.Vector3f(wi.T), mi.Vector3f(wo.T), mi.Float(eta), mi.Vector3f(wi.T)
        )
        ok = np.array(ok)
        assert ok.all(), kind
        np.testing.assert_allclose(np.array(wo_y).T, wo, atol=2e-5)
        np.testing.assert_allclose(np.array(J), 1.0, rtol=1e-4)


def test_reconnection_jacobian_matches_finite_differences(variant):
    """Base x and offset y see the vertex z on a plane; moving the base direction moves z and
    with it the reconnected direction z - y."""
    import mitsuba as mi
    from gdpt.integrators.shifts import reconnection_jacobian

    rng = np.random.default_rng(11)
    n_cases = 256
    normal = _unit(rng.normal(size=(n_cases, 3)) * [0.4, 0.4, 0] + [0, 0, 1])
    origin = rng.normal(size=(n_cases, 3)) * 0.3  # a point of the plane
    x = origin + normal * rng.uniform(0.5, 2.0, (n_cases, 1)) + rng.normal(size=(n_cases, 3))
    y = x + rng.normal(size=(n_cases, 3)) * 0.2
    z = origin + np.cross(normal, rng.normal(size=(n_cases, 3))) * 0.5
    wo = _unit(z - x)
    keep = (np.sum((x - origin) * normal, -1) > 0.2) & (np.sum((y - origin) * normal, -1) > 0.2)
    keep &= np.abs(np.sum(wo * normal, -1)) > 0.1
    normal, origin, x, y, wo = normal[keep], origin[keep], x[keep], y[keep], wo[keep]

    def hit(d):
        d = _unit(d)
        t = np.sum((origin - x) * normal, -1) / np.sum(d * normal, -1)
        return x + t[:, None] * d, t

    def offset_dir(d):
        return _unit(hit(d)[0] - y)

    t1, t2 = _tangents(wo)
    du = (offset_dir(wo + STEP * t1) - offset_dir(wo - STEP * t1)) / (2 * STEP)
    dv = (offset_dir(wo + STEP * t2) - offset_dir(wo - STEP * t2)) / (2 * STEP)
    J_fd = np.linalg.norm(np.cross(du, dv), axis=-1)

    zz, t = hit(wo)
    to_z = zz - y
    J = np.array(
        reconnection_jacobian(
            mi.Normal3f(normal.T),
            mi.Vector3f(wo.T),
            mi.Float(t * t),
            mi.Vector3f(_unit(to_z).T),
            mi.Float(np.sum(to_z * to_z, -1)),
        )
    )
    assert len(J) > n_cases // 4
    np.testing.assert_allclose(J, J_fd, rtol=RTOL_RECONNECTION)
