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


def histogram_figure(path, field: str, output, *, bins: int = 256,
                     overwrite: bool = False) -> Path:
    """Write the histogram of ``field`` of the file ``path`` to ``output`` (PNG, atomically)."""
    output = check_output(output, suffixes=(".png",), overwrite=overwrite, make_folders=True)
    from mi_amr.core.derive import DERIVED_FIELDS, derive
    from mi_amr.kernels.prepared import fields_to_read
    from mi_amr.readers import available_fields, load

    volume = load(path, fields=fields_to_read(field, None, available_fields(path)))
    if field not in volume.field_names and field in DERIVED_FIELDS:
        volume = derive(volume, field)
    v, g = value_and_gradient(volume, field)
    if len(v) == 0:
        raise AMRError(f"{path}: field '{field}' has no finite leaf cells")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm

    fig, ax = plt.subplots(figsize=(6.4, 4.8), dpi=120)
    counts, xe, ye, image = ax.hist2d(v, g, bins=bins, norm=LogNorm(), cmap="magma")
    fig.colorbar(image, ax=ax, label="leaf cells (log)")
    ax.set_xlabel(f"{field}")
    ax.set_ylabel(f"|grad {field}| (per world unit)")
    ax.set_title(f"{Path(path).name}: {len(v):,} leaf cells")
    fig.tight_layout()
    with replacing(output) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
    return output
