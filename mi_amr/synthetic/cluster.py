"""Clustering tagged cells into boxes, as AMR codes do when they build a finer level.

The Berger-Rigoutsos algorithm (Berger & Rigoutsos 1991, used by AMReX and Chombo): take the
bounding box of the tagged cells; if it is efficient enough (tagged / all cells) and small
enough, keep it; otherwise cut it at a hole in the tag signature (the count of tags per plane),
else at the strongest inflection of the signature, else in the middle, and recurse.

Boxes are integer, half-open ``(lo, hi)`` in the index space of the tag array.
"""

from __future__ import annotations

import numpy as np


def berger_rigoutsos(tags: np.ndarray, *, efficiency: float = 0.7, max_size: int = 32,
                     min_size: int = 2) -> list:
    """Cover the True cells of the 3-D boolean array ``tags`` with boxes.

    Every tagged cell ends up in exactly one box, boxes do not overlap, no side exceeds
    ``max_size`` and a box whose tagged fraction is below ``efficiency`` is cut further unless
    its sides are below ``2 * min_size``. Returns a list of ``(lo, hi)`` int tuples.
    """
    tags = np.asarray(tags, dtype=bool)
    boxes = []
    todo = [(np.zeros(3, dtype=np.int64), np.array(tags.shape, dtype=np.int64))]
    while todo:
        lo, hi = todo.pop()
        sub = tags[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]]
        if not sub.any():
            continue
        # Shrink to the bounding box of the tags.
        sig = [sub.any(axis=tuple(a for a in range(3) if a != ax)) for ax in range(3)]
        first = np.array([np.argmax(s) for s in sig])
        last = np.array([len(s) - np.argmax(s[::-1]) for s in sig])
        lo, hi = lo + first, lo + last
        sub = sub[first[0]:last[0], first[1]:last[1], first[2]:last[2]]
        size = hi - lo
        eff = sub.sum() / np.prod(size)
        if (eff >= efficiency or np.all(size < 2 * min_size)) and np.all(size <= max_size):
            boxes.append((tuple(int(x) for x in lo), tuple(int(x) for x in hi)))
            continue
        axis, cut = _choose_cut(sub, size, min_size, max_size)
        left_hi = hi.copy()
        left_hi[axis] = lo[axis] + cut
        right_lo = lo.copy()
        right_lo[axis] = lo[axis] + cut
        todo.append((lo, left_hi))
        todo.append((right_lo, hi))
    return boxes


def _choose_cut(sub, size, min_size, max_size):
    """Axis and offset (within the box) of the next cut."""
    counts = [sub.sum(axis=tuple(a for a in range(3) if a != ax)) for ax in range(3)]
    # 1. A hole: an empty plane strictly inside, the one nearest the middle of the longest axis.
    best = None
    for ax in np.argsort(-size):
        holes = np.flatnonzero(counts[ax][1:-1] == 0) + 1
        if len(holes):
            cut = holes[np.argmin(np.abs(holes - size[ax] / 2))]
            return int(ax), int(cut)
    # 2. The strongest inflection of the signature (sign change of its second difference),
    #    keeping both sides at least min_size long.
    for ax in np.argsort(-size):
        s = counts[ax].astype(np.int64)
        if len(s) < 2 * min_size + 2:
            continue
        lap = s[:-2] - 2 * s[1:-1] + s[2:]
        change = np.flatnonzero(np.sign(lap[:-1]) != np.sign(lap[1:]))
        cuts = change + 2
        ok = (cuts >= min_size) & (cuts <= len(s) - min_size)
        if ok.any():
            strength = np.abs(lap[change] - lap[change + 1])[ok]
            cand = (int(ax), int(cuts[ok][np.argmax(strength)]), int(strength.max()))
            if best is None or cand[2] > best[2]:
                best = cand
    if best is not None:
        return best[0], best[1]
    # 3. The middle of the longest axis.
    ax = int(np.argmax(size))
    return ax, int(size[ax] // 2)
