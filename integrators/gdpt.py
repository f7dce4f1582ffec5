"""``gdpt``: gradient-domain path tracing with the hybrid shift (Kettunen et al. 2015)."""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from .common import (
    FeatureState,
    GradientIntegratorBase,
    PathSamples,
    camera_transform,
    safe_div,
    update_features,
)
from .shifts import half_vector_shift, reconnection_jacobian

#: Offset status. RECENTLY_CONNECTED: y_{i-1} was reconnected to x_i; CONNECTING: one vertex
#: later, the offset shares x_i but its pdf of the segment into x_i is its own; CONNECTED: from
#: here on its throughput and MIS ratio change exactly like the base's (two-phase fold).
NOT_CONNECTED, RECENTLY_CONNECTED, CONNECTING, CONNECTED = 0, 1, 2, 3


@dataclass
class BaseState:
    """Loop state of the base path."""

    ray_d: mi.Vector3f  # direction of the segment that arrived at `si`
    si: mi.SurfaceInteraction3f  # current vertex x_i
    prev: mi.Interaction3f  # previous vertex x_{i-1} (position and normal only)
    beta: mi.Spectrum  # β = f / p of the prefix
    eta: mi.Float  # relative IOR product (Russian roulette)
    pb_prev: mi.Float  # MIS pdf of the segment x_{i-1} -> x_i (1 for camera / delta)
    delta_prev: mi.Bool  # that segment could not have been light-sampled
    depth: mi.UInt32
    active: mi.Bool
    L: mi.Spectrum  # primal radiance
    bad_shift: mi.UInt32  # shifts failed because their throughput or MIS ratio was not finite
    bad_term: mi.UInt32  # gradient terms dropped because they were not finite


@dataclass
class OffsetState:
    """Loop state of one offset path y (shifted by one pixel).

    ``q = f(ȳ) J / p(x̄)`` and ``r = J p̃(ȳ) / p̃(x̄)`` are kept as ratios to the base path so
    that no long pdf products appear in float32 (p̃: MIS pdf, 1 at delta vertices).
    """

    si: mi.SurfaceInteraction3f  # own vertex y_i (while NOT_CONNECTED)
    prev: mi.Interaction3f  # own previous vertex y_{i-1}
    status: mi.UInt32  # NOT_CONNECTED / RECENTLY_CONNECTED / CONNECTING / CONNECTED
    alive: mi.Bool  # False once the shift failed: the base then takes full MIS weight
    escaped: mi.Bool  # left the scene while the base continues (dies after its emission)
    q: mi.Spectrum
    r: mi.Float
    pb_prev: mi.Float  # MIS pdf of the segment y_{i-1} -> y_i
    bsdf_only: mi.Bool  # that segment left a near-specular pair: no light technique (see NEE)
    s: mi.Float  # after a reconnection y_{i-1} -> x_i: r_{i-1} / p̃(x_{i-1} -> x_i)
    sJ: mi.Float  # ... and the same times the reconnection Jacobian
    G: mi.Spectrum  # half-gradient accumulator


class GDPTIntegrator(GradientIntegratorBase):
    r"""
    .. _integrator-gdpt:

    Gradient-domain path tracer (:monosp:`gdpt`)
    --------------------------------------------

    .. pluginparameters::

     * - max_depth
       - |int|
       - Longest path depth (-1: unbounded). (Default: 6)
     * - rr_depth
       - |int|
       - Depth at which Russian roulette starts. (Default: 5)
     * - gradients
       - |bool|
       - Trace offset paths and output ``dx``/``dy``; false gives plain path tracing with the
         same features (equal-time baselines). (Default: true)
     * - features
       - |bool|
       - Output albedo, view-space normal and depth. (Default: true)
     * - variance
       - |bool|
       - Output the variance of the per-pixel means. (Default: false)
     * - samples_per_pass
       - |int|
       - Samples traced per kernel launch. (Default: 2^20)
     * - freeze
       - |bool|
       - Replay the recorded kernels of a pass (``dr.freeze``) instead of tracing it again.
         (Default: true)
     * - shift_threshold
       - |float|
       - Microfacet roughness (alpha) at or below which a glossy vertex is near-specular: the
         offsets copy the base's half vector there instead of reconnecting. (Default: 0.001)

    Traces a base path and four offset paths (pixel shifts right, down, left, up) in lockstep.
    A vertex is near-specular when the base sampled a delta lobe there, its BSDF has only delta
    lobes, or it is glossy with roughness <= ``shift_threshold``; otherwise it is rough.
    Offsets follow the base through delta vertices by sampling the same lobe (reflection or
    transmission), copy the base's half vector through near-specular glossy vertices (reflection
    and refraction, with the half-vector Jacobians), replay the base's random numbers through
    rough vertices whose successor is near-specular, and reconnect to the base at the first pair
    of consecutive rough vertices (the reconnection Jacobian is the ratio of
    solid-angle-to-area factors). Next-event estimation on an offset reconnects to the base's
    light point (so sphere and point lights are exact). The two shift directions of every pixel
    pair are combined with the balance heuristic over base/offset BSDF and light sampling,
    computed in a ratio form; a light sample joins that MIS only where the BSDF shift of the
    same path exists in both directions, and segments leaving a near-specular pair are
    estimated by BSDF sampling alone (see the NEE section of ``sample_paths``). Failed shifts
    give the base full weight. Numerical guards are counted in ``guard_counts``.

    Cost: the loop runs in two phases. While some offset still has vertices of its own it runs
    the full shift (per-offset work for own vertices sits in ``dr.if_stmt`` blocks, which skip
    packets without such lanes); once every offset has reconnected or failed, the rest of the
    path is a plain path tracer whose radiance all offsets share with fixed weights.

    The output ``dx``/``dy`` are the sums of the two MIS halves, i.e. unbiased estimates of
    ``I(x+1) - I(x)``; the primal is the standard base-path estimate. Needs a box pixel filter.
    The short twin :ref:`gdpt_rr <integrator-gdpt_rr>` (random replay) serves as an oracle.

    .. tabs::
        .. code-tab:: python

            'type': 'gdpt', 'max_depth': 8
    """

    plugin_name = "gdpt"

    #: shift_threshold if the scene may have glossy lobes at or below it, else None (no
    #: per-vertex roughness look-ups); set by prepare().
    _active_threshold: float | None = None
    #: Whether some BSDF of the scene has a null lobe (opacity masks); set by prepare().
    _has_null: bool = False

    def prepare(self, scene: mi.Scene) -> None:
        near = _may_have_near_specular_glossy(scene, self.shift_threshold)
        self._active_threshold = self.shift_threshold if near else None
        self._has_null = any(
            mi.has_flag(shape.bsdf().flags(), mi.BSDFFlags.Null) for shape in scene.shapes()
        )

    def prepared_state(self) -> tuple:
        return (self._active_threshold, self._has_null)

    def sample_paths(self, scene, sensor, sampler, rays, weights, active) -> PathSamples:
        n = dr.width(rays[0].d)
        ctx = mi.BSDFContext()
        ctx_refl = mi.BSDFContext()
        ctx_refl.type_mask = int(mi.BSDFFlags.DeltaReflection)
        ctx_trans = mi.BSDFContext()
        ctx_trans.type_mask = int(mi.BSDFFlags.DeltaTransmission)
        to_camera = camera_transform(sensor)
        n_off = len(rays) - 1
        threshold = self._active_threshold
        has_null = self._has_null

        def near_glossy(si, bsdf, active):
            """Glossy vertex with roughness <= shift_threshold (half-vector copy, features pass)."""
            if threshold is None:
                return mi.Bool(False)
            return _near_specular_glossy(si, bsdf, threshold, active)

        base = BaseState(
            ray_d=mi.Vector3f(rays[0].d),
            si=_primary_hit(scene, rays[0], active),
            prev=dr.zeros(mi.Interaction3f, n),
            beta=mi.Spectrum(weights[0]),
            eta=mi.Float(1.0),
            pb_prev=mi.Float(1.0),
            delta_prev=mi.Bool(True),
            depth=mi.UInt32(0),
            active=mi.Bool(active),
            L=dr.zeros(mi.Spectrum, n),
            bad_shift=dr.zeros(mi.UInt32, n),
            bad_term=dr.zeros(mi.UInt32, n),
        )
        base_hit = base.si.is_valid()
        offsets = []
        for k in range(1, n_off + 1):
            si_k = _primary_hit(scene, rays[k], active)
            offsets.append(
                OffsetState(
                    si=si_k,
                    prev=dr.zeros(mi.Interaction3f, n),
                    status=mi.UInt32(NOT_CONNECTED),
                    alive=mi.Bool(active),
                    escaped=base_hit & ~si_k.is_valid(),
                    q=mi.Spectrum(weights[k]),
                    r=mi.Float(1.0),
                    pb_prev=mi.Float(1.0),
                    bsdf_only=mi.Bool(False),
                    s=mi.Float(0.0),
                    sJ=mi.Float(0.0),
                    G=dr.zeros(mi.Spectrum, n),
                )
            )
        feat = FeatureState.zeros(n) if self.features else None

        def body(sampler, base, offsets, feat, beta_scale=None):
            """One vertex of the base path and of ``offsets`` (``beta_scale``: the tail's
            throughput scale, see phase 2)."""
            si, active = base.si, base.active
            bsdf = si.bsdf()
            if feat is not None:
                near = near_glossy(si, bsdf, active & feat.open)
                update_features(feat, si, bsdf, base.ray_d, to_camera, active, near)

            # ----------------------- Emission at x_i ------------------------
            ds = mi.DirectionSample3f(scene, si, base.prev)
            pn_x = scene.pdf_emitter_direction(base.prev, ds, active & ~base.delta_prev)
            Le_x = ds.emitter.eval(si, active)
            cone = _is_cone_sampled(ds.emitter)
            ratio_x = pn_x / dr.select(base.pb_prev > 0, base.pb_prev, 1)  # p_light / p_bsdf
            base.L += base.beta * Le_x / (1 + ratio_x)
            c_main_num = base.beta * Le_x

            def add_term(o, term, active):
                """o.G += term where active; a non-finite term is dropped and counted."""
                ok = dr.isfinite(dr.sum(term))
                o.G += dr.select(active & ok, term, 0)
                base.bad_term += dr.select(active & ~ok, 1, 0)

            # The offset's current vertex: its own y_i (NOT_CONNECTED), or the base's x_i seen
            # from the offset's previous vertex (RECENTLY_CONNECTED: o.si holds x_i, only wi
            # differs; CONNECTED: unused). Merging both halves the virtual calls below.
            views, near_ys = [], []
            for o in offsets:
                recent = o.status == RECENTLY_CONNECTED
                view = dr.copy(o.si)
                turn = recent & si.is_valid()
                view.wi = dr.select(turn, si.to_local(dr.normalize(o.prev.p - si.p)), view.wi)
                views.append(view)
                # Own y_i glossy at or below shift_threshold (read once for NEE and the shift)
                own_next = (o.status == NOT_CONNECTED) & o.alive & active
                near_ys.append(
                    near_glossy(o.si, o.si.bsdf(), own_next)
                    if threshold is not None
                    else mi.Bool(False)
                )

            for o, view in zip(offsets, views, strict=True):
                own = o.status == NOT_CONNECTED
                recent = o.status == RECENTLY_CONNECTED
                act = active & (own | recent) & o.alive
                ds_y = mi.DirectionSample3f(scene, view, o.prev)
                pn_y = scene.pdf_emitter_direction(o.prev, ds_y, act & ~base.delta_prev)
                Le_y = dr.select(own | recent, ds_y.emitter.eval(view, act), Le_x)
                # The offset's light technique relative to the base's BSDF pdf, r p_light(y) /
                # p_bsdf(y), without 0 * inf at grazing y: after a reconnection J p_light(y) =
                # p_light(x) for area-sampled emitters (see NEE). Once connected, the segment
                # pdf is the offset's own (pb_prev) for one more vertex (CONNECTING).
                light_y = dr.select(
                    own,
                    o.r * pn_y / dr.select(o.pb_prev > 0, o.pb_prev, 1),
                    dr.select(
                        recent,
                        dr.select(cone, o.sJ * pn_y, o.s * pn_x),
                        o.r * pn_x / dr.select(o.pb_prev > 0, o.pb_prev, 1),
                    ),
                )
                # A segment sampled at a near-specular pair is estimated by BSDF sampling alone.
                den = 1 + dr.select(o.bsdf_only, 0, ratio_x + dr.select(o.alive, light_y, 0))
                den += dr.select(o.alive, o.r, 0)
                c_shift = dr.select(o.alive, o.q * Le_y, 0)
                add_term(o, (c_shift - c_main_num) / den, active)
                o.alive &= ~o.escaped

            # --------------------- Next-event estimation --------------------
            active_next = active & (base.depth + 1 < self.max_depth) & si.is_valid()
            active_em = active_next & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
            # Visibility is tested separately: an occluded base light sample still has offsets.
            ds, em_weight = scene.sample_emitter_direction(si, sampler.next_2d(), False, active_em)
            active_em &= ds.pdf != 0
            visible_x = ~scene.ray_test(si.spawn_ray_to(ds.p), active_em)
            em_weight = dr.select(visible_x, em_weight, 0)
            wo_em = si.to_local(ds.d)
            # One virtual call evaluates the light sample and samples the next direction.
            u1, u2 = sampler.next_1d(), sampler.next_2d()
            f_x, pb_x, bs, bsdf_weight = bsdf.eval_pdf_sample(ctx, si, wo_em, u1, u2, active_next)
            f_x = dr.select(active_em, f_x, 0)
            pb_x = dr.select(active_em & ~ds.delta, pb_x, 0)
            pn_x = ds.pdf
            em_val = em_weight * pn_x  # radiance (intensity / d^2 for point lights) at x_i
            w_light = safe_div(pn_x, pn_x + pb_x)
            base.L += dr.select(active_em, base.beta * f_x * em_weight * w_light, 0)
            nee_main = base.beta * f_x * em_val
            is_infinite = mi.has_flag(ds.emitter.flags(), mi.EmitterFlags.Infinite)
            cone = _is_cone_sampled(ds.emitter)
            fixed_point = is_infinite | ds.delta  # light "vertex" shared exactly: J = 1
            near_x = near_glossy(si, bsdf, active_next)

            # Light samples join the MIS of a pixel pair only where the BSDF shift of the same
            # path exists in both directions, so that the four techniques (base / offset x
            # BSDF / light) see the same set of shifted paths: the light point visible from x_i
            # and y_i, nonzero BSDF pdfs at both (delta lights have no BSDF technique), and a
            # reconnection as the BSDF shift's mapping. At a near-specular pair (x_i or y_i at
            # or below shift_threshold) the BSDF shift copies the half vector instead, so there
            # the gradient takes the segment from BSDF sampling alone (bsdf_only) and drops the
            # light technique of both paths; the primal keeps its own MIS.
            for o, view, near_y in zip(offsets, views, near_ys, strict=True):
                own = o.status == NOT_CONNECTED
                recent = o.status == RECENTLY_CONNECTED
                act = active_em & o.alive
                # Recently connected: the base's BSDF at x_i towards the same light sample,
                # arriving from y_{i-1}. Connected: the base's own values.
                f_r, pb_r = bsdf.eval_pdf(ctx, view, wo_em, act & recent)
                pb_r = dr.select(ds.delta, 0, pb_r)

                def nee_own(o=o, act=act):
                    """Own vertex y_i: reconnect it to the base's light point."""
                    y = o.si
                    bsdf_y = y.bsdf()
                    to_light = ds.p - y.p
                    dist_y = dr.norm(to_light)
                    dir_y = dr.select(is_infinite, ds.d, to_light / dist_y)
                    dist_y = dr.select(is_infinite, ds.dist, dist_y)
                    ds_y = mi.DirectionSample3f(
                        ds.p, ds.n, ds.uv, ds.time, ds.pdf, ds.delta, dir_y, dist_y, ds.emitter
                    )
                    act_own = act & mi.has_flag(bsdf_y.flags(), mi.BSDFFlags.Smooth)
                    ray_y = dr.select(is_infinite, y.spawn_ray(dir_y), y.spawn_ray_to(ds.p))
                    visible = ~scene.ray_test(ray_y, act_own)
                    em = dr.select(visible, scene.eval_emitter_direction(y, ds_y, act_own), 0)
                    J = dr.select(
                        fixed_point,
                        1.0,
                        reconnection_jacobian(
                            ds.n, ds.d, dr.square(ds.dist), dir_y, dr.square(dist_y)
                        ),
                    )
                    # J p_light(y). Area-sampled emitters and fixed points: exactly p_light(x),
                    # also when the light turns its back to y (Mitsuba samples such points with
                    # nonzero pdf, although pdf_emitter_direction() reports 0), and free of
                    # 0 * inf at grazing y. Spheres are sampled by cone, which never picks their
                    # far side.
                    front = dr.dot(ds.n, dir_y) < 0
                    pn_cone = scene.pdf_emitter_direction(y, ds_y, act_own & cone & front)
                    Jpn = dr.select(cone, J * pn_cone, pn_x)
                    f, pb = bsdf_y.eval_pdf(ctx, y, y.to_local(dir_y), act_own)
                    pair = act_own & (ds.delta | (visible & (pb > 0)))
                    pb = dr.select(ds.delta, 0, pb)
                    return f, em, J, dr.select(act_own, Jpn, 0) + J * pb, pair

                def nee_follow(recent=recent, f_r=f_r, pb_r=pb_r):
                    f = dr.select(recent, f_r, f_x)
                    pair = ~recent | ds.delta | (pb_r > 0)
                    return f, em_val, mi.Float(1.0), pn_x + dr.select(recent, pb_r, pb_x), pair

                f_y, e_y, J, Jp_y, pair = dr.if_stmt((), act & own, nee_own, nee_follow)
                # Connected offsets always pair (the two-phase fold relies on it).
                pair &= o.alive & ((o.status >= CONNECTING) | ds.delta | (visible_x & (pb_x > 0)))
                den = pn_x + pb_x + dr.select(pair, o.r * Jp_y, 0)
                c_shift = dr.select(pair, o.q * f_y * e_y * J, 0)
                bsdf_only = own & o.alive & (near_x | near_y) & ~ds.delta
                add_term(o, (c_shift - nee_main) / den, active_em & ~bsdf_only)

            # ------------------------ BSDF sampling -------------------------
            delta_x = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
            ray_next = si.spawn_ray(si.to_world(bs.wo))
            si_next = scene.ray_intersect(ray_next, active_next)
            hit_next = si_next.is_valid()
            bsdf_next = si_next.bsdf()
            rough_next = ~hit_next | ~(
                mi.has_flag(bsdf_next.flags(), mi.BSDFFlags.Delta)
                | near_glossy(si_next, bsdf_next, hit_next & active_next)
            )
            reflect = mi.has_flag(bs.sampled_type, mi.BSDFFlags.DeltaReflection)
            null_x = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Null) if has_null else mi.Bool(False)
            # A non-delta sample at a near-specular glossy x_i: offsets copy its half vector.
            half_x = ~delta_x & near_x

            inv_p = safe_div(1.0, bs.pdf)
            pb_next = dr.select(delta_x, 1.0, bs.pdf)  # MIS pdf of the segment x_i -> x_{i+1}
            for o, view, near_y in zip(offsets, views, near_ys, strict=True):
                # No base sample, no shift (the reverse shift finds a zero pdf at x_i)
                act = active_next & o.alive & (bs.pdf > 0)
                own = o.status == NOT_CONNECTED
                recent = o.status == RECENTLY_CONNECTED
                # Recently connected: the base's BSDF at x_i towards the base's sample,
                # arriving from y_{i-1}.
                f_r, p_r = bsdf.eval_pdf(ctx, view, bs.wo, act & recent)

                def shift_own(o=o, act=act, near_y=near_y):
                    """Own vertex y_i: reconnect, follow a delta lobe, copy the half vector, or
                    replay the numbers."""
                    y = o.si
                    bsdf_y = y.bsdf()
                    y_smooth = mi.has_flag(bsdf_y.flags(), mi.BSDFFlags.Smooth)
                    half_y = near_y & ~delta_x
                    reconnect = ~delta_x & ~half_x & rough_next & y_smooth & ~half_y

                    # Reconnection y_i -> x_{i+1} (or environment shift: copy the direction)
                    act_rc = act & reconnect
                    to_next = si_next.p - y.p
                    d_y2 = dr.squared_norm(to_next)
                    dir_rc = dr.select(hit_next, to_next * dr.rsqrt(d_y2), ray_next.d)
                    ray_rc = dr.select(hit_next, y.spawn_ray_to(si_next.p), y.spawn_ray(dir_rc))
                    J_rc = dr.select(
                        hit_next,
                        reconnection_jacobian(
                            si_next.n, ray_next.d, dr.square(si_next.t), dir_rc, d_y2
                        ),
                        1.0,
                    )
                    f_rc, p_rc = bsdf_y.eval_pdf(ctx, y, y.to_local(dir_rc), act_rc)

                    # Delta lobe: sample the offset's lobe of the same kind; f_d is its delta
                    # coefficient (weight x pdf of the restricted sample).
                    act_d = act & delta_x & ~null_x
                    bs_r, w_r = bsdf_y.sample(ctx_refl, y, u1, u2, act_d & reflect)
                    bs_t, w_t = bsdf_y.sample(ctx_trans, y, u1, u2, act_d & ~reflect)
                    bs_d = dr.select(reflect, bs_r, bs_t)
                    f_d = dr.select(reflect, w_r, w_t) * bs_d.pdf
                    # The sample must be of the requested kind: a mask BSDF answers a restricted
                    # context with its null lobe.
                    kind = mi.has_flag(bs_d.sampled_type, mi.BSDFFlags.DeltaReflection)
                    kind = dr.select(
                        reflect,
                        kind,
                        mi.has_flag(bs_d.sampled_type, mi.BSDFFlags.DeltaTransmission),
                    )
                    ok_d = (bs_d.pdf > 0) & (dr.max(f_d) > 0) & kind
                    if has_null:
                        # Null lobe (opacity masks): straight on, f = the null transmission
                        wo_d = dr.select(null_x, -y.wi, bs_d.wo)
                        f_null = bsdf_y.eval_null_transmission(y, act & null_x)
                        f_d = dr.select(null_x, f_null, f_d)
                        ok_d = dr.select(null_x, dr.max(f_null) > 0, ok_d)
                    else:
                        wo_d = bs_d.wo

                    # Near-specular glossy x_i and y_i: copy the base's half vector
                    act_h = act & half_x
                    wo_h, J_h, ok_h = half_vector_shift(si.wi, bs.wo, bs.eta, y.wi)
                    ok_h &= half_y & ((bs.eta == 1) | (bsdf_y == bsdf))  # refraction: same IOR
                    f_h, p_h = bsdf_y.eval_pdf(ctx, y, wo_h, act_h & ok_h)
                    ok_h &= p_h > 0

                    # Rough x_i before a near-specular x_{i+1}: replay the base's random numbers
                    act_s = act & ~delta_x & ~half_x & ~reconnect
                    bs_s, w_s = bsdf_y.sample(ctx, y, u1, u2, act_s)
                    # A near-specular y_i under a rough x_i fails: from y the shift would copy
                    # the half vector, so replay would not be the inverse of the reverse shift.
                    ok_s = y_smooth & (bs_s.pdf > 0) & ~half_y
                    ok_s &= ~mi.has_flag(bs_s.sampled_type, mi.BSDFFlags.Delta)

                    trace = act & ~reconnect
                    # Shadow test (any hit) for a reconnection; closest hit for a new vertex
                    visible = ~scene.ray_test(ray_rc, act_rc)
                    wo_y = dr.select(delta_x, wo_d, dr.select(half_x, wo_h, bs_s.wo))
                    si_y = scene.ray_intersect(y.spawn_ray(y.to_world(wo_y)), trace)
                    hit_y = si_y.is_valid()
                    bsdf_ny = si_y.bsdf()
                    rough_y = ~hit_y | ~(
                        mi.has_flag(bsdf_ny.flags(), mi.BSDFFlags.Delta)
                        | near_glossy(si_y, bsdf_ny, hit_y & act_s)
                    )
                    # Non-invertible: the reverse shift from y would reconnect at this vertex
                    ok_s &= ~rough_y

                    # Reconnection and half-vector copy: f J / p_x and p_y J / p_x. Delta lobes
                    # (J = 1) and replay (J = p_x / p_y in solid angle) simplify to sample weights.
                    mapped = reconnect | half_x
                    f_m = dr.select(half_x, f_h, f_rc)
                    J_m = dr.select(half_x, J_h, J_rc)
                    p_m = dr.select(half_x, p_h, p_rc)
                    q = dr.select(
                        mapped,
                        o.q * f_m * (J_m * inv_p),
                        dr.select(delta_x, o.q * f_d * inv_p, o.q * w_s),
                    )
                    r = dr.select(mapped, o.r * p_m * J_m * inv_p, o.r)
                    # A mapping whose Jacobian is 0 or not finite (grazing, coincident vertices)
                    # fails (safe_div returns 0 there).
                    ok = dr.select(reconnect, visible & (p_rc > 0) & (J_rc > 0), ok_s)
                    ok = dr.select(half_x, ok_h & (J_h > 0), dr.select(delta_x, ok_d, ok))
                    pb = dr.select(mapped, p_m, dr.select(delta_x, 1.0, bs_s.pdf))
                    s_rc = dr.select(reconnect, o.r * inv_p, 0)
                    status = dr.select(reconnect, mi.UInt32(RECENTLY_CONNECTED), NOT_CONNECTED)
                    return (
                        q,
                        r,
                        ok,
                        pb,
                        s_rc,
                        s_rc * J_rc,
                        trace & ~hit_y & hit_next,
                        trace,
                        si_y,
                        status,
                        act & (near_x | near_y),
                    )

                def follow(o=o, recent=recent, f_r=f_r, p_r=p_r):
                    """Recently connected or connected: the offset shares the base's next vertex."""
                    q = dr.select(recent, o.q * f_r * inv_p, o.q * bsdf_weight)
                    r = dr.select(recent, o.r * p_r * inv_p, o.r)
                    pb = dr.select(recent, p_r, pb_next)
                    zero = dr.zeros(mi.Float, n)
                    # The offset's own segment pdf matters for one more vertex, unless it equals
                    # the base's (diffuse x_i: the pdf does not depend on wi)
                    status = dr.select(
                        recent & (p_r != pb_next), mi.UInt32(CONNECTING), mi.UInt32(CONNECTED)
                    )
                    return (
                        q,
                        r,
                        ~recent | (p_r > 0),
                        pb,
                        zero,
                        zero,
                        mi.Bool(False),
                        mi.Bool(False),
                        dr.zeros(mi.SurfaceInteraction3f, n),
                        status,
                        mi.Bool(False),
                    )

                (q, r, ok, o.pb_prev, o.s, o.sJ, o.escaped, trace, si_y, o.status, o.bsdf_only) = (
                    dr.if_stmt((), act & own, shift_own, follow)
                )
                # A throughput or MIS ratio that is not finite fails the shift (counted). An
                # overflowing r (+inf: the offset's pdf dwarfs the base's) is capped, so that the
                # base's weight goes to 0, its correct limit.
                numeric = dr.isfinite(dr.sum(q)) & ~dr.isnan(r)
                base.bad_shift += dr.select(act & ok & ~numeric, 1, 0)
                o.q = dr.select(numeric, q, 0)
                o.r = dr.select(numeric, dr.minimum(r, 1e30), 0)
                o.alive = act & ok & numeric
                # Selected here, not in the branches: returning the outer si_next from one branch
                # of dr.if_stmt corrupted the base path's copy of it (Dr.Jit 1.5).
                o.si = dr.select(trace, si_y, si_next)
                o.prev = _vertex(view)  # y_i (own) or x_i

            # ----------------------- Russian roulette -----------------------
            base.beta *= bsdf_weight
            base.eta *= bs.eta
            # Roulette and termination follow the largest throughput of the base and its live
            # offsets: a base of zero throughput (a black surface) still carries offsets whose
            # share of the pair's MIS is counted on this side only.
            carried = base.beta if beta_scale is None else base.beta * beta_scale
            for o in offsets:
                carried = dr.maximum(carried, dr.select(o.alive, o.q, 0))
            beta_max = dr.max(carried)
            rr_active = base.depth >= self.rr_depth
            rr_prob = dr.minimum(beta_max * dr.square(base.eta), 0.95)
            rr_scale = dr.select(rr_active, safe_div(1.0, rr_prob), 1.0)
            base.beta *= rr_scale
            for o in offsets:
                o.q *= rr_scale
            survive = sampler.next_1d() < rr_prob

            # ----------------------- Advance the base -----------------------
            base.prev = _vertex(si)
            base.si = si_next
            base.ray_d = ray_next.d
            base.pb_prev = pb_next
            base.delta_prev = delta_x
            base.depth += 1
            base.active = active_next & (beta_max != 0) & (~rr_active | survive)
            return sampler, base, offsets, feat

        # The sampler is loop state: its RNG must advance from one iteration to the next.
        if offsets:
            # Phase 1: the full hybrid shift while some offset still has vertices of its own.
            def pending(sampler, base, offsets, feat):
                own = mi.Bool(False)
                for o in offsets:
                    own |= o.alive & (o.status != CONNECTED)
                    if threshold is not None:
                        # The next emission of a segment from a near-specular pair has its own
                        # MIS (BSDF sampling alone), also when that shift failed.
                        own |= o.bsdf_only
                return base.active & own

            sampler, base, offsets, feat = dr.while_loop(
                (sampler, base, offsets, feat),
                pending,
                body,
                labels=("sampler", "base", "offsets", "features"),
                label="gdpt_shift",
            )

        # Phase 2: every offset is connected (it shares all further vertices with the base) or
        # failed. A connected offset's throughput q and MIS ratio r then change exactly like the
        # base's, so each further contribution c of the base adds (q - beta) c / ((1 + r) beta)
        # to the half-gradient (a failed one: q = r = 0). Trace the tail once as a plain path
        # with throughput relative to here (no division by beta, whose channels may be 0).
        head_beta, head_L = base.beta, base.L
        base.beta = dr.full(mi.Spectrum, 1.0, n)
        base.L = dr.zeros(mi.Spectrum, n)
        carried = head_beta  # the tail's roulette scale (see the roulette in body)
        for o in offsets:
            carried = dr.maximum(carried, dr.select(o.alive, o.q, 0))

        def tail_body(sampler, base, feat):
            sampler, base, _, feat = body(sampler, base, [], feat, carried)
            return sampler, base, feat

        sampler, base, feat = dr.while_loop(
            (sampler, base, feat),
            lambda sampler, base, feat: base.active,
            tail_body,
            labels=("sampler", "base", "features"),
            label="gdpt_tail",
        )
        tail = base.L
        gradients = [
            o.G + (dr.select(o.alive, o.q, 0) - head_beta) * tail / (1 + dr.select(o.alive, o.r, 0))
            for o in offsets
        ]
        return PathSamples(
            primal=head_L + head_beta * tail,
            gradients=gradients,
            albedo=feat.albedo if feat is not None else None,
            normal=feat.normal if feat is not None else None,
            depth=feat.depth if feat is not None else None,
            guards={"shift_nonfinite": base.bad_shift, "term_nonfinite": base.bad_term},
        )


def _roughness(bsdf: mi.BSDFPtr, si: mi.SurfaceInteraction3f, active: mi.Bool) -> mi.Float:
    """Microfacet alpha of a glossy BSDF (the mean of alpha_u and alpha_v when anisotropic;
    roughness^2 for ``principled``); 0 where the BSDF exposes none of these attributes."""
    alpha = bsdf.eval_attribute_1("alpha", si, active)
    alpha_uv = 0.5 * (
        bsdf.eval_attribute_1("alpha_u", si, active) + bsdf.eval_attribute_1("alpha_v", si, active)
    )
    roughness = bsdf.eval_attribute_1("roughness", si, active)
    return dr.maximum(dr.maximum(alpha, alpha_uv), dr.square(roughness))


def _near_specular_glossy(
    si: mi.SurfaceInteraction3f, bsdf: mi.BSDFPtr, threshold: float, active: mi.Bool
) -> mi.Bool:
    """Glossy BSDF whose roughness is in (0, threshold]. A glossy BSDF exposing no roughness
    attribute reads 0 and stays reconnectable (the safe choice: reconnection is valid at any
    non-delta vertex, only noisier on narrow lobes)."""
    glossy = active & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Glossy)
    alpha = _roughness(bsdf, si, glossy)
    return glossy & (alpha > 0) & (alpha <= threshold)


def _may_have_near_specular_glossy(scene: mi.Scene, threshold: float) -> bool:
    """Whether some glossy BSDF of ``scene`` may have roughness in (0, threshold]: uniform
    roughness parameters are compared, textured ones count as maybe (read on the host, without
    launching kernels)."""
    for bsdf in {shape.bsdf() for shape in scene.shapes()}:
        if not mi.has_flag(bsdf.flags(), mi.BSDFFlags.Glossy):
            continue
        params = mi.traverse(bsdf)
        for key in params.keys():
            name, _, kind = key.rpartition(".")
            name = name.rpartition(".")[2] if kind in ("value", "data") else kind
            if name not in ("alpha", "alpha_u", "alpha_v", "roughness"):
                continue
            if kind == "data":
                return True
            value = float(dr.ravel(params[key])[0]) if dr.width(params[key]) else 0.0
            alpha = value * value if name == "roughness" else value
            if 0 < alpha <= threshold:
                return True
    return False


def _primary_hit(scene: mi.Scene, ray: mi.Ray3f, active: mi.Bool) -> mi.SurfaceInteraction3f:
    """Camera rays are coherent: Embree's coherent traversal is faster for them."""
    return scene.ray_intersect(ray, mi.RayFlags.All, True, active)


def _vertex(si: mi.SurfaceInteraction3f) -> mi.Interaction3f:
    """The part of a vertex later iterations need (keeps the loop state small)."""
    return mi.Interaction3f(si.t, si.time, si.wavelengths, si.p, si.n)


def _is_cone_sampled(emitter: mi.EmitterPtr) -> mi.Bool:
    """Emitters on spheres: Mitsuba samples them by solid angle (cone), not by area."""
    return emitter.get_shape().shape_type() == int(mi.ShapeType.Sphere)


# Mitsuba's documented registration pattern: a constructor lambda
mi.register_integrator("gdpt", lambda props: GDPTIntegrator(props))  # noqa: PLW0108
