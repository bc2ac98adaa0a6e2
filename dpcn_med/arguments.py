"""Checks of values passed through the Python API (settings dataclasses, keyword arguments), one message format.

Python does not check annotations, and numpy scalars, ``bool`` (an ``int``) and NaN pass most comparisons silently;
each check names the argument, shows the value and its type, and says what is expected:
``"histogram_bins is 3 (int); expected an integer >= 8"``.
"""

from __future__ import annotations

import math
import numbers
import reprlib
from collections.abc import Sequence
from typing import Any

import numpy as np

from dpcn_med.errors import InputError


def shown(value: Any) -> str:
    """A value and its type for a message, shortened (an array's repr can run to megabytes)."""
    return f"{reprlib.repr(value)} ({type(value).__name__})"


def _number(value: float) -> str:
    """A bound as written: ``4294967295``, not ``4.29497e+09``."""
    if isinstance(value, int):
        return str(value)
    return str(int(value)) if float(value).is_integer() and abs(value) < 1e16 else repr(float(value))


def _range(low: float | None, high: float | None, low_open: bool, high_open: bool) -> str:
    parts = []
    if low is not None:
        parts.append(f"{'>' if low_open else '>='} {_number(low)}")
    if high is not None:
        parts.append(f"{'<' if high_open else '<='} {_number(high)}")
    return " and ".join(parts)


def check_integer(name: str, value: Any, *, minimum: int | None = None, maximum: int | None = None) -> int:
    """``value`` as an ``int`` (numpy integers accepted; ``bool`` and integral floats refused) within the bounds."""
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        bounds = _range(minimum, maximum, False, False)
        raise InputError(f"{name} is {shown(value)}; expected an integer{' ' + bounds if bounds else ''}")
    value = int(value)
    if (minimum is not None and value < minimum) or (maximum is not None and value > maximum):
        raise InputError(f"{name} is {value}; expected an integer {_range(minimum, maximum, False, False)}")
    return value


def check_real(name: str, value: Any, *, minimum: float | None = None, maximum: float | None = None,
               above: bool = False, below: bool = False, note: str = "") -> float:
    """``value`` as a finite ``float`` (ints and numpy scalars accepted, ``bool`` refused) within the bounds.

    ``above`` / ``below`` make the minimum / maximum exclusive; ``note`` ends the message.
    """
    bounds = _range(minimum, maximum, above, below)
    expected = f"a finite number{' ' + bounds if bounds else ''}{note}"
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise InputError(f"{name} is {shown(value)}; expected {expected}")
    try:
        value = float(value)
    except OverflowError:  # an int beyond 1e308
        raise InputError(f"{name} is {shown(value)}; expected {expected}") from None
    too_low = minimum is not None and (value <= minimum if above else value < minimum)
    too_high = maximum is not None and (value >= maximum if below else value > maximum)
    if not math.isfinite(value) or too_low or too_high:
        raise InputError(f"{name} is {value!r}; expected {expected}")
    return value


def check_flag(name: str, value: Any) -> bool:
    """``value`` if it is a ``bool`` (numpy's too); a string such as ``"false"`` is truthy, so it is refused."""
    if not isinstance(value, (bool, np.bool_)):
        raise InputError(f"{name} is {shown(value)}; expected True or False")
    return bool(value)


def check_sequence(name: str, value: Any, *, length: int | None = None, nonempty: bool = True) -> tuple[Any, ...]:
    """``value`` as a tuple (a list, tuple or 1-D array; a string or a mapping is refused), of ``length`` items if
    given."""
    if isinstance(value, np.ndarray) and value.ndim == 1:
        value = value.tolist()
    if isinstance(value, (str, bytes, bytearray)) or not isinstance(value, Sequence):
        raise InputError(f"{name} is {shown(value)}; expected a tuple"
                         f"{f' of {length} values' if length is not None else ''}")
    items = tuple(value)
    if length is not None and len(items) != length:
        raise InputError(f"{name} is {value!r}: {len(items)} values; expected {length}")
    if nonempty and not items:
        raise InputError(f"{name} is empty; expected at least one value")
    return items


def check_pair(name: str, value: Any, *, minimum: float | None = None, maximum: float | None = None,
               above: bool = False, equal: bool = False, note: str = "") -> tuple[float, float]:
    """``value`` as ``(low, high)``: two finite numbers, ``low < high`` (``equal``: ``low <= high``, as a range to
    draw from may hold one value), within the bounds (``above``: the minimum exclusive); ``note`` ends the message,
    e.g. what the numbers are."""
    low, high = (check_real(f"{name}[{index}]", item)
                 for index, item in enumerate(check_sequence(name, value, length=2)))
    too_low = minimum is not None and (low <= minimum if above else low < minimum)
    too_high = maximum is not None and high > maximum
    if too_low or too_high or (low > high if equal else low >= high):
        start = "" if minimum is None else f"{_number(minimum)} {'<' if above else '<='} "
        end = "" if maximum is None else f" <= {_number(maximum)}"
        order = "<=" if equal else "<"
        raise InputError(f"{name} is {(low, high)!r}; expected (low, high) with {start}low {order} high{end}{note}")
    return low, high
