"""Checks of API arguments: what each accepts (numpy scalars included) and the one message format of a refusal."""

from __future__ import annotations

import math

import numpy as np
import pytest

from dpcn_med.arguments import check_flag, check_integer, check_pair, check_real, check_sequence
from dpcn_med.errors import InputError


class TestCheckInteger:
    @pytest.mark.parametrize("value", [3, np.int64(3), np.uint8(3), np.int32(3)])
    def test_accepts_integers_as_int(self, value):
        checked = check_integer("steps", value, minimum=1, maximum=3)
        assert checked == 3 and type(checked) is int

    @pytest.mark.parametrize(("value", "message"), [
        (True, r"steps is True \(bool\); expected an integer >= 1"),
        (np.bool_(True), r"steps is np\.True_ \(bool\); expected an integer >= 1"),
        (2.0, r"steps is 2\.0 \(float\); expected an integer >= 1"),
        ("2", r"steps is '2' \(str\); expected an integer >= 1"),
        (None, r"steps is None \(NoneType\); expected an integer >= 1"),
        (0, r"^steps is 0; expected an integer >= 1 and <= 10$"),
        (11, r"^steps is 11; expected an integer >= 1 and <= 10$"),
    ])
    def test_refusals(self, value, message):
        with pytest.raises(InputError, match=message):
            check_integer("steps", value, minimum=1, maximum=10)

    def test_bounds_are_inclusive_and_optional(self):
        assert check_integer("n", 1, minimum=1, maximum=1) == 1
        assert check_integer("n", -10**30) == -10**30
        with pytest.raises(InputError, match=r"^n is 1\.5 \(float\); expected an integer$"):
            check_integer("n", 1.5)


class TestCheckReal:
    @pytest.mark.parametrize("value", [0.5, 1, np.float32(0.5), np.float64(0.5), np.int64(1)])
    def test_accepts_real_numbers_as_float(self, value):
        checked = check_real("rate", value, minimum=0.0, maximum=1.0)
        assert checked == float(value) and type(checked) is float

    @pytest.mark.parametrize(("value", "message"), [
        (math.nan, r"^rate is nan; expected a finite number >= 0 and <= 1$"),
        (np.float32(np.nan), r"^rate is nan; expected a finite number"),
        (math.inf, r"^rate is inf; expected a finite number"),
        (-math.inf, r"^rate is -inf; expected a finite number"),
        (False, r"^rate is False \(bool\); expected a finite number >= 0 and <= 1$"),
        ("0.5", r"^rate is '0\.5' \(str\); expected a finite number"),
        (1 + 0j, r"^rate is \(1\+0j\) \(complex\); expected a finite number"),
        (-0.1, r"^rate is -0\.1; expected a finite number >= 0 and <= 1$"),
        (1.1, r"^rate is 1\.1; expected a finite number >= 0 and <= 1$"),
    ])
    def test_refusals(self, value, message):
        with pytest.raises(InputError, match=message):
            check_real("rate", value, minimum=0.0, maximum=1.0)

    def test_inclusive_bounds_accept_the_bound(self):
        assert check_real("rate", 0.0, minimum=0.0) == 0.0
        assert check_real("rate", 1.0, maximum=1.0) == 1.0

    @pytest.mark.parametrize(("options", "value", "message"), [
        ({"minimum": 0.0, "above": True}, 0.0, r"^rate is 0\.0; expected a finite number > 0$"),
        ({"maximum": 1.0, "below": True}, 1.0, r"^rate is 1\.0; expected a finite number < 1$"),
        ({"minimum": 0.0, "maximum": 1.0, "above": True, "below": True}, 1.0,
         r"^rate is 1\.0; expected a finite number > 0 and < 1$"),
    ])
    def test_exclusive_bounds_refuse_the_bound(self, options, value, message):
        with pytest.raises(InputError, match=message):
            check_real("rate", value, **options)
        assert check_real("rate", 0.5, **options) == 0.5

    def test_huge_integer_is_an_input_error(self):
        with pytest.raises(InputError, match=r"\(int\); expected a finite number$"):
            check_real("rate", 10**400)

    def test_bounds_are_written_in_full(self):
        with pytest.raises(InputError, match=r"^rate is 0\.1; expected a finite number >= 0\.123456789$"):
            check_real("rate", 0.1, minimum=0.123456789)
        with pytest.raises(InputError, match=r"^seed is 0; expected an integer >= 1 and <= 4294967295$"):
            check_integer("seed", 0, minimum=1, maximum=2**32 - 1)


class TestCheckFlag:
    @pytest.mark.parametrize("value", [True, False, np.bool_(True), np.bool_(False)])
    def test_accepts_booleans(self, value):
        checked = check_flag("refine", value)
        assert checked is bool(value)

    @pytest.mark.parametrize(("value", "message"), [
        ("false", r"^refine is 'false' \(str\); expected True or False$"),
        (0, r"^refine is 0 \(int\); expected True or False$"),
        (1.0, r"^refine is 1\.0 \(float\); expected True or False$"),
        (None, r"^refine is None \(NoneType\); expected True or False$"),
    ])
    def test_refusals(self, value, message):
        with pytest.raises(InputError, match=message):
            check_flag("refine", value)


class TestCheckSequence:
    @pytest.mark.parametrize("value", [[0.1, 0.5], (0.1, 0.5), np.array([0.1, 0.5])])
    def test_accepts_lists_and_tuples_as_tuples(self, value):
        assert check_sequence("band", value, length=2) == (0.1, 0.5)

    def test_empty_only_when_allowed(self):
        assert check_sequence("bands", [], nonempty=False) == ()
        with pytest.raises(InputError, match=r"^bands is empty; expected at least one value$"):
            check_sequence("bands", ())

    @pytest.mark.parametrize(("value", "message"), [
        ("mni", r"^band is 'mni' \(str\); expected a tuple of 2 values$"),
        (b"ab", r"^band is b'ab' \(bytes\); expected a tuple of 2 values$"),
        (bytearray(b"ab"), r"\(bytearray\); expected a tuple of 2 values$"),
        ({"low": 0.1, "high": 0.5}, r"^band is \{.*\} \(dict\); expected a tuple of 2 values$"),
        ({0.1, 0.5}, r"\(set\); expected a tuple of 2 values$"),
        (0.5, r"^band is 0\.5 \(float\); expected a tuple of 2 values$"),
        ([0.1, 0.5, 0.9], r"^band is \[0\.1, 0\.5, 0\.9\]: 3 values; expected 2$"),
        ((), r"^band is \(\): 0 values; expected 2$"),
    ])
    def test_refusals(self, value, message):
        with pytest.raises(InputError, match=message):
            check_sequence("band", value, length=2)

    def test_without_a_length_any_length_passes(self):
        assert check_sequence("channels", [8, 16, 32]) == (8, 16, 32)
        with pytest.raises(InputError, match=r"^channels is 'abc' \(str\); expected a tuple$"):
            check_sequence("channels", "abc")


class TestCheckPair:
    def test_accepts_an_increasing_pair(self):
        assert check_pair("window", [np.int16(-1000), 1000.5]) == (-1000.0, 1000.5)
        assert check_pair("band", (0.05, 1), minimum=0, maximum=1, above=True) == (0.05, 1.0)

    def test_equal_accepts_one_value(self):
        assert check_pair("sigma_range", (0.5, 0.5), minimum=0, equal=True) == (0.5, 0.5)

    @pytest.mark.parametrize(("value", "options", "message"), [
        ((2, 1), {}, r"^window is \(2\.0, 1\.0\); expected \(low, high\) with low < high$"),
        ((1, 1), {}, r"^window is \(1\.0, 1\.0\); expected \(low, high\) with low < high$"),
        ((0, 0.5), {"minimum": 0, "maximum": 1, "above": True, "note": " (fractions)"},
         r"^window is \(0\.0, 0\.5\); expected \(low, high\) with 0 < low < high <= 1 \(fractions\)$"),
        ((-1, 50), {"minimum": 0, "maximum": 100}, r"with 0 <= low < high <= 100$"),
        ((1, 101), {"minimum": 0, "maximum": 100}, r"with 0 <= low < high <= 100$"),
        ((1, float("inf")), {}, r"^window\[1\] is inf; expected a finite number$"),
        ((1, float("inf")), {"equal": True}, r"^window\[1\] is inf; expected a finite number$"),
        ((2, 1), {"minimum": 0, "equal": True},
         r"^window is \(2\.0, 1\.0\); expected \(low, high\) with 0 <= low <= high$"),
        ((0, 1), {"minimum": 0, "maximum": 1, "above": True, "equal": True}, r"with 0 < low <= high <= 1$"),
        ((1,), {}, r"^window is \(1,\): 1 values; expected 2$"),
    ])
    def test_refusals(self, value, options, message):
        with pytest.raises(InputError, match=message):
            check_pair("window", value, **options)
