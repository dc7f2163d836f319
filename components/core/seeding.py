"""Deterministic random streams: every draw descends from the root seed in ``params.yaml``.

A stream is named by the root seed and a path of keys (strings or non-negative integers), e.g.
``rng(seed, "data", "train", 17)``; the same path always gives the same stream and different paths
give independent streams (``numpy.random.SeedSequence`` entropy mixing). No global RNG state.

Used by every stage and the ``pidc`` CLI.
"""

from __future__ import annotations

import zlib

import numpy as np

from components.core.checks import whole_number

__all__ = ["seed_sequence", "rng", "derive_seed"]


def _key(k: str | int) -> int:
    if isinstance(k, str):
        return zlib.crc32(k.encode("utf-8"))
    return whole_number("a seed key", k, low=0, type_error=TypeError, hint=" or a string")


def seed_sequence(seed: int, *keys: str | int) -> np.random.SeedSequence:
    """The ``SeedSequence`` of the stream named ``(seed, *keys)``."""
    if seed is None:
        raise ValueError("a seed is required (set `seed` in params.yaml)")
    return np.random.SeedSequence([_key(seed), *(_key(k) for k in keys)])


def rng(seed: int, *keys: str | int) -> np.random.Generator:
    """A PCG64 generator for the stream named ``(seed, *keys)``."""
    return np.random.Generator(np.random.PCG64(seed_sequence(seed, *keys)))


def derive_seed(seed: int, *keys: str | int) -> int:
    """A 63-bit integer seed for the stream named ``(seed, *keys)`` (e.g. a scene seed)."""
    return int(seed_sequence(seed, *keys).generate_state(2, np.uint64)[0] >> np.uint64(1))
