"""The integrator's render loop on vectorised variants: Mitsuba's wavefront, with its lanes in
tile order.

Mitsuba's own ``SamplingIntegrator.render`` lays the wavefront out in scanlines (lane
``q = pixel * spp + sample``, pixels row after row), so a SIMD packet of 16 lanes is a strip of
16 pixels of one row at 1 spp. Rays of a square of pixels stay closer together through the
volume: their kd-tree walks, leaves and cubic pieces agree more often, and a packet runs its
loops as long as its slowest lane. :func:`pixel_order` puts the pixels in squares of
:data:`TILE` x :data:`TILE` inside squares of :data:`SUPER` x :data:`SUPER`, the samples of a
pixel side by side as before.

:func:`render` is Mitsuba's loop otherwise (``render_sample``: the pixel's sample position,
aperture, time, the sensor's ray and its weight, the film's channels R, G, B, [alpha], weight,
then the AOVs, one ``ImageBlock.put`` per lane). With ``order=None`` it keeps Mitsuba's lanes
and renders what Mitsuba's loop renders, up to float rounding (the slow twin,
``tests/test_wavefront.py``). In tile order lane ``j`` draws what lane ``j`` of the scanline
wavefront draws from the sampler, for another pixel: the same image up to Monte Carlo noise
(the committed references were rendered again for it: each differs from the one before as
much as a render at another seed does).

Pixel positions are in the film's crop coordinates plus the crop offset (pixels, origin at the
film's top left), as Mitsuba's.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Optional

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_amr.kernels.jitter import stable_jitter
from mi_amr.plugin import bridge
from mi_amr.plugin.layers import ONE_BELOW

TILE = 4        # a 16-lane packet at 1 spp: 4 x 4 pixels
PACKET = 16     # lanes of a SIMD packet (AVX-512; AVX2's 8 are half of one)
SUPER = 32      # tiles in squares of 32 x 32 pixels: the lanes a thread takes in a row
# (Scanlines, 8 x 8 tiles and Morton order were tried against these; the bench outputs keep
# the measurements.)


def pixel_order(width: int, height: int) -> np.ndarray:
    """The pixels ``y * width + x`` in tile order (``uint32``, a permutation of ``width *
    height``): lane ``j`` of the tiled wavefront takes scanline lane ``order[j // spp] * spp +
    j % spp``."""
    y, x = np.divmod(np.arange(width * height, dtype=np.int64), width)
    key = (((y // SUPER) * ((width + SUPER - 1) // SUPER) + x // SUPER) * (SUPER * SUPER) +
           ((y % SUPER) // TILE * (SUPER // TILE) + (x % SUPER) // TILE) * (TILE * TILE) +
           (y % TILE) * TILE + x % TILE)
    return np.argsort(key, kind="stable").astype(np.uint32)


class Orders:
    """:func:`pixel_order` as a device array, for the last film size asked (a kernel input,
    not a literal: a new film size compiles only what Mitsuba's image block compiles for it,
    as in Mitsuba's loop)."""

    def __init__(self):
        self._cache = {}

    def __call__(self, width: int, height: int):
        key = (width, height)
        if key not in self._cache:
            self._cache = {key: mi.UInt32(pixel_order(width, height))}
        return self._cache[key]


@dataclass(frozen=True)
class Lanes:
    """What :func:`render` hands each ``sample`` call of the frame it traces (the sample's
    lanes, not the integrator, hold it): ``lane``, each lane's scanline lane ``pixel * spp +
    sample`` (a device ``UInt32``); ``picks``, for a wavefront by sample, ``(spp, seed)`` as
    opaque device values that :func:`packet_u` hashes, else None."""

    lane: Any
    picks: Any = None


def lane_index(lanes: Optional[Lanes], ray):
    """Each lane's scanline lane ``pixel * spp + sample`` (what a per-pixel hash such as the
    stable jitter takes), for the wavefront ``lanes`` of :func:`render`; else (Mitsuba's own
    loop, or a ray of another width) the lane itself."""
    lane = None if lanes is None else lanes.lane
    if lane is None or dr.width(lane) != dr.width(ray.o):
        lane = dr.arange(mi.UInt32, dr.width(ray.o))
    return lane


def film_shape(sensor, spp: int):
    """``(width, height, spp, border)`` of the wavefront: the film's crop, grown by the
    filter's border where the film samples it, and the samples per pixel (``spp`` 0: the
    sampler's)."""
    film = sensor.film()
    size = film.crop_size()
    border = film.rfilter().border_size() if film.sample_border() else 0
    return (int(size[0]) + 2 * border, int(size[1]) + 2 * border,
            spp or sensor.sampler().sample_count(), border)


def supported(sensor, spp: int, part=None) -> bool:
    """Does :func:`render` handle this variant, film and wavefront? (Else Mitsuba's loop does,
    which also splits a wavefront of more than 2^32 lanes into passes.) The wavefront holds
    the samples that :func:`render` takes: the count the sampler keeps of ``spp`` (rounded up
    by a stratified sampler), or ``spp`` itself for a ``part`` of a set."""
    if not (dr.is_jit_v(mi.Float) and mi.is_rgb and not mi.is_polarized):
        return False
    width, height, spp, _ = film_shape(sensor, spp)
    if part is None:
        spp = int(_sampler(sensor, spp, None).sample_count())
    return not mi.has_flag(sensor.film().flags(), mi.FilmFlags.Special) and \
        width * height * spp < 2 ** 32


def render(integrator, scene, sensor, seed, spp, develop=True, evaluate=True, *,
           tiled=True, by_sample=False, part=None):
    """Render ``scene`` through ``sensor`` with ``integrator.sample``, the wavefront's pixels
    in tile order (scanlines where ``tiled`` is False, the slow twin; the tile orders come from
    ``integrator.pixel_orders``, an :class:`Orders`). Returns the developed image as
    ``mi.render`` does (None unless ``develop``). ``by_sample`` (tile order and 2 or more
    samples per pixel only): each packet holds one sample index of :data:`PACKET` pixels,
    and :func:`packet_u` gives the packet's shared numbers. ``part`` ``(first, count)``: the
    frame's ``spp`` samples are samples ``first .. first + spp - 1`` (``first`` a multiple of
    ``spp``) of a set of ``count`` a pixel that the sampler stratifies: frames of one set at
    one seed together draw each stratum once."""
    film = sensor.film()
    width, height, spp, border = film_shape(sensor, spp)
    order = integrator.pixel_orders(width, height) if tiled else None
    sampler = _sampler(sensor, spp, part)
    spp = int(sampler.sample_count()) if part is None else spp
    sampler.set_samples_per_wavefront(spp)
    n = width * height * spp
    sampler.seed(seed, n)
    if part is not None:
        for _ in range(part[0] // spp):
            sampler.advance()                   # the set's next spp samples
        # (Evaluated, the advanced index is a kernel input like the first pass's: advanced as
        # an expression, each pass would compile a kernel of its own.)
        sampler.schedule_state()
        dr.eval()
    film.prepare(integrator.aov_names())
    block = film.create_block()
    block.set_offset(film.crop_offset())
    block.set_coalesce(block.coalesce() and spp >= 4)

    # (At 1 spp a packet's shared number would be 16 pixels' only one: their noise would show
    # as 4 x 4 blocks. With more, each pixel's samples take every stratum.)
    by_sample = by_sample and order is not None and spp > 1
    lane = tiled_lanes(order, n, spp, by_sample) if order is not None else \
        dr.arange(mi.UInt32, n)
    picks = None
    if by_sample:
        seed_u = mi.UInt32(seed)
        dr.make_opaque(seed_u)          # a new seed compiles nothing
        picks = (dr.opaque(mi.UInt32, spp), seed_u)
    _render_lanes(integrator, scene, sensor, sampler, block, Lanes(lane, picks), width, spp,
                  border)
    film.put_block(block)
    result = None
    if develop:
        result = film.develop()
        dr.schedule(result)
    else:
        film.schedule_storage()
    if evaluate:
        dr.eval()
        dr.sync_thread()
    return result


def own_seed(args: tuple, part) -> tuple:
    """Mitsuba's ``render`` arguments ``(integrator, scene, sensor, seed, spp, develop,
    evaluate)`` for its own loop, which cannot draw a ``part`` of a stratified set
    (:func:`render`): the part gets a seed of its own, so that the passes of a set differ
    (unstratified)."""
    if part is None:
        return args
    seed = (args[3] * 0x9E3779B1 + part[0] + 1) % 2 ** 32
    return args[:3] + (seed,) + args[4:]


def _sampler(sensor, spp: int, part):
    """A clone of the sensor's sampler for ``spp`` samples a pixel, or (``part``) for the
    set of ``part[1]`` that they are a part of. A stratified or low-discrepancy sampler
    rounds its count up to a square or a power of two: a frame takes the count it kept, as
    Mitsuba's loop does."""
    sampler = sensor.sampler().clone()
    sampler.set_sample_count(spp if part is None else part[1])
    if part is not None and (part[0] % spp or part[0] + spp > int(sampler.sample_count())):
        raise ValueError(f"samples {part[0]}..{part[0] + spp - 1} are not a pass of a set of "
                         f"{int(sampler.sample_count())}")
    return sampler


def tiled_lanes(order, n: int, spp: int, by_sample: bool):
    """The scanline lane (``pixel * spp + sample``) of each lane of the tiled wavefront of
    ``n`` lanes: the pixels in ``order`` (:func:`pixel_order`, a device array), the samples
    of a pixel side by side, or (``by_sample``) in groups of :data:`PACKET` pixels, sample 0
    of the group's pixels, then sample 1, ... (a last group of fewer pixels alike)."""
    pos = dr.arange(mi.UInt32, n)
    spp_u = dr.opaque(mi.UInt32, spp)
    if not by_sample:
        pixel = pos // spp_u
        return dr.gather(mi.UInt32, order, pixel) * spp_u + (pos - pixel * spp_u)
    group = pos // (spp_u * PACKET)
    first = group * PACKET
    size = dr.minimum(dr.opaque(mi.UInt32, n) // spp_u - first, PACKET)
    r = pos - first * spp_u
    sample = r // size
    pixel = dr.gather(mi.UInt32, order, first + (r - sample * size))
    return pixel * spp_u + sample


def packet_u(m, lanes: Optional[Lanes], ray, salt: int):
    """A uniform number in ``[0, 1)`` per lane that all lanes of a packet share, stratified
    over a pixel's samples: ``((sample + r) mod spp + xi) / spp``, ``xi`` a hash of the
    packet and ``r`` (in ``0 .. spp - 1``) of its group of pixels, both of the frame's seed
    and ``salt`` (one stream per use: the streams of a sample are independent); computed on
    the kernels' backend ``m``. None unless ``lanes`` are those of a ``by_sample`` wavefront
    of :func:`render` of ``ray``'s width. A packet's lanes end their walks together where the
    number decides how far they go (stochastic layers)."""
    if lanes is None or lanes.picks is None or dr.width(lanes.lane) != dr.width(ray.o):
        return None
    picks, lane = lanes.picks, lanes.lane
    spp_u, seed = picks
    pos = dr.arange(m.UInt32, dr.width(lane))
    key = m.UInt32(seed) * 32 + 2 * salt
    xi = stable_jitter(m, pos // PACKET, key)
    turn = m.UInt32(stable_jitter(m, pos // (spp_u * PACKET), key + 1) * m.Float(spp_u))
    stratum = (m.UInt32(lane % spp_u) + turn) % spp_u
    u = bridge.to_mi((m.Float(stratum) + xi) / m.Float(spp_u), mi.Float)
    return dr.minimum(u, ONE_BELOW)


def _render_lanes(integrator, scene, sensor, sampler, block, lanes: Lanes, width, spp, border):
    """One sample per lane, put into ``block`` (Mitsuba's ``render_sample``)."""
    film = sensor.film()
    lane = lanes.lane
    # The film's size and offset are opaque inputs (Mitsuba's image block still compiles once
    # for a new size, as with Mitsuba's loop: tests/test_wavefront.py test05).
    width_u = dr.opaque(mi.UInt32, width)
    pixel = lane // dr.opaque(mi.UInt32, spp)
    y = pixel // width_u
    pos = mi.Vector2f(mi.Float(pixel - y * width_u), mi.Float(y))
    crop = mi.ScalarVector2f(film.crop_offset())
    scale = 1.0 / mi.ScalarVector2f(film.crop_size())
    shift, offset, scale = (mi.Vector2f(v) for v in (crop - border, -crop * scale, scale))
    dr.make_opaque(shift, offset, scale)
    pos += shift
    sample_pos = pos + sampler.next_2d()
    adjusted = dr.fma(sample_pos, scale, offset)
    aperture = sampler.next_2d() if sensor.needs_aperture_sample() else mi.Point2f(0.5)
    time = mi.Float(sensor.shutter_open())
    if sensor.shutter_open_time() > 0.0:
        time += sampler.next_1d() * sensor.shutter_open_time()
    ray, weight = sensor.sample_ray_differential(time, 0.0, adjusted, aperture)
    if ray.has_differentials:
        ray.scale_differential(dr.rsqrt(spp))
    L, valid, aovs = integrator.sample(scene, sampler, ray, None, True, lanes=lanes)
    rgb = weight * L
    if mi.has_flag(film.flags(), mi.FilmFlags.Alpha):
        # (a mask, as Mitsuba's loop takes, or the sample's opacity: volume mode's 1 - T)
        alpha = dr.select(valid, 1.0, 0.0) if dr.is_mask_v(valid) else mi.Float(valid)
        values = [rgb.x, rgb.y, rgb.z, alpha, mi.Float(1.0)]
    else:
        values = [rgb.x, rgb.y, rgb.z, mi.Float(1.0)]
    box = film.rfilter().is_box_filter()
    block.put(pos if box else sample_pos, values + list(aovs))
