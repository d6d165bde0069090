"""Which fast paths an ``amr_iso`` integrator takes: :class:`Twins`, fixed when it is built.

Every fast path of the integrator has a slow, obvious twin that renders the same image (bit for
bit, or up to Monte Carlo noise where the twin draws other numbers). Users always get the fast
paths (``Twins()``); tests build a reference integrator with a twin switched on,
:func:`with_twins`, and compare. No scene parameter reaches these.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import mitsuba as mi

from mi_amr.kernels.config import SEEK_STEPS


@dataclass(frozen=True)
class Twins:
    """True: the fast path (the default, what users render with); False: its slow twin.

    ``layer_fast_paths``: a layer's search resumes where the last one ended, and shadow rays of
    the exact method count crossings in one walk (False: every layer searched from scratch and
    composited one by one).
    ``clip_to_active``: exact/basis isosurface rays are clipped to the isovalues' active box
    (False: they walk the whole volume).
    ``start_tables``: leaf searches start from the active box's start table (False: from the
    kd-tree's root).
    ``packet_picks``: stochastic layers at 2 or more spp share their numbers by SIMD packet
    (False: a number per lane).
    ``wavefront_loop``: frames are rendered by :func:`mi_amr.plugin.wavefront.render` where it
    applies (False: always by Mitsuba's own ``SamplingIntegrator.render``).
    ``tile_order``: the wavefront's lanes go through the film in tiles (False: in scanlines,
    as Mitsuba's own loop).
    ``two_levels``: a turn of the leaf search goes down through a non-empty inner node before
    its full step (False: one level a turn; reaches the kernels as
    :attr:`~mi_amr.kernels.config.SearchPlan.two_levels`).
    ``seek_steps``: steps of a leaf search per step of the march that waits for it
    (:attr:`~mi_amr.kernels.config.SearchPlan.steps`, :data:`~mi_amr.kernels.config.SEEK_STEPS`; any number, or None for the whole search at
    once, finds the same)."""

    layer_fast_paths: bool = True
    clip_to_active: bool = True
    start_tables: bool = True
    packet_picks: bool = True
    wavefront_loop: bool = True
    tile_order: bool = True
    two_levels: bool = True
    seek_steps: Optional[int] = SEEK_STEPS


FAST = Twins()


def with_twins(integ, twins: Twins):
    """Another ``amr_iso`` integrator of the variant of ``integ``, taking the fast paths and
    slow twins ``twins`` names, for the same scene: it shares the parameters, the prepared
    volume, the frame inputs (what ``mi.traverse`` changes on ``integ`` holds for it too) and
    the transform of ``integ``. Render with it by ``mi.render(scene, integrator=...)``."""
    return type(integ)(mi.Properties("amr_iso"), twins=twins, like=integ)
