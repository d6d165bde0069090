"""Shading in the scene (scene world space): Phong at isosurface points (lecture 23), Mitsuba's
BSDFs at mesh points, and shadow rays that both meshes and isosurfaces block.

Isosurface points are lit by every emitter of the scene with one light sample each, Phong's
model with the gradient as the normal: a point of colour ``c`` gets ``c * A + S`` with
``A = ka ambient + sum kd L max(N.L, 0)`` and ``S = sum ks L max(N.H, 0)^shininess``. Mesh points
get their BSDF's diffuse reflectance times ``ka ambient`` plus direct light through the BSDF.
Shadow rays leave a surface interaction with ``spawn_ray_to`` (Mitsuba's own offsets, so a ray
hits neither the surface it leaves nor the emitter it aims at) and are dimmed by the
isosurfaces' transmittance in between (a callback into the kernels).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import drjit as dr
import mitsuba as mi


@dataclass
class Phong:
    """Phong's coefficients (Mitsuba-typed values; opaque arrays in vectorised variants)."""

    ka: Any
    kd: Any
    ks: Any
    shininess: Any
    ambient: Any


def phong_terms(phong: Phong, n, to_light, to_eye, light):
    """Diffuse and specular light from one emitter, ``(kd L max(N.L, 0), ks L max(N.H, 0)^ns)``,
    for unit vectors ``n``, ``to_light``, ``to_eye`` and incident radiance ``light`` (already
    shadowed)."""
    n_l = dr.maximum(dr.dot(n, to_light), 0.0)
    n_h = dr.maximum(dr.dot(n, dr.normalize(to_light + to_eye)), 0.0)
    return phong.kd * light * n_l, phong.ks * light * dr.power(n_h, phong.shininess)


def facing_normal(to_world, grad, ray_d):
    """The shading normal of an isosurface point: the gradient ``grad`` (volume space) taken to
    the scene and turned towards the viewer; ``-ray_d`` where the gradient vanishes."""
    n = dr.normalize(to_world @ grad)
    n = dr.select(dr.dot(n, ray_d) > 0.0, -n, n)
    return dr.select(dr.all(dr.isfinite(n)), n, -ray_d)


def shadow_ray(origin, ds):
    """The ray from ``origin`` (a surface interaction, or a point off every mesh) towards the
    light sample ``ds``, ending just before the light."""
    if isinstance(origin, mi.SurfaceInteraction3f):
        return origin.spawn_ray_to(ds.p)
    ray = mi.Ray3f(origin, ds.d)
    ray.maxt = ds.dist * (1.0 - mi.math.ShadowEpsilon)
    return ray


def visibility(scene, origin, ds, active, shadows, iso_transmittance: Callable, from_iso: bool):
    """Fraction of the light of sample ``ds`` reaching ``origin``: 0 behind a mesh, else the
    transmittance of the isosurfaces in between (``iso_transmittance(ray, from_iso, active)``),
    and 1 where ``shadows`` is off."""
    return ray_visibility(scene, shadow_ray(origin, ds), active, shadows, iso_transmittance,
                          from_iso)


def ray_visibility(scene, ray, active, shadows, iso_transmittance: Callable, from_iso: bool):
    """:func:`visibility` along the shadow ray ``ray`` itself."""
    test = active & shadows
    blocked = scene.ray_test(ray, test)
    clear = test & dr.select(blocked, False, True)
    T = iso_transmittance(ray, from_iso, clear)
    return dr.select(shadows, dr.select(blocked, 0.0, T), mi.Float(1.0))


def iso_light(scene, light_u, ray, P, n, phong: Phong, active, shadows, iso_transmittance):
    """``(A, S)`` of an isosurface point ``P`` with shading normal ``n`` (see the module
    docstring), one light sample ``light_u[i]`` per emitter."""
    A = mi.Spectrum(phong.ka * phong.ambient)
    S = mi.Spectrum(0.0)
    for emitter, u in zip(scene.emitters(), light_u):
        ds, w = sample_emitter(emitter, u, ray, P, active)
        lit = active & (ds.pdf > 0.0) & (dr.dot(n, ds.d) > 0.0)
        vis = visibility(scene, P, ds, lit, shadows, iso_transmittance, from_iso=True)
        diffuse, specular = phong_terms(phong, n, ds.d, -ray.d, w * vis)
        A += dr.select(lit, diffuse, 0.0)
        S += dr.select(lit, specular, 0.0)
    return A, S


@dataclass
class LightPart:
    """One emitter's direct light at an isosurface point before its shadow ray: the Phong
    terms ``diffuse`` (to be multiplied by the point's colour) and ``specular``, zero where
    the light is not on the normal's side, and the shadow ray that would decide them."""

    diffuse: Any
    specular: Any
    shadow: Any      # mi.Ray3f


def iso_light_parts(scene, light_u, ray, P, n, phong: Phong, active):
    """``(A0, parts)``: what :func:`iso_light` adds up, the shadow rays not yet traced --
    the ambient term ``A0`` and one :class:`LightPart` per emitter. ``iso_light`` is
    ``A0 + sum(diffuse * V)``, ``sum(specular * V)`` with each part's visibility ``V``."""
    parts = []
    for emitter, u in zip(scene.emitters(), light_u):
        ds, w = sample_emitter(emitter, u, ray, P, active)
        lit = active & (ds.pdf > 0.0) & (dr.dot(n, ds.d) > 0.0)
        diffuse, specular = phong_terms(phong, n, ds.d, -ray.d, w)
        parts.append(LightPart(diffuse=dr.select(lit, diffuse, 0.0),
                               specular=dr.select(lit, specular, 0.0),
                               shadow=shadow_ray(P, ds)))
    return mi.Spectrum(phong.ka * phong.ambient), parts


def sample_emitter(emitter, u, ray, P, active):
    """``emitter``'s direction sample and weight at the point ``P`` of the ray ``ray``."""
    it = dr.zeros(mi.Interaction3f)
    it.p = P
    it.time = ray.time
    it.wavelengths = ray.wavelengths
    return emitter.sample_direction(it, u, active)


@dataclass
class LightSample:
    """One emitter's light at a point: the unit direction to it (scene space), the radiance
    arriving (shadowed where asked) and where the sample is valid; for an emitter shadowed
    through its cache, also the radiance ``open`` that arrives past the meshes (the band's
    shadow left out) and the ``cached`` transmittance of the band (1 where shadows are off),
    so that ``radiance = open * cached``."""

    to_light: Any
    radiance: Any
    valid: Any
    open: Any = None
    cached: Any = None


@dataclass
class Shadowing:
    """How the light samples of a volume point are shadowed: ``shadows`` (a Mitsuba Bool, or
    False for no shadow rays at all), ``transmittance(ray, from_iso, active)`` (the exact
    shadow ray through the isosurfaces or the band) and per emitter ``cached``, the
    transmittance from its cache (``cached(P, ds, active)``, a Mitsuba Float at scene points
    ``P`` towards light samples ``ds``, see :class:`~mi_amr.plugin.shadow_cache.CachedShadow`;
    its meshes still tested by a shadow ray), or None for the exact shadow ray."""

    shadows: Any
    transmittance: Callable
    cached: list


def light_samples(scene, light_u, ray, P, active, shadowing: Shadowing):
    """One :class:`LightSample` per emitter at the scene point ``P`` (a point inside the
    volume band, lit from every side); shadowed by meshes and isosurfaces (or the band) as
    ``shadowing`` says."""
    out = []
    for emitter, u, cached in zip(scene.emitters(), light_u, shadowing.cached):
        ds, w = sample_emitter(emitter, u, ray, P, active)
        valid = active & (ds.pdf > 0.0)
        if shadowing.shadows is False:
            out.append(LightSample(to_light=ds.d, radiance=w, valid=valid))
        elif cached is None:
            w = w * visibility(scene, P, ds, valid, shadowing.shadows, shadowing.transmittance,
                               from_iso=True)
            out.append(LightSample(to_light=ds.d, radiance=w, valid=valid))
        else:
            w = w * visibility(scene, P, ds, valid, shadowing.shadows, _clear, from_iso=True)
            band = dr.select(shadowing.shadows, cached(P, ds, valid), 1.0)
            out.append(LightSample(to_light=ds.d, radiance=w * band, valid=valid, open=w,
                                   cached=band))
    return out


def _clear(_ray, _from_iso, _active):
    """The isosurfaces' transmittance where it is looked up elsewhere: 1."""
    return mi.Float(1.0)


def volume_terms(samples, phong: Phong, n, to_eye, active):
    """``(A, S)`` (see the module docstring) of a point with shading normal ``n`` lit by
    ``samples`` (:func:`light_samples`)."""
    return phong_sum(samples, phong, n, to_eye, active, mi.Spectrum(phong.ka * phong.ambient))


def phong_sum(samples, phong: Phong, n, to_eye, active, A):
    """``A`` plus each sample's diffuse light, and the sum of their specular light, where the
    sample is valid and lights the front of ``n``."""
    S = mi.Spectrum(0.0)
    for smp in samples:
        diffuse, specular = phong_terms(phong, n, smp.to_light, to_eye, smp.radiance)
        lit = active & smp.valid & (dr.dot(n, smp.to_light) > 0.0)
        A += dr.select(lit, diffuse, 0.0)
        S += dr.select(lit, specular, 0.0)
    return A, S


def mesh_light(scene, sampler, ray, si, phong: Phong, active, shadows, iso_transmittance):
    """Emission plus ambient and direct light through the BSDF at a mesh point ``si``,
    shadowed by meshes and isosurfaces; the environment where the ray escaped."""
    emitter = si.emitter(scene, active)
    scalar = not dr.is_jit_v(mi.Float)
    # (Scalar variants give None for "no emitter" / "no BSDF" instead of masked calls.)
    L = mi.Spectrum(0.0) if scalar and emitter is None else \
        dr.select(active, emitter.eval(si, active), 0.0)
    on_mesh = active & si.is_valid()
    if scalar and not on_mesh:
        return L
    bsdf = si.bsdf(ray)
    ctx = mi.BSDFContext()
    L += dr.select(on_mesh, bsdf.eval_diffuse_reflectance(si, on_mesh) *
                   (phong.ka * phong.ambient), 0.0)
    for emitter in scene.emitters():
        ds, w = emitter.sample_direction(si, sampler.next_2d(on_mesh), on_mesh)
        lit = on_mesh & (ds.pdf > 0.0)
        vis = visibility(scene, si, ds, lit, shadows, iso_transmittance, from_iso=False)
        f = bsdf.eval(ctx, si, si.to_local(ds.d), lit)
        L += dr.select(lit, f * w * vis, 0.0)
    return L
