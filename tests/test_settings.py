"""Numeric settings from the environment: one check for all of them."""

from __future__ import annotations

import pytest

from kbbatch.ray_executor import (
    RAY_NODE_WAIT_ENV,
    RAY_NODE_WAIT_S,
    RayUnavailableError,
    node_wait_s,
)
from kbbatch.settings import env_number


def test_a_number_is_read_and_unset_or_empty_is_the_default(monkeypatch):
    monkeypatch.delenv("KBBATCH_TEST_NUMBER", raising=False)
    assert env_number("KBBATCH_TEST_NUMBER", 7.5) == 7.5
    monkeypatch.setenv("KBBATCH_TEST_NUMBER", "")
    assert env_number("KBBATCH_TEST_NUMBER", 7.5) == 7.5
    monkeypatch.setenv("KBBATCH_TEST_NUMBER", " 12 ")
    assert env_number("KBBATCH_TEST_NUMBER", 7.5) == 12.0
    monkeypatch.setenv("KBBATCH_TEST_NUMBER", "0")
    assert env_number("KBBATCH_TEST_NUMBER", 7.5) == 0.0


@pytest.mark.parametrize("value", ["lots", "inf", "-inf", "nan", "-1", "1e400"])
def test_a_value_that_is_not_a_finite_number_at_least_zero_is_refused_by_name(monkeypatch, value):
    monkeypatch.setenv("KBBATCH_TEST_NUMBER", value)
    with pytest.raises(ValueError, match=f"KBBATCH_TEST_NUMBER={value!r} is not a number"):
        env_number("KBBATCH_TEST_NUMBER", 1.0)


def test_the_ray_node_wait_says_what_the_number_is_for(monkeypatch):
    monkeypatch.delenv(RAY_NODE_WAIT_ENV, raising=False)
    assert node_wait_s() == RAY_NODE_WAIT_S
    monkeypatch.setenv(RAY_NODE_WAIT_ENV, "forever")
    with pytest.raises(RayUnavailableError, match="'forever' is not a number.*seconds to wait"):
        node_wait_s()
