"""``glass_path``: a path tracer for glass on a table that converges at a few samples per pixel.

Why: in an exact path tracer the table *under and behind* a solid glass object is lit only through the glass
(refractive caustics). Next-event estimation cannot reach a light through a dielectric, so that light arrives
only when a BSDF-sampled path happens to hit a light: at 16-64 spp the glass shows dark, speckled interiors
(measured: ``benchmarks/render.py``, integrator ``path`` vs ``glass_path``).

What it changes (the practice of Blender Cycles' "caustics off" + transparent shadows, used for synthetic
transparent-object data sets), everything else being Mitsuba's ``path`` integrator (MIS between emitter and
BSDF sampling, Russian roulette):

1. Shadow rays pass straight through dielectric surfaces (up to ``shadow_hits`` of them), attenuated by each
   surface's Fresnel transmittance (evaluated by the surface's own BSDF at the hit, i.e. with its IOR, as seen
   from outside: the unrefracted ray would otherwise meet total internal reflection on the way out); any other
   surface blocks them. Such a sample gets MIS weight 1, because
2. a path that reaches a delta (glass) surface *after* a non-delta bounce ends there: the light it would carry
   (the caustic) is what the straight-through shadow rays already gave.

Camera paths are untouched until their first non-delta bounce: what the camera sees through glass is refracted
and reflected exactly (Fresnel, total internal reflection, any number of interfaces up to ``max_depth``).
The approximation only concerns how surfaces *behind* glass are lit: glass casts a Fresnel-dimmed, unfocused
shadow instead of a focused caustic. JIT variants only (``llvm_ad_rgb``); under ``scalar_rgb`` the renderer
uses Mitsuba's ``path``.
"""

from __future__ import annotations

from typing import Any

import drjit as dr  # module globals: dr.syntax resolves names through them
import mitsuba as mi

_REGISTERED = {"done": False}


def mis_weight(pdf_a: Any, pdf_b: Any) -> Any:
    """Power heuristic (beta 2) weight of strategy a, 0 where ``pdf_a`` is 0 (as in Mitsuba's integrators)."""
    a2 = dr.square(pdf_a)
    return dr.detach(dr.select(pdf_a > 0, a2 / dr.fma(pdf_b, pdf_b, a2), 0.0), True)


def register() -> None:
    """Register the ``glass_path`` integrator with Mitsuba (a JIT variant must be set)."""
    if _REGISTERED["done"]:
        return
    from mitsuba.ad.integrators.common import RBIntegrator

    class GlassPathIntegrator(RBIntegrator):
        """Path tracer with straight-through shadow rays for dielectrics and no refractive caustics."""

        def __init__(self, props: Any) -> None:
            super().__init__(props)
            self.shadow_hits = int(props.get("shadow_hits", 8))

        @dr.syntax
        def shadow_transmittance(self, scene: Any, si: Any, ds: Any, active: Any) -> tuple[Any, Any]:
            """(Tr, crossed): Fresnel transmittance of the straight segment si -> ds.p through dielectrics only."""
            ctx = mi.BSDFContext()
            ctx.type_mask = mi.BSDFFlags.DeltaTransmission
            ray = si.spawn_ray_to(ds.p)
            Tr = mi.Spectrum(1.0)
            crossed = mi.Bool(False)
            act = mi.Bool(active)
            i = mi.UInt32(0)
            while dr.hint(act, max_iterations=self.shadow_hits, label="glass shadow"):
                hit = scene.ray_intersect(ray, mi.RayFlags.All, False, act)
                act &= hit.is_valid()
                bsdf = hit.bsdf()
                glass = mi.has_flag(bsdf.flags(), mi.BSDFFlags.DeltaTransmission)
                Tr[act & ~glass] = 0.0
                act &= glass
                # Fresnel transmittance as seen from outside the surface (entering and leaving a slab transmit
                # alike; from inside, a straight, unrefracted ray would hit total internal reflection)
                hit.wi = mi.Vector3f(hit.wi.x, hit.wi.y, dr.abs(hit.wi.z))
                bs, w = bsdf.sample(ctx, hit, mi.Float(0.5), mi.Point2f(0.5, 0.5), act)
                # the sampled weight is t / eta^2 in radiance mode: undo the solid-angle factor
                Tr[act] *= w * dr.square(bs.eta)
                crossed |= act
                ray = mi.Ray3f(hit.spawn_ray(ray.d))
                ray.maxt = dr.maximum(ds.dist - dr.norm(ray.o - si.p), 0.0) * (1.0 - mi.math.ShadowEpsilon)
                i += 1
                act &= i < self.shadow_hits
            Tr[act] = 0.0  # still inside after shadow_hits surfaces: treat as blocked
            return Tr, crossed

        @dr.syntax
        def sample(self, mode: Any, scene: Any, sampler: Any, ray: Any, δL: Any, state_in: Any,  # noqa: N803
                   active: Any, **kwargs: Any) -> tuple[Any, Any, list, Any]:
            ctx = mi.BSDFContext()
            ray = mi.Ray3f(ray)
            depth = mi.UInt32(0)
            L = mi.Spectrum(0.0)
            β = mi.Spectrum(1.0)
            η = mi.Float(1.0)
            active = mi.Bool(active)
            si_prev = dr.zeros(mi.SurfaceInteraction3f)
            pdf_prev = mi.Float(1.0)
            delta_prev = mi.Bool(True)
            diffuse_seen = mi.Bool(False)
            while dr.hint(active, max_iterations=self.max_depth, label="glass_path"):
                si = scene.ray_intersect(ray, mi.RayFlags.All, depth == 0, active)
                bsdf = si.bsdf(ray)
                # emission reached by BSDF sampling, MIS-weighted against the previous vertex's emitter sample
                ds = mi.DirectionSample3f(scene, si=si, ref=si_prev)
                mis = mis_weight(pdf_prev, scene.pdf_emitter_direction(si_prev, ds, ~delta_prev))
                L += β * mis * ds.emitter.eval(si, active)
                active_next = active & (depth + 1 < self.max_depth) & si.is_valid()
                # a glass surface after a diffuse bounce ends the path (its light came through the shadow rays)
                active_next &= ~(diffuse_seen & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Delta))
                # emitter sampling with straight-through shadow rays for dielectrics
                active_em = active_next & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
                ds, em_w = scene.sample_emitter_direction(si, sampler.next_2d(), False, active_em)
                active_em &= ds.pdf != 0.0
                Tr, crossed = self.shadow_transmittance(scene, si, ds, active_em)
                wo = si.to_local(ds.d)
                val, pdf_bsdf = bsdf.eval_pdf(ctx, si, wo, active_em)
                mis_em = dr.select(ds.delta | crossed, 1.0, mis_weight(ds.pdf, pdf_bsdf))
                L[active_em] += β * mis_em * val * em_w * Tr
                # BSDF sampling
                bs, bw = bsdf.sample(ctx, si, sampler.next_1d(), sampler.next_2d(), active_next)
                ray = si.spawn_ray(si.to_world(bs.wo))
                η *= bs.eta
                β *= bw
                si_prev = dr.detach(si, True)
                pdf_prev = bs.pdf
                delta_prev = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
                diffuse_seen |= active_next & ~delta_prev
                β_max = dr.max(mi.unpolarized_spectrum(β))
                active_next &= β_max != 0
                rr_prob = dr.minimum(β_max * η**2, 0.95)
                rr_active = depth >= self.rr_depth
                β[rr_active] *= dr.rcp(rr_prob)
                active_next &= ~rr_active | (sampler.next_1d() < rr_prob)
                depth[si.is_valid()] += 1
                active = active_next
            return L, depth != 0, [], L

    mi.register_integrator("glass_path", lambda props: GlassPathIntegrator(props))
    _REGISTERED["done"] = True
