"""physics/validity.py: each rule's array form is its float form element by element (the live path
takes floats, replay arrays), including at and around every boundary."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings, strategies as st

from millsense.daemon.physics import validity as v

RPM = st.one_of(st.floats(30.0, 6000.0), st.sampled_from([200.0, 600.0, 4500.0]))


@st.composite
def ramps(draw):
    rpm = draw(RPM)
    edge = max(v.RAMP_RISE_FRAC * rpm, v.RAMP_RISE_MIN_RPM)
    rise = draw(st.one_of(st.floats(-400.0, 400.0), st.sampled_from([edge, -edge, 0.0]),
                          st.sampled_from([edge * (1 + 1e-9), edge * (1 - 1e-9)])))
    prev = draw(st.one_of(st.none(), st.floats(30.0, 6000.0), st.just(rpm * (1 + v.RAMP_SLOWING_FRAC))))
    p_gap = draw(st.one_of(st.floats(-5000.0, 20000.0), st.just(0.0), st.just(-0.0)))
    inertia = draw(st.one_of(st.just(0.0), st.floats(-50.0, 50.0)))
    torque = draw(st.one_of(st.floats(-50.0, 100.0), st.just(inertia)))
    return rpm, rise, prev, p_gap, inertia, torque


@settings(max_examples=300, deadline=None)
@given(rows=st.lists(ramps(), min_size=1, max_size=6))
def test_spindle_ramp_on_floats_is_the_array_form(rows):
    floats = [bool(v.spindle_ramp(rise, rpm, prev, p, j, t)) for rpm, rise, prev, p, j, t in rows]
    cols = [np.array([r[i] if r[i] is not None else math.nan for r in rows], dtype=float) for i in range(6)]
    rpm, rise, prev, p, j, t = cols
    assert v.spindle_ramp(rise, rpm, prev, p, j, t).tolist() == floats


@settings(max_examples=300, deadline=None)
@given(t_c=st.lists(st.one_of(st.floats(0.0, 2.0), st.just(math.nan),
                              st.sampled_from([v.FEED_PER_TOOTH_MIN_MM, v.FEED_PER_TOOTH_MAX_MM, 0.3, 0.0])),
                    min_size=1, max_size=6),
       radius=st.sampled_from([1.0, 3.0, 4.0, 7.0, 8.0, 10.0]))
def test_feed_status_on_floats_is_the_array_form(t_c, radius):
    low, high = v.feed_masks(np.array(t_c), radius)
    for x, lo, hi in zip(t_c, low.tolist(), high.tolist()):
        expected = v.NOT_FEEDING if lo else v.FEED_OUT_OF_RANGE if hi else None
        assert v.feed_status(x, radius) == expected


def test_feed_bounds_at_their_edges():
    assert v.feed_status(v.FEED_PER_TOOTH_MIN_MM, 10.0) is None
    assert v.feed_status(math.nextafter(v.FEED_PER_TOOTH_MIN_MM, 0.0), 10.0) == v.NOT_FEEDING
    assert v.feed_status(v.FEED_PER_TOOTH_MAX_MM, 10.0) is None                # φ20: 0.7 mm
    assert v.feed_status(math.nextafter(v.FEED_PER_TOOTH_MAX_MM, 1.0), 10.0) == v.FEED_OUT_OF_RANGE
    assert v.feed_status(0.4, 4.0) is None                                     # φ8: a tenth of the radius
    assert v.feed_status(math.nextafter(0.4, 1.0), 4.0) == v.FEED_OUT_OF_RANGE


@settings(max_examples=200, deadline=None)
@given(rows=st.lists(st.tuples(st.one_of(st.none(), st.floats(0.0, 50.0)), st.one_of(st.none(), st.floats(0.0, 100.0))),
                     min_size=1, max_size=6),
       diameter=st.sampled_from([6.0, 8.0, 20.0]), length=st.sampled_from([9.0, 16.0, 40.0]))
def test_within_tool_on_floats_is_the_array_form(rows, diameter, length):
    radial = np.array([math.nan if r is None else r for r, _ in rows])
    axial = np.array([math.nan if a is None else a for _, a in rows])
    got = v.within_tool(radial, axial, diameter, length).tolist()
    assert got == [v.within_tool(r, a, diameter, length) for r, a in rows]


def test_the_default_flute_length_is_twice_the_diameter():
    assert v.default_flute_length_mm(8.0) == 16.0 and v.default_flute_length_mm(20.0) == 40.0
