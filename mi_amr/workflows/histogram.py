"""``python -m mi_amr histogram FILE --field F -o hist.png``: the 2D histogram of a field's value
against its gradient magnitude over the leaf cells (log counts), the picture a person designs a
2D transfer function on (the lecture's value / |grad f| plane: material boundaries are the arcs
of high gradient, smooth regions that merely pass a value sit near the axis).

Gradients are central differences inside each grid (one-sided at its faces), per world unit;
only leaf cells (not covered by a finer level) with finite values are counted, each once.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mi_amr.core.atomic import check_output, replacing
from mi_amr.errors import AMRError

# Bins per axis at most: the figure is 768 x 576 pixels, so finer bins show nothing more, and
# the counts take bins^2 numbers.
MAX_BINS = 4096


def value_and_gradient(volume, field: str):
    """``(values, |grad|)`` of ``field`` over the volume's finite leaf cells (float64)."""
    if field not in volume.field_names:
        raise AMRError(f"{volume.source_prefix()}unknown field '{field}'; the volume holds "
                       f"{list(volume.field_names)}")
    values, grads = [], []
    for gi, g in enumerate(volume.grids):
        f = np.asarray(g.fields[field], dtype=np.float64)
        parts = [np.gradient(f, g.spacing[a], axis=a) if f.shape[a] > 1 else np.zeros_like(f)
                 for a in range(3)]
        mag = np.sqrt(sum(p * p for p in parts))
        keep = volume.leaf_mask(gi) & np.isfinite(f) & np.isfinite(mag)
        values.append(f[keep])
        grads.append(mag[keep])
    return np.concatenate(values), np.concatenate(grads)


DECADES = 3.0        # auto: a log axis for values spanning at least this many decades


def value_axis(values, scale: str = "auto"):
    """``(kind, linthresh)`` of the value axis: ``linear``, ``log`` (all values > 0) or
    ``symlog`` (linear within +-``linthresh``, logarithmic beyond). ``scale`` ``auto`` picks
    a log axis for values spanning :data:`DECADES` decades or more (of their magnitude, where
    they reach or cross 0), ``log`` a log or symlog axis, ``linear`` a linear one."""
    if scale not in ("auto", "linear", "log"):
        raise AMRError(f"value axis must be auto, linear or log, got {scale!r}")
    mag = np.abs(values[values != 0])
    if scale == "linear" or mag.size == 0:
        return "linear", None
    small = float(np.percentile(mag, 1))
    spans = np.log10(mag.max() / small) >= DECADES if small > 0 else False
    if scale == "auto" and not spans:
        return "linear", None
    if values.min() > 0:
        return "log", None
    return "symlog", small


def _value_edges(values, bins: int, kind: str, linthresh):
    """``bins + 1`` bin edges over the values, evenly spaced on the axis ``kind``."""
    lo, hi = float(values.min()), float(values.max())
    if kind == "linear" or lo == hi:
        return bins
    from matplotlib.scale import LogTransform, SymmetricalLogTransform

    tr = LogTransform(10) if kind == "log" else SymmetricalLogTransform(10, linthresh, 1.0)
    ends = tr.transform(np.array([lo, hi]))
    edges = tr.inverted().transform(np.linspace(ends[0], ends[1], bins + 1))
    edges[0], edges[-1] = lo, hi        # (the round trip may move the ends by an ulp)
    return edges


def histogram_figure(path, field: str, output, *, bins: int = 256, overwrite: bool = False,
                     value_scale: str = "auto", allow_nonfinite: bool = False) -> Path:
    """Write the histogram of ``field`` of the file ``path`` to ``output`` (PNG, atomically),
    ``bins`` bins (2 to :data:`MAX_BINS`) on each axis; ``value_scale`` as :func:`value_axis`
    takes it; ``allow_nonfinite``: NaN and Inf values are missing data (left out), as
    :func:`mi_amr.load` takes it."""
    if not 2 <= bins <= MAX_BINS:
        raise AMRError(f"--bins must be between 2 and {MAX_BINS}, got {bins}")
    output = check_output(output, suffixes=(".png",), overwrite=overwrite, make_folders=True)
    import drjit as dr

    from mi_amr.core.derive import DERIVED_FIELDS
    from mi_amr.kernels.derive import derive
    from mi_amr.kernels.prepared import fields_to_read
    from mi_amr.readers import available_fields, load

    volume = load(path, fields=fields_to_read(field, None, available_fields(path), path),
                  allow_nonfinite=allow_nonfinite)
    if field not in volume.field_names and field in DERIVED_FIELDS:
        volume = derive(volume, field, m=dr.llvm.ad)        # (the scene load's kernels)
    v, g = value_and_gradient(volume, field)
    if len(v) == 0:
        raise AMRError(f"{path}: field '{field}' has no finite leaf cells")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm

    kind, linthresh = value_axis(v, value_scale)
    gkind, gthresh = value_axis(g, "auto")        # |grad| spans decades as often
    fig, ax = plt.subplots(figsize=(6.4, 4.8), dpi=120)
    counts, xe, ye, image = ax.hist2d(v, g, bins=[_value_edges(v, bins, kind, linthresh),
                                                  _value_edges(g, bins, gkind, gthresh)],
                                      norm=LogNorm(), cmap="magma")
    for set_scale, k, t in ((ax.set_xscale, kind, linthresh), (ax.set_yscale, gkind, gthresh)):
        if k != "linear":
            set_scale(k, **({"linthresh": t} if k == "symlog" else {}))
    fig.colorbar(image, ax=ax, label="leaf cells (log)")
    ax.set_xlabel(f"{field}" + ("" if kind == "linear" else f" ({kind} axis)"))
    ax.set_ylabel(f"|grad {field}| (per world unit" + ("" if gkind == "linear" else
                                                        f", {gkind} axis") + ")")
    ax.set_title(f"{Path(path).name}: {len(v):,} leaf cells")
    fig.tight_layout()
    with replacing(output) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
    return output
