"""What every ``pidc`` command shares: the user-error type (its own module so that ``python -m components.cli.main`` and
the command modules raise and catch the same class).

Used by the ``pidc`` CLI only.
"""

from __future__ import annotations

__all__ = ["CLIError"]


class CLIError(Exception):
    """A user error: printed as one line, exit status 2."""
