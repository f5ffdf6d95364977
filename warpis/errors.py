"""The one exception type that the command line turns into a one-line message."""

from __future__ import annotations


class WarpisError(Exception):
    """Bad input: a file, a scene, an estimator spec or an option that cannot be used.

    The message is one line that names the offending file or option and the problem;
    the command line prints it and exits with status 2, without a traceback.
    """


def fail(where: object, problem: str) -> WarpisError:
    """Build a :class:`WarpisError` reading ``"<where>: <problem>"``."""
    return WarpisError(f"{where}: {problem}")
