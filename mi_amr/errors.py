"""The one exception type for mistakes a user can make (bad file, bad hierarchy, bad parameter)."""


class AMRError(ValueError):
    """A user-facing error: the message names the file, grid or parameter and what was expected.

    Deriving from ``ValueError`` lets callers that already catch ``ValueError`` keep working.
    """
