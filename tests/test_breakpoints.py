"""The one breakpoint rule of every table axis (ECU grid, ECU files, load tables)."""

import numpy as np
import pytest

from engine_model.contracts import check_breakpoints
from engine_model.globalmodel.load_table import LoadTable
from engine_model.tables.ecu_table import EcuTable
from engine_model.tables.grid import EcuGrid


@pytest.mark.parametrize("values, match", [
    ((1000, 2000, 2000), r"X.rpm: duplicate breakpoint 2000 rpm at positions 1 and 2"),
    ((1000, 3000, 2000), r"X.rpm: breakpoints must be sorted ascending; 3000 rpm \(position 1\) is followed by 2000"),
    ((1000, float("inf")), r"X.rpm: breakpoint 1 = inf is not a finite number"),
    ((1000,), r"X.rpm: needs at least 2 breakpoints, got 1"),
    (("a", 2), r"X.rpm: .* must be a sequence of numbers \[rpm\]"),
    ((500, 30000), r"X.rpm: breakpoints 500..30000 rpm leave the allowed range \[1000, 20000\] rpm"),
])
def test_each_broken_rule_is_named_with_the_breakpoint(values, match):
    with pytest.raises(ValueError, match=match):
        check_breakpoints("X.rpm", values, "rpm", 1000, 20000)


def test_good_breakpoints_come_back_as_floats_in_order():
    out = check_breakpoints("X.rpm", [1000, "2000", 3500.5], "rpm")
    assert out.dtype == float and list(out) == [1000.0, 2000.0, 3500.5]


@pytest.mark.parametrize("make", [
    lambda v: EcuGrid((0.0, 100.0), v),
    lambda v: EcuTable("spark_advance", np.zeros((2, 3)), v, (0.0, 100.0), unit="deg BTDC"),
    lambda v: LoadTable((0, 10, 20, 30), v + (9000.0,), np.ones((4, 4))),
])
def test_every_table_kind_follows_the_same_rule(make):
    with pytest.raises(ValueError, match=r"duplicate breakpoint 2000 rpm at positions 1 and 2"):
        make((1000.0, 2000.0, 2000.0))
