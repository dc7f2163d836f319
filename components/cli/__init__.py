"""cli — the ``pidc`` command: thin over the other packages, heavy imports only inside commands.

- :mod:`~components.cli.main`: ``main(argv)``, the entry point (``render``, ``weather``, ``config check``).
- :mod:`~components.cli.models`: the command lines of ``characterize``, ``domain``, ``relate`` over registry models;
  each command in :mod:`~components.cli.characterize`, :mod:`~components.cli.domain`, :mod:`~components.cli.relate`,
  what they share (the model, the images read into its inputs, the common options) in :mod:`~components.cli.reading`.
- :mod:`~components.cli.drawsfile`: posterior draws written as CSV or Parquet, atomically.
- :mod:`~components.cli.outputs`: output files checked before any work; one-line messages of failed writes and memory.
- :mod:`~components.cli.errors`: ``CLIError``, a one-line error with exit code 2.

Used by the ``pidc`` CLI only: no pipeline stage imports this package.
"""

__all__ = [
    "main",
    "models",
    "characterize",
    "domain",
    "relate",
    "reading",
    "drawsfile",
    "outputs",
    "errors",
]
