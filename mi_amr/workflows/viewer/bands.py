"""The transfer-function editor's requests (volume mode): one band moved, widened, raised or
recoloured, as a new :class:`~mi_amr.workflows.viewer.state.ViewState`; every one is an
``mi.traverse`` update of ``integrator.isovalue``, ``band_width``, ``band_offsets``,
``band_peak`` or ``iso_color`` (nothing compiles).

``{"op": "band", "index": I, "center": V, "width": W, "peak": P, "color": C}``: any of the four
values, ``center`` and ``width`` in field units, ``peak`` the band's opacity scale (clamped to 1
per finest-cell step, see :mod:`mi_amr.kernels.band`), ``color`` ``#rrggbb``. A new width makes
the band's support ``+- 2 W`` (as the band width control does). Bands may not overlap (each value
holds the opacity of one band at most); a change that would make them overlap is refused with a
message naming the two bands.
"""

from __future__ import annotations

from mi_amr.errors import AMRError
from mi_amr.workflows.viewer.controls import color, number

MAX_PEAK = 1e3


def change(state, msg: dict, ctx):
    """The state after the band request ``msg`` (an :class:`AMRError` says why it is
    refused)."""
    if state.mode != "volume":
        raise AMRError("band: the transfer-function editor works in volume mode (Mode: volume)")
    k = len(state.isovalues)
    i = msg.get("index", 0)
    if not isinstance(i, int) or isinstance(i, bool) or not 0 <= i < k:
        raise AMRError(f"band: number {i!r} does not exist (there are {k})")
    lo, hi = ctx.value_range
    changes = {}
    if "center" in msg:
        v = number(msg["center"], "band centre", lo, hi)
        changes["isovalues"] = _put(state.isovalues, i, v)
    if "width" in msg:
        w = number(msg["width"], "band width", 0.0, max(hi - lo, 1e-30))
        if w <= 0:
            raise AMRError("band width: must be above 0")
        changes["band_width"] = _put(state.band_width, i, w)
        changes["band_offsets"] = _put(state.band_offsets, i, (-2.0 * w, 2.0 * w))
    if "peak" in msg:
        p = number(msg["peak"], "band peak", 0.0, MAX_PEAK)
        if p <= 0:
            raise AMRError("band peak: must be above 0")
        changes["band_peak"] = _put(state.band_peak, i, p)
    if "color" in msg:
        changes["iso_colors"] = _put(state.iso_colors, i, color(msg["color"], "band colour"))
    if not changes:
        raise AMRError("band: give center, width, peak or color")
    new = state.replace(**changes)
    check_disjoint(new)
    return new


def _put(values: tuple, i: int, v) -> tuple:
    return values[:i] + (v,) + values[i + 1:]


def spans(state) -> list:
    """``(lo, hi)`` of each band's support (field units), in the isovalues' order."""
    return [(iso + a, iso + b) for iso, (a, b) in zip(state.isovalues, state.band_offsets)]


def check_disjoint(state) -> None:
    """An :class:`AMRError` when two bands' supports overlap (the integrator refuses them)."""
    order = sorted(range(len(state.isovalues)), key=lambda j: spans(state)[j][0])
    s = spans(state)
    for a, b in zip(order, order[1:]):
        if s[b][0] < s[a][1]:
            raise AMRError(f"band: bands {a + 1} ([{s[a][0]:g}, {s[a][1]:g}]) and {b + 1} "
                           f"([{s[b][0]:g}, {s[b][1]:g}]) would overlap; move or narrow one")
