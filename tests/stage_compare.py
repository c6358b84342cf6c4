"""Test helper: two USD stages hold the same animation, sample by sample."""

from __future__ import annotations

import numpy as np
from pxr import Usd


def assert_stages_equal(actual: Usd.Stage, expected: Usd.Stage) -> None:
    """Same prims, attributes, time samples and values at every sample (and the same timeline)."""
    assert actual.GetStartTimeCode() == expected.GetStartTimeCode()
    assert actual.GetEndTimeCode() == expected.GetEndTimeCode()
    assert actual.GetTimeCodesPerSecond() == expected.GetTimeCodesPerSecond()
    assert [p.GetPath() for p in actual.Traverse()] == [p.GetPath() for p in expected.Traverse()]
    for prim in expected.Traverse():
        other = actual.GetPrimAtPath(prim.GetPath())
        assert sorted(a.GetName() for a in other.GetAttributes()) == sorted(a.GetName() for a in prim.GetAttributes())
        for attr in prim.GetAttributes():
            mine = other.GetAttribute(attr.GetName())
            assert mine.GetTimeSamples() == attr.GetTimeSamples(), attr.GetPath()
            for t in attr.GetTimeSamples():
                a, b = mine.Get(t), attr.Get(t)
                if hasattr(b, "__len__") and not isinstance(b, str):
                    np.testing.assert_array_equal(np.asarray(a), np.asarray(b), err_msg=f"{attr.GetPath()} at {t}")
                else:
                    assert a == b, f"{attr.GetPath()} at {t}"
