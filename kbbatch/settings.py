"""Numbers read from the environment, checked one way for every setting."""

from __future__ import annotations

import os


def env_number(name: str, default: float) -> float:
    """$name as a finite number >= 0, or default when it is unset or empty.

    A bad value raises ValueError naming the variable and what it holds, so each command can
    refuse it at start instead of failing every photo later (inf once did: OverflowError).
    """
    text = os.environ.get(name)
    if not text:
        return default
    try:
        number = float(text)
    except ValueError:
        number = float("nan")
    if not 0 <= number < float("inf"):
        raise ValueError(f"{name}={text!r} is not a number >= 0")
    return number
