"""``python -m mi_amr info FILE [--fields ...]``: the file's summary (levels, grids, cells,
bounds) and, for each field, its range, percentiles, per-level leaf cells and ranges, and the
isovalues worth trying first (:mod:`mi_amr.core.suggest`). Derived fields (``q_criterion``,
``speed``, ``vorticity`` / ``vorticity_magnitude``) can be named when the velocity is stored.
"""

from __future__ import annotations


def info_text(path, fields=None, *, allow_nonfinite: bool = False) -> str:
    """What ``info`` prints; ``allow_nonfinite``: NaN and Inf values are missing data, as
    :func:`mi_amr.load` takes it."""
    from mi_amr.core.suggest import field_stats
    from mi_amr.plugin.datafields import load_with_fields

    volume, names = load_with_fields(path, fields, allow_nonfinite=allow_nonfinite)
    parts = [volume.summary(), ""]
    parts += [field_stats(volume, name).text() for name in names]
    return "\n".join(parts)
