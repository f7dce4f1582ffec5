"""``gdpt_rr``: gradient-domain path tracing with the random-replay shift (the short twin)."""

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


@dataclass
class PathState:
    """Loop state of one standard MIS path tracer (NEE + BSDF sampling, balance heuristic)."""

    ray_d: mi.Vector3f
    si: mi.SurfaceInteraction3f
    prev: mi.SurfaceInteraction3f
    beta: mi.Spectrum
    eta: mi.Float
    pb_prev: mi.Float
    delta_prev: mi.Bool
    active: mi.Bool
    L: mi.Spectrum


class GDPTReplayIntegrator(GradientIntegratorBase):
    r"""
    .. _integrator-gdpt_rr:

    Random-replay gradient-domain path tracer (:monosp:`gdpt_rr`)
    -------------------------------------------------------------

    Same parameters and outputs as :ref:`gdpt <integrator-gdpt>`. Deliberately short: every
    offset path is an ordinary path tracer started from the shifted camera ray that consumes
    exactly the base path's random numbers (the primary-sample-space shift). Its Jacobian in
    primary sample space is 1, so the balance heuristic gives each of the two directions of a
    pixel pair weight 1/2 and each half-gradient is ``(L_offset - L_base) / 2``. It never fails
    and needs no vertex classification, which makes it a readable reference and a test oracle
    for ``gdpt``; it correlates poorly after the first diffuse bounce, so its gradients are
    noisier. With ``primal="mis"`` the base path and the offset that lands in a pixel share it
    with these weights, 1/2 each.
    """

    plugin_name = "gdpt_rr"

    def sample_paths(self, scene, sensor, sampler, rays, weights, active) -> PathSamples:
        n = dr.width(rays[0].d)
        ctx = mi.BSDFContext()
        to_camera = camera_transform(sensor)
        paths = [
            PathState(
                ray_d=mi.Vector3f(ray.d),
                si=scene.ray_intersect(ray, active),
                prev=dr.zeros(mi.SurfaceInteraction3f, n),
                beta=mi.Spectrum(weight),
                eta=mi.Float(1.0),
                pb_prev=mi.Float(1.0),
                delta_prev=mi.Bool(True),
                active=mi.Bool(active),
                L=dr.zeros(mi.Spectrum, n),
            )
            for ray, weight in zip(rays, weights, strict=True)
        ]
        feat = FeatureState.zeros(n) if self.features else None
        depth = mi.UInt32(0)

        def cond(sampler, paths, feat, depth):
            return _any_active(paths)

        def body(sampler, paths, feat, depth):
            # One set of random numbers per depth, shared by all five paths.
            u_em, u1, u2, u_rr = (
                sampler.next_2d(),
                sampler.next_1d(),
                sampler.next_2d(),
                sampler.next_1d(),
            )
            for i, p in enumerate(paths):
                bsdf = p.si.bsdf()
                if i == 0 and feat is not None:
                    update_features(feat, p.si, bsdf, p.ray_d, to_camera, p.active)
                ds = mi.DirectionSample3f(scene, p.si, p.prev)
                pn = scene.pdf_emitter_direction(p.prev, ds, p.active & ~p.delta_prev)
                p.L += p.beta * ds.emitter.eval(p.si, p.active) / (1 + safe_div(pn, p.pb_prev))

                active_next = p.active & (depth + 1 < self.max_depth) & p.si.is_valid()
                active_em = active_next & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
                ds, em_weight = scene.sample_emitter_direction(p.si, u_em, True, active_em)
                f, pb = bsdf.eval_pdf(ctx, p.si, p.si.to_local(ds.d), active_em & (ds.pdf != 0))
                pb = dr.select(ds.delta, 0, pb)
                p.L += p.beta * f * em_weight * safe_div(ds.pdf, ds.pdf + pb)

                bs, bsdf_weight = bsdf.sample(ctx, p.si, u1, u2, active_next)
                ray = p.si.spawn_ray(p.si.to_world(bs.wo))
                p.beta *= bsdf_weight
                p.eta *= bs.eta
                beta_max = dr.max(p.beta)
                rr_active = depth >= self.rr_depth
                rr_prob = dr.minimum(beta_max * dr.square(p.eta), 0.95)
                p.beta *= dr.select(rr_active, safe_div(1.0, rr_prob), 1.0)
                p.prev = p.si
                p.si = scene.ray_intersect(ray, active_next)
                p.ray_d = ray.d
                p.pb_prev = dr.select(mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta), 1.0, bs.pdf)
                p.delta_prev = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
                p.active = active_next & (beta_max != 0) & (~rr_active | (u_rr < rr_prob))
            return sampler, paths, feat, depth + 1

        sampler, paths, feat, depth = dr.while_loop(
            (sampler, paths, feat, depth),
            cond,
            body,
            labels=("sampler", "paths", "features", "depth"),
            label="gdpt_rr",
        )
        L0 = paths[0].L
        mis = self.primal == "mis"
        return PathSamples(
            primal=L0,
            gradients=[0.5 * (p.L - L0) for p in paths[1:]],
            base_shares=[0.5 * L0 for _ in paths[1:]] if mis else [],
            albedo=feat.albedo if feat is not None else None,
            normal=feat.normal if feat is not None else None,
            depth=feat.depth if feat is not None else None,
        )


def _any_active(paths: list[PathState]) -> mi.Bool:
    active = mi.Bool(paths[0].active)
    for p in paths[1:]:
        active |= p.active
    return active


# Mitsuba's documented registration pattern: a constructor lambda
mi.register_integrator("gdpt_rr", lambda props: GDPTReplayIntegrator(props))  # noqa: PLW0108
