"""The fields a data-file scene or ``info`` names, read from the file: stored ones as they are,
derived ones (``q_criterion``, ``speed``, ``vorticity`` / ``vorticity_magnitude``) from the
velocity they need, with one error naming the file, the missing names and what it holds.
"""

from __future__ import annotations

from mi_amr.errors import AMRError

ALIASES = {"vorticity": "vorticity_magnitude"}


def load_with_fields(path, fields=None, *, derive_them: bool = True,
                     allow_nonfinite: bool = False):
    """``(volume, names)``: ``path`` read with ``fields`` (stored or derived; default: every
    stored field) and, with ``derive_them``, the derived ones computed (by the Dr.Jit kernels
    that a scene's load derives them with, :func:`mi_amr.kernels.derive.derive`: the host's
    numbers, bit for bit); ``names`` in the order asked, aliases resolved.
    ``allow_nonfinite``: as :func:`mi_amr.load` takes it."""
    import drjit as dr

    from mi_amr.core.derive import DERIVED_FIELDS, VELOCITY_NAMES
    from mi_amr.kernels.derive import derive
    from mi_amr.kernels.prepared import fields_to_read
    from mi_amr.readers import available_fields, load

    stored = available_fields(path)
    names = list(dict.fromkeys(ALIASES.get(f, f) if f not in stored else f
                               for f in (fields or stored)))
    velocity = any(all(n in stored for n in v) for v in VELOCITY_NAMES)
    unknown = [f for f in names if f not in stored and not (f in DERIVED_FIELDS and velocity)]
    if unknown:
        derived = f"; from its velocity: {', '.join(DERIVED_FIELDS)}" if velocity else ""
        if not velocity and any(u in DERIVED_FIELDS for u in unknown):
            derived = (f"; {', '.join(u for u in unknown if u in DERIVED_FIELDS)} would be "
                       f"derived from three velocity components, which it lacks (named "
                       f"{'/'.join(VELOCITY_NAMES[0])}, {'/'.join(VELOCITY_NAMES[1])}, ...)")
        raise AMRError(f"{path}: no field(s) {', '.join(repr(u) for u in unknown)}; it holds "
                       f"{', '.join(stored)}{derived}")
    read = list(dict.fromkeys(n for f in names for n in fields_to_read(f, None, stored, path)))
    volume = load(path, fields=read, allow_nonfinite=allow_nonfinite)
    derived = [f for f in names if f not in volume.field_names]
    if derived and derive_them:
        volume = derive(volume, *derived, m=dr.llvm.ad)
    return volume, names
