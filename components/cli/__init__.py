"""cli — the ``pidc`` command: thin over the other packages, heavy imports only inside commands.

- :mod:`~components.cli.main`: ``main(argv)``, the entry point (``render``, ``weather``, ``config check``).
- :mod:`~components.cli.models`: ``characterize``, ``domain``, ``relate`` over registry models.
- :mod:`~components.cli.drawsfile`: posterior draws written as CSV or Parquet, atomically.
- :mod:`~components.cli.errors`: ``CLIError``, a one-line error with exit code 2.

Used by the ``pidc`` CLI only: no pipeline stage imports this package.
"""

__all__ = ["main", "models", "drawsfile", "errors"]
