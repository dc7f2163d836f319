"""core — the vocabulary every stage shares; imports nothing of the other packages.

- :mod:`~components.core.weather`: the six predicted parameters θ (order, ranges, units), the fixed ones, the prior
  ``Box``, validation, the scaled-logit bijection.
- :mod:`~components.core.config`: ``params.yaml`` (and its profiles) → frozen, validated ``Params``; ``ConfigError``.
- :mod:`~components.core.paths`: ``ProjectPaths``, where each stage reads and writes.
- :mod:`~components.core.seeding`: ``derive_seed``/``rng``: every random draw descends from ``seed``.
- :mod:`~components.core.files`: atomic writes and file hashes.
- :mod:`~components.core.images`: reading users' image files (the CLI).

Used by every stage and the ``pidc`` CLI (``paths`` by the stages only, ``images`` by the CLI only).
"""

__all__ = ["weather", "config", "paths", "seeding", "files", "images"]
