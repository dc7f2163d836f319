"""The shared whole-number check: what it accepts, what it refuses, and the error it raises."""

from __future__ import annotations

import math
from fractions import Fraction

import numpy as np
import pytest

from components.core.checks import whole_number


@pytest.mark.parametrize("value", [0, 1, 7, -3, 10**20, np.int64(5), np.uint8(3), np.int32(-2)])
def test_integers_come_back_as_plain_ints_of_the_same_value(value):
    out = whole_number("v", value)
    assert type(out) is int and out == int(value)


@pytest.mark.parametrize("value", [True, False, np.bool_(True), np.bool_(False)])
def test_booleans_are_refused_even_where_floats_are_allowed(value):
    for floats in (False, True):
        with pytest.raises(ValueError, match=r"^flag must be an integer, got "):
            whole_number("flag", value, floats=floats)


@pytest.mark.parametrize("value", [3.0, np.float64(4.0), np.float32(2.0), Fraction(6, 2)])
def test_whole_floats_pass_only_when_the_caller_allows_them(value):
    with pytest.raises(ValueError, match="must be an integer"):
        whole_number("n", value)
    out = whole_number("n", value, floats=True)
    assert type(out) is int and out == value


@pytest.mark.parametrize("value", [3.5, math.nan, math.inf, -math.inf, "3", None, [1], np.array([2])])
def test_non_whole_values_are_refused_with_or_without_floats(value):
    for floats in (False, True):
        with pytest.raises(ValueError, match=r"^n must be an integer, got "):
            whole_number("n", value, floats=floats)


@pytest.mark.parametrize(
    ("low", "high", "inside", "outside", "words"),
    [
        (0, None, [0, 5], [-1], "a non-negative integer"),
        (1, None, [1, 9], [0, -4], "a positive integer"),
        (100, None, [100, 101], [99], "an integer ≥ 100"),
        (None, 10, [10, -50], [11], "an integer ≤ 10"),
        (2, 32, [2, 17, 32], [1, 33], r"an integer in \[2, 32\]"),
    ],
)
def test_bounds_are_inclusive_and_named_in_the_message(low, high, inside, outside, words):
    for v in inside:
        assert whole_number("grid", v, low=low, high=high) == v
    for v in outside:
        with pytest.raises(ValueError, match=rf"^grid must be {words}, got {v}$"):
            whole_number("grid", v, low=low, high=high)


def test_the_range_error_and_the_type_error_can_differ():
    with pytest.raises(TypeError, match="port must be an integer in"):
        whole_number("port", 80.0, low=1, high=65534, type_error=TypeError)
    with pytest.raises(ValueError, match="port must be an integer in"):
        whole_number("port", 0, low=1, high=65534, type_error=TypeError)
    with pytest.raises(TypeError, match="rng must be an integer seed or a torch.Generator, got 'x'"):
        whole_number("rng", "x", error=TypeError, hint=" seed or a torch.Generator")
    with pytest.raises(KeyError):
        whole_number("k", -1, low=0, error=KeyError)


def test_the_hint_follows_the_range_and_the_value_is_shown_as_given():
    with pytest.raises(ValueError, match=r"^evaluate\.images must be a positive integer or 'all', got np\.int64\(0\)$"):
        whole_number("evaluate.images", np.int64(0), low=1, hint=" or 'all'")


def test_an_empty_range_is_a_caller_error():
    with pytest.raises(ValueError, match="low 5 exceeds high 4"):
        whole_number("x", 4, low=5, high=4)
