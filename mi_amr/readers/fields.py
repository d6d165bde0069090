"""The fields a reader is asked for, checked against the ones its file holds (every reader
answers a bad request the same way)."""

from __future__ import annotations

from mi_amr.errors import AMRError


def requested(source, fields, known, listed=None, holder: str = "file") -> list:
    """The requested field names, in order, each once: all of ``known`` for ``None``, one
    name, or a list of names. ``listed`` is what an error message says the file holds
    (default ``known``); ``source`` names the file. Raises :class:`~mi_amr.AMRError` for a
    request that is not names, is empty, or names a field the file lacks."""
    listed = list(known) if listed is None else listed
    if fields is None:
        return list(known)
    if isinstance(fields, str):
        fields = [fields]
    try:
        wanted = list(dict.fromkeys(fields))
    except TypeError:
        raise AMRError(f"{source}: fields must be a field name or a list of names, got "
                       f"{fields!r}") from None
    if not wanted:
        raise AMRError(f"{source}: no fields requested; the {holder} holds {listed}")
    unknown = [n for n in wanted if n not in known]
    if unknown:
        raise AMRError(f"{source}: unknown field(s) {unknown}; the {holder} holds {listed}")
    return wanted
