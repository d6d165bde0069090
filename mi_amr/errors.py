"""The one exception type for mistakes a user can make (bad file, bad hierarchy, bad parameter),
:func:`shown`, how a value is written in its messages, :func:`did_you_mean`, how a misspelt
name is answered, and :func:`print_traceback`, how a
long-lived thread reports a bug and goes on."""

import traceback


# Where a user keeps NaN and Inf values as missing data: the end of the message that refuses
# a file holding them.
ALLOW_NONFINITE_HOW = ("allow_nonfinite=True (mi_amr.load, from_grids), the scene parameter "
                       "allow_nonfinite, or --allow-nonfinite on the command line")


class AMRError(ValueError):
    """A user-facing error: the message names the file, grid or parameter and what was expected.

    Deriving from ``ValueError`` lets callers that already catch ``ValueError`` keep working.
    """


def did_you_mean(name: str, known) -> str:
    """`` (did you mean 'x'?)`` naming the entry of ``known`` closest to the misspelt ``name``,
    or "" where none is close: the end of a message that refuses a name."""
    import difflib

    close = difflib.get_close_matches(name, list(known), n=1)
    return f" (did you mean '{close[0]}'?)" if close else ""


def shown(value) -> str:
    """``repr(value)`` with NumPy scalars and arrays, also inside tuples and lists, written as
    plain Python numbers and lists: ``(0.5, 2.25)``, not ``(np.float64(0.5), np.float64(2.25))``.
    (Duck-typed, so this module needs no NumPy.)"""
    return repr(_plain(value))


def _plain(value):
    if type(value) in (tuple, list):
        return type(value)(_plain(v) for v in value)
    if type(value).__module__ == "numpy" and callable(getattr(value, "tolist", None)):
        return value.tolist()
    return value


def print_traceback() -> None:
    """The exception being handled, printed on stderr, unless stderr cannot be written (a full
    disk, a file size limit, a closed stream): a thread that answers requests (the viewer's)
    must go on answering either way."""
    try:
        traceback.print_exc()
    except (OSError, ValueError):       # ValueError: stderr closed
        pass
