"""core — the vocabulary every stage shares; imports nothing of the other packages.

- :mod:`~components.core.weather`: the six predicted parameters θ (order, ranges, units), the fixed ones, the prior
  ``Box``, validation, the scaled-logit bijection.
- :mod:`~components.core.config`: ``params.yaml`` (and its profiles) → frozen, validated ``Params``; ``ConfigError``.
- :mod:`~components.core.paths`: ``ProjectPaths``, where each stage reads and writes.
- :mod:`~components.core.seeding`: ``derive_seed``/``rng``: every random draw descends from ``seed``.
- :mod:`~components.core.files`: atomic writes and file hashes.
- :mod:`~components.core.checks`: ``whole_number``, the argument check every stage shares (bool refused, bounds).
- :mod:`~components.core.images`: reading users' image files (the CLI).
- :mod:`~components.core.code`: the project modules a computation imports and a fingerprint of their source.
- :mod:`~components.core.kept`: results kept between runs outside the DVC outputs, keyed by what made them.

Used by every stage and the ``pidc`` CLI (``paths`` by the stages only, ``images`` by the CLI only, ``code`` by
``train`` and ``evaluate``, ``kept`` by ``evaluate``).
"""

__all__ = ["weather", "config", "paths", "seeding", "checks", "files", "images", "code", "kept"]
