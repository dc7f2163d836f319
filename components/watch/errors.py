"""The error of a watch that cannot be done as asked: a drive or source that cannot be read, an option out of range.

Its message is one line naming the file or the option and what was expected; the ``pidc watch`` command prints it as
its error.
"""

from __future__ import annotations

__all__ = ["WatchError"]


class WatchError(ValueError):
    """A bad drive, source or option: one line naming the file or option and the expected range."""
