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

#: BSDF contexts: all lobes; one kind of delta lobe (an offset follows the base's delta lobe).
_CTX = mi.BSDFContext()
_CTX_REFLECT = mi.BSDFContext(mi.TransportMode.Radiance, mi.BSDFFlags.DeltaReflection)
_CTX_TRANSMIT = mi.BSDFContext(mi.TransportMode.Radiance, mi.BSDFFlags.DeltaTransmission)


# ------------------------------------------------------------------------------- loop state
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
    bsdf_only: mi.Bool  # that segment left a near-specular pair: no light technique (_shift_light)
    s: mi.Float  # after a reconnection y_{i-1} -> x_i: r_{i-1} / p̃(x_{i-1} -> x_i)
    sJ: mi.Float  # ... and the same times the reconnection Jacobian
    G: mi.Spectrum  # half-gradient accumulator
    B: mi.Spectrum | None  # primal="mis": the base's contributions with this pair's MIS weights


# ------------------------------------------------------- per-vertex values (not loop state)
@dataclass
class Emission:
    """Emission at the base's vertex x_i, reached by BSDF sampling from x_{i-1}."""

    Le: mi.Spectrum  # emitted radiance towards x_{i-1}
    pn: mi.Float  # light-sampling pdf of x_i from x_{i-1} (solid angle)
    cone: mi.Bool  # the emitter is sampled by solid angle (spheres), not by area
    ratio: mi.Float  # p_light / p_bsdf of the segment x_{i-1} -> x_i
    c_main: mi.Spectrum  # β Le: the base's contribution before MIS


@dataclass
class LightSample:
    """The base's light sample at x_i (next-event estimation) and its evaluation there."""

    ds: mi.DirectionSample3f
    wo: mi.Vector3f  # ds.d in x_i's local frame
    active: mi.Bool  # a sample with nonzero pdf from a smooth x_i (visible or not)
    visible: mi.Bool
    weight: mi.Spectrum  # emitted radiance / pdf, 0 where occluded
    em: mi.Spectrum  # emitted radiance at x_i (intensity / d^2 for point lights)
    f: mi.Spectrum  # BSDF value times cosine at x_i (0 where not active)
    pb: mi.Float  # BSDF pdf of ``wo`` (0 for delta lights)
    mis: mi.Float  # balance weight of light sampling, p_light / (p_light + p_bsdf)
    infinite: mi.Bool  # environment light: a direction, no point
    cone: mi.Bool  # sampled by solid angle (spheres), not by area
    fixed_point: mi.Bool  # the light "vertex" is shared exactly by the offsets: J = 1


@dataclass
class Segment:
    """The base's BSDF sample at x_i and the next vertex x_{i+1} it reaches."""

    bs: mi.BSDFSample3f
    weight: mi.Spectrum  # f cos / pdf
    u1: mi.Float  # the random numbers of ``bs`` (replayed by offsets)
    u2: mi.Point2f
    ray: mi.Ray3f  # x_i -> x_{i+1}
    si: mi.SurfaceInteraction3f  # x_{i+1}
    hit: mi.Bool  # x_{i+1} is a surface (else the ray escaped)
    rough: mi.Bool  # x_{i+1} is rough, or the environment (a valid reconnection target)
    delta: mi.Bool  # ``bs`` sampled a delta lobe
    reflect: mi.Bool  # ... a delta reflection
    null: mi.Bool  # ... a null lobe (opacity masks)
    near: mi.Bool  # x_i is glossy at or below shift_threshold
    half: mi.Bool  # a non-delta sample at a near-specular glossy x_i (half-vector copy)
    inv_p: mi.Float  # 1 / bs.pdf (0 where the pdf is 0)
    pb: mi.Float  # MIS pdf of the segment x_i -> x_{i+1} (1 for delta lobes)


# ------------------------------------------------ per-offset results (dr.if_stmt state)
@dataclass
class LightShift:
    """One offset's version of the base's light sample (both branches of its ``dr.if_stmt``)."""

    f: mi.Spectrum  # BSDF value times cosine at the offset's vertex
    em: mi.Spectrum  # emitted radiance reaching it (0 where occluded)
    J: mi.Float  # Jacobian of the reconnection to the light point
    Jp: mi.Float  # J (p_light + p_bsdf) of the offset, relative to the base's light pdf
    pair: mi.Bool  # the light technique joins the pixel pair's MIS


@dataclass
class ShiftStep:
    """One offset's step along the base's BSDF sample (both branches of its ``dr.if_stmt``)."""

    q: mi.Spectrum  # new throughput ratio f(ȳ) J / p(x̄)
    r: mi.Float  # new MIS ratio J p̃(ȳ) / p̃(x̄)
    ok: mi.Bool  # the shift exists
    pb: mi.Float  # MIS pdf of the offset's new segment
    s: mi.Float  # OffsetState.s after a reconnection (else 0)
    sJ: mi.Float  # OffsetState.sJ after a reconnection (else 0)
    escaped: mi.Bool  # the offset's own ray left the scene while the base's hit
    trace: mi.Bool  # the offset traced a vertex of its own: ``si``
    si: mi.SurfaceInteraction3f
    status: mi.UInt32
    bsdf_only: mi.Bool  # the new segment leaves a near-specular pair


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
     * - primal
       - |string|
       - ``base``: the primal is the base-path estimate; ``mis``: every base and offset path
         adds to the pixel it lands in, weighted by its pixel pair's MIS weight (the weights of
         the gradients), the mean over the pixel's four pairs. (Default: ``base``)

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
    estimated by BSDF sampling alone (see :meth:`_shift_light`). Failed shifts
    give the base full weight. Numerical guards are counted in ``guard_counts``.

    Cost: the loop runs in two phases. While some offset still has vertices of its own it runs
    the full shift (per-offset work for own vertices sits in ``dr.if_stmt`` blocks, which skip
    packets without such lanes); once every offset has reconnected or failed, the rest of the
    path is a plain path tracer whose radiance all offsets share with fixed weights.

    The output ``dx``/``dy`` are the sums of the two MIS halves, i.e. unbiased estimates of
    ``I(x+1) - I(x)``; the primal is the standard base-path estimate (``primal="base"``) or the
    MIS combination of the base path and the four neighbours' offset paths that land in the
    pixel (``primal="mis"``, :mod:`.common`). Needs a box pixel filter.
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

    # ------------------------------------------------------------------ path loop
    def sample_paths(self, scene, sensor, sampler, rays, weights, active) -> PathSamples:
        n = dr.width(rays[0].d)
        to_camera = camera_transform(sensor)

        # -------------------- Configure loop state --------------------
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
        mis = self.primal == "mis"
        offsets = [
            _initial_offset(_primary_hit(scene, ray, active), weight, base_hit, active, n, mis)
            for ray, weight in zip(rays[1:], weights[1:], strict=True)
        ]
        feat = FeatureState.zeros(n) if self.features else None

        # ------------- Phase 1: the hybrid shift, vertex by vertex -------------
        # The sampler is loop state: its RNG must advance from one iteration to the next.
        if offsets:
            sampler, base, offsets, feat = dr.while_loop(
                (sampler, base, offsets, feat),
                self._pending,
                lambda sampler, base, offsets, feat: self._step(
                    scene, to_camera, sampler, base, offsets, feat
                ),
                labels=("sampler", "base", "offsets", "features"),
                label="gdpt_shift",
            )

        # ---------------- Phase 2: the tail shared by all offsets ----------------
        # Every offset is connected (it shares all further vertices with the base) or failed.
        # A connected offset's throughput q and MIS ratio r then change exactly like the
        # base's, so each further contribution c of the base adds (q - beta) c / ((1 + r) beta)
        # to the half-gradient (a failed one: q = r = 0). Trace the tail once as a plain path
        # with throughput relative to here (no division by beta, whose channels may be 0).
        head_beta, head_L = base.beta, base.L
        base.beta = dr.full(mi.Spectrum, 1.0, n)
        base.L = dr.zeros(mi.Spectrum, n)
        carried = head_beta  # the tail's roulette scale (see the roulette in _step)
        for o in offsets:
            carried = dr.maximum(carried, dr.select(o.alive, o.q, 0))

        def tail_step(sampler, base, feat):
            sampler, base, _, feat = self._step(scene, to_camera, sampler, base, [], feat, carried)
            return sampler, base, feat

        sampler, base, feat = dr.while_loop(
            (sampler, base, feat),
            lambda sampler, base, feat: base.active,
            tail_step,
            labels=("sampler", "base", "features"),
            label="gdpt_tail",
        )

        # --------------------------- Outputs ---------------------------
        tail = base.L
        gradients = [
            o.G + (dr.select(o.alive, o.q, 0) - head_beta) * tail / (1 + dr.select(o.alive, o.r, 0))
            for o in offsets
        ]
        # The base's share of the tail in each pair: the same fold (a non-finite one is dropped
        # in pass_sums, counted)
        base_shares = [
            o.B + head_beta * tail / (1 + dr.select(o.alive, o.r, 0)) for o in offsets if mis
        ]
        return PathSamples(
            primal=head_L + head_beta * tail,  # base-path radiance
            gradients=gradients,  # half-gradients towards the four offsets
            base_shares=base_shares,
            albedo=feat.albedo if feat is not None else None,
            normal=feat.normal if feat is not None else None,
            depth=feat.depth if feat is not None else None,
            guards={"shift_nonfinite": base.bad_shift, "term_nonfinite": base.bad_term},
        )

    def _pending(self, sampler, base: BaseState, offsets: list[OffsetState], feat) -> mi.Bool:
        """Condition of phase 1: the base is active and some offset still has vertices of its
        own (or, with near-specular glossy lobes, a pending segment of BSDF sampling alone)."""
        own = mi.Bool(False)
        for o in offsets:
            own |= o.alive & (o.status != CONNECTED)
            if self._active_threshold is not None:
                # The next emission of a segment from a near-specular pair has its own MIS
                # (BSDF sampling alone), also when that shift failed.
                own |= o.bsdf_only
        return base.active & own

    def _step(self, scene, to_camera, sampler, base, offsets, feat, beta_scale=None):
        """One vertex x_i of the base path and the offsets' vertices that go with it.

        ``sampler, base, offsets, feat`` are the loop state (returned updated); ``beta_scale``
        is the tail's throughput scale in phase 2 of :meth:`sample_paths` (None in phase 1).
        """
        si, active = base.si, base.active
        bsdf = si.bsdf()
        n = dr.width(base.L)
        if feat is not None:
            near = self._near_glossy(si, bsdf, active & feat.open)
            update_features(feat, si, bsdf, base.ray_d, to_camera, active, near)

        # ---------------------- Emission at x_i ----------------------
        emission = self._emission(scene, base)
        base.L += base.beta * emission.Le / (1 + emission.ratio)
        # The offsets' current vertices (own y_i, or x_i seen from y_{i-1}) and whether an own
        # y_i is near-specular glossy (read once for the NEE and the BSDF shift)
        views = [_offset_view(o, si) for o in offsets]
        near_ys = [self._own_near_glossy(o, active) for o in offsets]
        for o, view in zip(offsets, views, strict=True):
            self._shift_emission(scene, base, o, view, emission)

        # -------------------- Next-event estimation --------------------
        active_next = active & (base.depth + 1 < self.max_depth) & si.is_valid()
        light, bs, bsdf_weight, u1, u2 = self._sample_light(scene, sampler, si, bsdf, active_next)
        base.L += dr.select(light.active, base.beta * light.f * light.weight * light.mis, 0)
        c_main = base.beta * light.f * light.em
        near_x = self._near_glossy(si, bsdf, active_next)
        for o, view, near_y in zip(offsets, views, near_ys, strict=True):
            self._shift_light(scene, base, o, view, near_y, bsdf, light, near_x, c_main)

        # ----------------------- BSDF sampling -----------------------
        seg = self._trace_segment(scene, si, bs, bsdf_weight, u1, u2, near_x, active_next)
        for o, view, near_y in zip(offsets, views, near_ys, strict=True):
            self._shift_segment(scene, base, o, view, near_y, si, bsdf, seg, active_next, n)

        # ---------------------- Russian roulette ----------------------
        base.beta *= seg.weight
        base.eta *= seg.bs.eta
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

        # ---------------------- Advance the base ----------------------
        base.prev = _vertex(si)
        base.si = seg.si
        base.ray_d = seg.ray.d
        base.pb_prev = seg.pb
        base.delta_prev = seg.delta
        base.depth += 1
        base.active = active_next & (beta_max != 0) & (~rr_active | survive)
        return sampler, base, offsets, feat

    # ------------------------------------------------------------------ emission
    def _emission(self, scene: mi.Scene, base: BaseState) -> Emission:
        """Emission at the base's vertex x_i with the MIS ratio of its segment."""
        ds = mi.DirectionSample3f(scene, base.si, base.prev)
        pn = scene.pdf_emitter_direction(base.prev, ds, base.active & ~base.delta_prev)
        Le = ds.emitter.eval(base.si, base.active)
        return Emission(
            Le=Le,
            pn=pn,
            cone=_is_cone_sampled(ds.emitter),
            ratio=pn / dr.select(base.pb_prev > 0, base.pb_prev, 1),
            c_main=base.beta * Le,
        )

    def _shift_emission(
        self, scene: mi.Scene, base: BaseState, o: OffsetState, view, emission: Emission
    ) -> None:
        """The offset's emission at its current vertex ``view``: adds the half-gradient term of
        the pair (base and offset, BSDF and light technique) to ``o.G``."""
        own = o.status == NOT_CONNECTED
        recent = o.status == RECENTLY_CONNECTED
        act = base.active & (own | recent) & o.alive
        ds_y = mi.DirectionSample3f(scene, view, o.prev)
        pn_y = scene.pdf_emitter_direction(o.prev, ds_y, act & ~base.delta_prev)
        Le_y = dr.select(own | recent, ds_y.emitter.eval(view, act), emission.Le)
        # The offset's light technique relative to the base's BSDF pdf, r p_light(y) /
        # p_bsdf(y), without 0 * inf at grazing y: after a reconnection J p_light(y) =
        # p_light(x) for area-sampled emitters (see _light_own). Once connected, the segment
        # pdf is the offset's own (pb_prev) for one more vertex (CONNECTING).
        light_y = dr.select(
            own,
            o.r * pn_y / dr.select(o.pb_prev > 0, o.pb_prev, 1),
            dr.select(
                recent,
                dr.select(emission.cone, o.sJ * pn_y, o.s * emission.pn),
                o.r * emission.pn / dr.select(o.pb_prev > 0, o.pb_prev, 1),
            ),
        )
        # A segment sampled at a near-specular pair is estimated by BSDF sampling alone.
        den = 1 + dr.select(o.bsdf_only, 0, emission.ratio + dr.select(o.alive, light_y, 0))
        den += dr.select(o.alive, o.r, 0)
        c_shift = dr.select(o.alive, o.q * Le_y, 0)
        _add_term(base, o, c_shift, emission.c_main, den, base.active)
        o.alive &= ~o.escaped

    # ------------------------------------------------------------------ next-event estimation
    def _sample_light(self, scene, sampler, si, bsdf, active_next):
        """The base's light sample at x_i and its BSDF sample for the next direction (one
        virtual call evaluates the first and draws the second). Returns ``(light, bs,
        bsdf_weight, u1, u2)``: the :class:`LightSample`, the BSDF sample with its weight
        ``f cos / pdf`` and the random numbers it used."""
        active_em = active_next & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
        # Visibility is tested separately: an occluded base light sample still has offsets.
        ds, em_weight = scene.sample_emitter_direction(si, sampler.next_2d(), False, active_em)
        active_em &= ds.pdf != 0
        visible = ~scene.ray_test(si.spawn_ray_to(ds.p), active_em)
        em_weight = dr.select(visible, em_weight, 0)
        wo = si.to_local(ds.d)
        u1, u2 = sampler.next_1d(), sampler.next_2d()
        f, pb, bs, bsdf_weight = bsdf.eval_pdf_sample(_CTX, si, wo, u1, u2, active_next)
        f = dr.select(active_em, f, 0)
        pb = dr.select(active_em & ~ds.delta, pb, 0)
        infinite = mi.has_flag(ds.emitter.flags(), mi.EmitterFlags.Infinite)
        light = LightSample(
            ds=ds,
            wo=wo,
            active=active_em,
            visible=visible,
            weight=em_weight,
            em=em_weight * ds.pdf,
            f=f,
            pb=pb,
            mis=safe_div(ds.pdf, ds.pdf + pb),
            infinite=infinite,
            cone=_is_cone_sampled(ds.emitter),
            fixed_point=infinite | ds.delta,
        )
        return light, bs, bsdf_weight, u1, u2

    def _shift_light(self, scene, base, o, view, near_y, bsdf, light, near_x, c_main) -> None:
        """The offset's version of the base's light sample (``c_main``: the base's
        contribution ``β f Le`` before MIS): adds its half-gradient term to ``o.G``.

        Light samples join the MIS of a pixel pair only where the BSDF shift of the same path
        exists in both directions, so that the four techniques (base / offset x BSDF / light)
        see the same set of shifted paths: the light point visible from x_i and y_i, nonzero
        BSDF pdfs at both (delta lights have no BSDF technique), and a reconnection as the
        BSDF shift's mapping. At a near-specular pair (``near_x`` or ``near_y``: x_i or y_i at
        or below shift_threshold) the BSDF shift copies the half vector instead, so there the
        gradient takes the segment from BSDF sampling alone (``bsdf_only``) and drops the light
        technique of both paths; the primal keeps its own MIS.
        """
        own = o.status == NOT_CONNECTED
        recent = o.status == RECENTLY_CONNECTED
        act = light.active & o.alive
        # Recently connected: the base's BSDF at x_i towards the same light sample, arriving
        # from y_{i-1}. Connected: the base's own values.
        f_r, pb_r = bsdf.eval_pdf(_CTX, view, light.wo, act & recent)
        pb_r = dr.select(light.ds.delta, 0, pb_r)
        shifted = dr.if_stmt(
            (),
            act & own,
            lambda: self._light_own(scene, o, light, act),
            lambda: _light_follow(light, recent, f_r, pb_r),
        )
        # Connected offsets always pair (the two-phase fold relies on it).
        pair = shifted.pair & (
            o.alive & ((o.status >= CONNECTING) | light.ds.delta | (light.visible & (light.pb > 0)))
        )
        den = light.ds.pdf + light.pb + dr.select(pair, o.r * shifted.Jp, 0)
        c_shift = dr.select(pair, o.q * shifted.f * shifted.em * shifted.J, 0)
        bsdf_only = own & o.alive & (near_x | near_y) & ~light.ds.delta
        _add_term(base, o, c_shift, c_main, den, light.active & ~bsdf_only)

    def _light_own(
        self, scene: mi.Scene, o: OffsetState, light: LightSample, act: mi.Bool
    ) -> LightShift:
        """Own vertex y_i: reconnect it to the base's light point."""
        y = o.si
        bsdf_y = y.bsdf()
        ds = light.ds
        to_light = ds.p - y.p
        dist_y = dr.norm(to_light)
        dir_y = dr.select(light.infinite, ds.d, to_light / dist_y)
        dist_y = dr.select(light.infinite, ds.dist, dist_y)
        ds_y = mi.DirectionSample3f(
            ds.p, ds.n, ds.uv, ds.time, ds.pdf, ds.delta, dir_y, dist_y, ds.emitter
        )
        act_own = act & mi.has_flag(bsdf_y.flags(), mi.BSDFFlags.Smooth)
        ray_y = dr.select(light.infinite, y.spawn_ray(dir_y), y.spawn_ray_to(ds.p))
        visible = ~scene.ray_test(ray_y, act_own)
        em = dr.select(visible, scene.eval_emitter_direction(y, ds_y, act_own), 0)
        J = dr.select(
            light.fixed_point,
            1.0,
            reconnection_jacobian(ds.n, ds.d, dr.square(ds.dist), dir_y, dr.square(dist_y)),
        )
        # J p_light(y). Area-sampled emitters and fixed points: exactly p_light(x), also when
        # the light turns its back to y (Mitsuba samples such points with nonzero pdf, although
        # pdf_emitter_direction() reports 0), and free of 0 * inf at grazing y. Spheres are
        # sampled by cone, which never picks their far side.
        front = dr.dot(ds.n, dir_y) < 0
        pn_cone = scene.pdf_emitter_direction(y, ds_y, act_own & light.cone & front)
        Jpn = dr.select(light.cone, J * pn_cone, ds.pdf)
        f, pb = bsdf_y.eval_pdf(_CTX, y, y.to_local(dir_y), act_own)
        pair = act_own & (ds.delta | (visible & (pb > 0)))
        pb = dr.select(ds.delta, 0, pb)
        return LightShift(f=f, em=em, J=J, Jp=dr.select(act_own, Jpn, 0) + J * pb, pair=pair)

    # ------------------------------------------------------------------ BSDF sampling
    def _trace_segment(self, scene, si, bs, bsdf_weight, u1, u2, near_x, active_next) -> Segment:
        """Trace the base's BSDF sample ``bs`` from x_i (near-specular glossy: ``near_x``) to
        x_{i+1} and classify both ends for the shift."""
        delta = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
        ray = si.spawn_ray(si.to_world(bs.wo))
        si_next = scene.ray_intersect(ray, active_next)
        hit = si_next.is_valid()
        bsdf_next = si_next.bsdf()
        rough = ~hit | ~(
            mi.has_flag(bsdf_next.flags(), mi.BSDFFlags.Delta)
            | self._near_glossy(si_next, bsdf_next, hit & active_next)
        )
        null = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Null) if self._has_null else mi.Bool(False)
        return Segment(
            bs=bs,
            weight=bsdf_weight,
            u1=u1,
            u2=u2,
            ray=ray,
            si=si_next,
            hit=hit,
            rough=rough,
            delta=delta,
            reflect=mi.has_flag(bs.sampled_type, mi.BSDFFlags.DeltaReflection),
            null=null,
            near=near_x,
            half=~delta & near_x,
            inv_p=safe_div(1.0, bs.pdf),
            pb=dr.select(delta, 1.0, bs.pdf),
        )

    def _shift_segment(self, scene, base, o, view, near_y, si, bsdf, seg, active_next, n) -> None:
        """Move the offset along the base's segment ``seg`` from x_i (``si``, ``bsdf``):
        its own vertex y_i shifts (:meth:`_shift_own`), a connected one follows."""
        # No base sample, no shift (the reverse shift finds a zero pdf at x_i)
        act = active_next & o.alive & (seg.bs.pdf > 0)
        own = o.status == NOT_CONNECTED
        recent = o.status == RECENTLY_CONNECTED
        # Recently connected: the base's BSDF at x_i towards the base's sample, arriving from
        # y_{i-1}.
        f_r, p_r = bsdf.eval_pdf(_CTX, view, seg.bs.wo, act & recent)
        step = dr.if_stmt(
            (),
            act & own,
            lambda: self._shift_own(scene, o, near_y, si, bsdf, seg, act),
            lambda: _shift_follow(o, seg, recent, f_r, p_r, n),
        )
        o.pb_prev = step.pb
        o.s = step.s
        o.sJ = step.sJ
        o.escaped = step.escaped
        o.status = step.status
        o.bsdf_only = step.bsdf_only
        # A throughput or MIS ratio that is not finite fails the shift (counted). An
        # overflowing r (+inf: the offset's pdf dwarfs the base's) is capped, so that the
        # base's weight goes to 0, its correct limit.
        numeric = dr.isfinite(dr.sum(step.q)) & ~dr.isnan(step.r)
        base.bad_shift += dr.select(act & step.ok & ~numeric, 1, 0)
        o.q = dr.select(numeric, step.q, 0)
        o.r = dr.select(numeric, dr.minimum(step.r, 1e30), 0)
        o.alive = act & step.ok & numeric
        # Selected here, not in the branches: returning the outer seg.si from one branch of
        # dr.if_stmt corrupted the base path's copy of it (Dr.Jit 1.5).
        o.si = dr.select(step.trace, step.si, seg.si)
        o.prev = _vertex(view)  # y_i (own) or x_i

    def _shift_own(self, scene, o, near_y, si, bsdf, seg, act) -> ShiftStep:
        """Own vertex y_i: reconnect, follow a delta lobe, copy the half vector, or replay the
        base's random numbers."""
        y = o.si
        bsdf_y = y.bsdf()
        y_smooth = mi.has_flag(bsdf_y.flags(), mi.BSDFFlags.Smooth)
        half_y = near_y & ~seg.delta
        reconnect = ~seg.delta & ~seg.half & seg.rough & y_smooth & ~half_y

        # Reconnection y_i -> x_{i+1} (or environment shift: copy the direction)
        act_rc = act & reconnect
        to_next = seg.si.p - y.p
        d_y2 = dr.squared_norm(to_next)
        dir_rc = dr.select(seg.hit, to_next * dr.rsqrt(d_y2), seg.ray.d)
        ray_rc = dr.select(seg.hit, y.spawn_ray_to(seg.si.p), y.spawn_ray(dir_rc))
        J_rc = dr.select(
            seg.hit,
            reconnection_jacobian(seg.si.n, seg.ray.d, dr.square(seg.si.t), dir_rc, d_y2),
            1.0,
        )
        f_rc, p_rc = bsdf_y.eval_pdf(_CTX, y, y.to_local(dir_rc), act_rc)

        # Delta lobe: sample the offset's lobe of the same kind; f_d is its delta coefficient
        # (weight x pdf of the restricted sample).
        act_d = act & seg.delta & ~seg.null
        bs_r, w_r = bsdf_y.sample(_CTX_REFLECT, y, seg.u1, seg.u2, act_d & seg.reflect)
        bs_t, w_t = bsdf_y.sample(_CTX_TRANSMIT, y, seg.u1, seg.u2, act_d & ~seg.reflect)
        bs_d = dr.select(seg.reflect, bs_r, bs_t)
        f_d = dr.select(seg.reflect, w_r, w_t) * bs_d.pdf
        # The sample must be of the requested kind: a mask BSDF answers a restricted context
        # with its null lobe.
        kind = mi.has_flag(bs_d.sampled_type, mi.BSDFFlags.DeltaReflection)
        kind = dr.select(
            seg.reflect, kind, mi.has_flag(bs_d.sampled_type, mi.BSDFFlags.DeltaTransmission)
        )
        ok_d = (bs_d.pdf > 0) & (dr.max(f_d) > 0) & kind
        if self._has_null:
            # Null lobe (opacity masks): straight on, f = the null transmission
            wo_d = dr.select(seg.null, -y.wi, bs_d.wo)
            f_null = bsdf_y.eval_null_transmission(y, act & seg.null)
            f_d = dr.select(seg.null, f_null, f_d)
            ok_d = dr.select(seg.null, dr.max(f_null) > 0, ok_d)
        else:
            wo_d = bs_d.wo

        # Near-specular glossy x_i and y_i: copy the base's half vector
        act_h = act & seg.half
        wo_h, J_h, ok_h = half_vector_shift(si.wi, seg.bs.wo, seg.bs.eta, y.wi)
        ok_h &= half_y & ((seg.bs.eta == 1) | (bsdf_y == bsdf))  # refraction: same IOR
        f_h, p_h = bsdf_y.eval_pdf(_CTX, y, wo_h, act_h & ok_h)
        ok_h &= p_h > 0

        # Rough x_i before a near-specular x_{i+1}: replay the base's random numbers
        act_s = act & ~seg.delta & ~seg.half & ~reconnect
        bs_s, w_s = bsdf_y.sample(_CTX, y, seg.u1, seg.u2, act_s)
        # A near-specular y_i under a rough x_i fails: from y the shift would copy the half
        # vector, so replay would not be the inverse of the reverse shift.
        ok_s = y_smooth & (bs_s.pdf > 0) & ~half_y
        ok_s &= ~mi.has_flag(bs_s.sampled_type, mi.BSDFFlags.Delta)

        trace = act & ~reconnect
        # Shadow test (any hit) for a reconnection; closest hit for a new vertex
        visible = ~scene.ray_test(ray_rc, act_rc)
        wo_y = dr.select(seg.delta, wo_d, dr.select(seg.half, wo_h, bs_s.wo))
        si_y = scene.ray_intersect(y.spawn_ray(y.to_world(wo_y)), trace)
        hit_y = si_y.is_valid()
        bsdf_ny = si_y.bsdf()
        rough_y = ~hit_y | ~(
            mi.has_flag(bsdf_ny.flags(), mi.BSDFFlags.Delta)
            | self._near_glossy(si_y, bsdf_ny, hit_y & act_s)
        )
        # Non-invertible: the reverse shift from y would reconnect at this vertex
        ok_s &= ~rough_y

        # Reconnection and half-vector copy: f J / p_x and p_y J / p_x. Delta lobes (J = 1)
        # and replay (J = p_x / p_y in solid angle) simplify to sample weights.
        mapped = reconnect | seg.half
        f_m = dr.select(seg.half, f_h, f_rc)
        J_m = dr.select(seg.half, J_h, J_rc)
        p_m = dr.select(seg.half, p_h, p_rc)
        q = dr.select(
            mapped,
            o.q * f_m * (J_m * seg.inv_p),
            dr.select(seg.delta, o.q * f_d * seg.inv_p, o.q * w_s),
        )
        r = dr.select(mapped, o.r * p_m * J_m * seg.inv_p, o.r)
        # A mapping whose Jacobian is 0 or not finite (grazing, coincident vertices) fails
        # (safe_div returns 0 there).
        ok = dr.select(reconnect, visible & (p_rc > 0) & (J_rc > 0), ok_s)
        ok = dr.select(seg.half, ok_h & (J_h > 0), dr.select(seg.delta, ok_d, ok))
        s_rc = dr.select(reconnect, o.r * seg.inv_p, 0)
        return ShiftStep(
            q=q,
            r=r,
            ok=ok,
            pb=dr.select(mapped, p_m, dr.select(seg.delta, 1.0, bs_s.pdf)),
            s=s_rc,
            sJ=s_rc * J_rc,
            escaped=trace & ~hit_y & seg.hit,
            trace=trace,
            si=si_y,
            status=dr.select(reconnect, mi.UInt32(RECENTLY_CONNECTED), NOT_CONNECTED),
            bsdf_only=act & (seg.near | near_y),
        )

    # ------------------------------------------------------------------ vertex classification
    def _near_glossy(self, si, bsdf, active) -> mi.Bool:
        """Glossy vertex with roughness <= shift_threshold (half-vector copy, features pass)."""
        if self._active_threshold is None:
            return mi.Bool(False)
        return _near_specular_glossy(si, bsdf, self._active_threshold, active)

    def _own_near_glossy(self, o: OffsetState, active: mi.Bool) -> mi.Bool:
        """Whether the offset's own vertex y_i is near-specular glossy."""
        if self._active_threshold is None:
            return mi.Bool(False)
        own_next = (o.status == NOT_CONNECTED) & o.alive & active
        return self._near_glossy(o.si, o.si.bsdf(), own_next)


# ---------------------------------------------------------------------- shift helpers
def _initial_offset(
    si: mi.SurfaceInteraction3f,
    weight: mi.Spectrum,
    base_hit: mi.Bool,
    active: mi.Bool,
    n: int,
    mis: bool,
) -> OffsetState:
    """Loop state of an offset whose camera ray hit ``si`` (``n`` lanes; ``mis``: keep the
    base's MIS-weighted contributions, ``primal="mis"``)."""
    return OffsetState(
        si=si,
        prev=dr.zeros(mi.Interaction3f, n),
        status=mi.UInt32(NOT_CONNECTED),
        alive=mi.Bool(active),
        escaped=base_hit & ~si.is_valid(),
        q=mi.Spectrum(weight),
        r=mi.Float(1.0),
        pb_prev=mi.Float(1.0),
        bsdf_only=mi.Bool(False),
        s=mi.Float(0.0),
        sJ=mi.Float(0.0),
        G=dr.zeros(mi.Spectrum, n),
        B=dr.zeros(mi.Spectrum, n) if mis else None,
    )


def _offset_view(o: OffsetState, si: mi.SurfaceInteraction3f) -> mi.SurfaceInteraction3f:
    """The offset's current vertex: its own y_i (NOT_CONNECTED), or the base's x_i (``si``)
    seen from the offset's previous vertex (RECENTLY_CONNECTED: ``o.si`` holds x_i, only wi
    differs; CONNECTED: unused). Merging both halves the virtual calls of the shift."""
    recent = o.status == RECENTLY_CONNECTED
    view = dr.copy(o.si)
    turn = recent & si.is_valid()
    view.wi = dr.select(turn, si.to_local(dr.normalize(o.prev.p - si.p)), view.wi)
    return view


def _add_term(
    base: BaseState, o: OffsetState, c_shift: mi.Spectrum, c_main: mi.Spectrum, den, active
) -> None:
    """One technique's contributions of the pair, the offset's ``c_shift`` and the base's
    ``c_main``, over their balance-heuristic denominator ``den`` (relative to the sampling
    pdf): ``o.G += (c_shift - c_main) / den`` and, with ``o.B`` (``primal="mis"``),
    ``o.B += c_main / den`` where ``active``; a term that is not finite is dropped (from both)
    and counted in ``base.bad_term``."""
    term = (c_shift - c_main) / den
    ok = dr.isfinite(dr.sum(term))
    if o.B is not None:
        share = c_main / den
        ok &= dr.isfinite(dr.sum(share))
        o.B += dr.select(active & ok, share, 0)
    o.G += dr.select(active & ok, term, 0)
    base.bad_term += dr.select(active & ~ok, 1, 0)


def _light_follow(light: LightSample, recent: mi.Bool, f_r, pb_r) -> LightShift:
    """Recently connected (``f_r``, ``pb_r``: the base's BSDF at x_i seen from y_{i-1}) or
    connected (the base's own values): the offset shares the base's light point."""
    return LightShift(
        f=dr.select(recent, f_r, light.f),
        em=light.em,
        J=mi.Float(1.0),
        Jp=light.ds.pdf + dr.select(recent, pb_r, light.pb),
        pair=~recent | light.ds.delta | (pb_r > 0),
    )


def _shift_follow(o: OffsetState, seg: Segment, recent: mi.Bool, f_r, p_r, n: int) -> ShiftStep:
    """Recently connected (``f_r``, ``p_r``: the base's BSDF at x_i towards its sample, seen
    from y_{i-1}) or connected: the offset shares the base's next vertex."""
    zero = dr.zeros(mi.Float, n)
    # The offset's own segment pdf matters for one more vertex, unless it equals the base's
    # (diffuse x_i: the pdf does not depend on wi)
    status = dr.select(recent & (p_r != seg.pb), mi.UInt32(CONNECTING), mi.UInt32(CONNECTED))
    return ShiftStep(
        q=dr.select(recent, o.q * f_r * seg.inv_p, o.q * seg.weight),
        r=dr.select(recent, o.r * p_r * seg.inv_p, o.r),
        ok=~recent | (p_r > 0),
        pb=dr.select(recent, p_r, seg.pb),
        s=zero,
        sJ=zero,
        escaped=mi.Bool(False),
        trace=mi.Bool(False),
        si=dr.zeros(mi.SurfaceInteraction3f, n),
        status=status,
        bsdf_only=mi.Bool(False),
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
