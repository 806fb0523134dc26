"""argparse types: bad numbers refused with a message naming the bound."""

import argparse

import pytest

from deform.argtypes import int_at_least, number


def test_integers_below_the_bound_and_non_integers_are_refused():
    parse = int_at_least(1)
    assert parse("3") == 3
    for bad, message in (("0", "at least 1, got 0"), ("-2", "at least 1"), ("2.5", "an integer")):
        with pytest.raises(argparse.ArgumentTypeError, match=message):
            parse(bad)


def test_numbers_refuse_negatives_infinities_nan_and_zero_when_positive():
    assert number(positive=False)("0") == 0.0 and number(positive=True)("0.1") == 0.1
    for positive, bad in ((True, "0"), (False, "-0.1"), (False, "inf"), (False, "nan"), (True, "x")):
        with pytest.raises(argparse.ArgumentTypeError):
            number(positive)(bad)
