"""Argument checks every stage shares: one way to say "a whole number in this range", with an error that names it.

A boolean is never a number here (``True`` would otherwise pass as 1, and YAML reads ``yes``/``no`` as booleans);
numpy integers are whole numbers like Python ints; a float such as ``3.0`` is one only where the caller allows it.
"""

from __future__ import annotations

import math
import numbers


def _wanted(low: int | None, high: int | None) -> str:
    if low is not None and high is not None:
        return f"an integer in [{low}, {high}]"
    if low == 0:
        return "a non-negative integer"
    if low == 1:
        return "a positive integer"
    if low is not None:
        return f"an integer ≥ {low}"
    if high is not None:
        return f"an integer ≤ {high}"
    return "an integer"


def _as_int(value: object, floats: bool) -> int | None:
    """``value`` as an int when it is a whole number (a float only when ``floats``), else None."""
    if isinstance(value, bool):
        return None
    if isinstance(value, numbers.Integral):
        return int(value)
    if floats and isinstance(value, numbers.Real) and math.isfinite(value) and float(value).is_integer():
        return int(value)
    return None


def whole_number(
    name: str,
    value: object,
    *,
    low: int | None = None,
    high: int | None = None,
    error: type[Exception] = ValueError,
    type_error: type[Exception] | None = None,
    floats: bool = False,
    hint: str = "",
) -> int:
    """``value`` as a Python int, checked to be a whole number within ``[low, high]``.

    Arguments:
        name: what the value is, as the message should name it (a parameter, a config key, a file and its field).
        value: the value to check; an int or a numpy integer, never a bool (nor a numpy bool).
        low: the smallest allowed value, or None for no lower bound.
        high: the largest allowed value, or None for no upper bound.
        error: the exception raised for a value out of range (and for a wrong type unless ``type_error`` is set).
        type_error: the exception raised when ``value`` is not a whole number at all; None: ``error``.
        floats: accept a finite float that is a whole number (``3.0`` → 3), as callers that take counts computed in
            floating point do; ``3.5``, NaN and infinities are refused either way.
        hint: words appended to the expected range in the message, e.g. ``" or 'all'"``.

    Returns:
        ``int(value)``: a plain Python int, so that callers store and serialise no numpy scalar.

    Raises:
        ValueError: ``error``, when ``value`` is out of range, or not a whole number and ``type_error`` is None; the
            message reads ``"{name} must be {range}{hint}, got {value!r}"``.
        Exception: ``type_error``, when it is set and ``value`` is not a whole number.

    Examples:
        >>> whole_number("batch_size", 64, low=1)
        64
        >>> whole_number("replicates", 200.0, low=100, floats=True)
        200
        >>> whole_number("grid", True, low=2, high=32)
        Traceback (most recent call last):
        ...
        ValueError: grid must be an integer in [2, 32], got True
    """
    if low is not None and high is not None and low > high:
        raise ValueError(f"whole_number: low {low} exceeds high {high} for {name}")
    v = _as_int(value, floats)
    if v is None or (low is not None and v < low) or (high is not None and v > high):
        raise (error if v is not None or type_error is None else type_error)(
            f"{name} must be {_wanted(low, high)}{hint}, got {value!r}"
        )
    return v
