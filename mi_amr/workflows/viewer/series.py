"""Time steps in the viewer: one scene and a list of data files substituted as its volume's
file, as ``python -m mi_amr movie --files`` substitutes them (``view SCENE --files 'run/plt*'``).

The files are checked once, at start: every one holds the same fields (a series of one
simulation), among them what the scene shows. A step is a new ``data_file`` in the view's
state, an ``integrator.load_volume`` in the render thread: everything else (camera, isovalues,
colours, colour range) stays, and no kernel compiles. While step ``k`` is shown, a background
thread (:class:`~mi_amr.workflows.prefetch.Prefetcher`) prepares step ``k + 1`` (reads it, builds its kd-tree and device
arrays into the integrator's :class:`~mi_amr.kernels.prepared.Preparations`), so that stepping forward
costs a frame, not a load.
"""

from __future__ import annotations

from pathlib import Path

from mi_amr.errors import AMRError


def expand_series(spec) -> list:
    """The data files of ``--files`` (globs, comma lists or paths; see
    :func:`mi_amr.workflows.movie.spec.expand_files`) as absolute paths in natural order; scene
    files (``.xml``) among them are left out (the page may open them, they are no steps)."""
    from mi_amr.workflows.movie.spec import expand_files

    if not spec:
        return []
    return [str(Path(f).resolve()) for f in expand_files(list(spec))
            if Path(f).suffix.lower() != ".xml"]


def check_series(files, field: str, color_field) -> None:
    """Every file of the series holds the fields of the first one, and those hold what the
    scene shows (stored, or what it is derived from); one :class:`AMRError` naming the file
    otherwise."""
    from mi_amr.kernels.prepared import fields_to_read
    from mi_amr.readers import available_fields

    if not files:
        return
    first = list(available_fields(files[0]))
    for f in files[1:]:
        have = list(available_fields(f))
        if sorted(have) != sorted(first):
            raise AMRError(f"--files: {f} holds the fields {have}, but {files[0]} holds "
                           f"{first}; the steps of a time series must hold the same fields")
    need = fields_to_read(field, color_field, first, files[0])
    missing = [n for n in need if n not in first]
    if missing:
        raise AMRError(f"--files: {files[0]} has no field(s) {missing} that the scene shows; "
                       f"the series holds {first}")


def next_step(files, current) -> str | None:
    """The file after ``current`` in the series (the first after the last: play loops); None
    when ``current`` is not a step or the series has one file."""
    if len(files) < 2 or current not in files:
        return None
    return files[(files.index(current) + 1) % len(files)]


def step(hub, client, msg: dict) -> None:
    """The page's ``{"op": "step", "index": K}``: show time step ``K`` (from 0)."""
    files = hub.series
    if not files:
        raise AMRError("step: this view has no time series (start it with --files "
                       "'run/plt*')")
    i = msg.get("index")
    if not isinstance(i, int) or isinstance(i, bool) or not 0 <= i < len(files):
        raise AMRError(f"step: {i!r} is not a time step; there are {len(files)} (0 to "
                       f"{len(files) - 1})")
    hub._change(hub.state.replace(data_file=files[i]))
