"""Polyline shapes the report looks for in cuts and in the exact reference (``cuts``): needles."""

from __future__ import annotations

import numpy as np
import pytest

from worker.dst.cuts import loop_needles

WIDTH, BUDGET = 1e-3, 0.025  # the reference's resolution and the default chord budget, mm


def _square_with_spike(length: float, gap: float) -> tuple[np.ndarray, np.ndarray]:
    """A 2 mm square (points every 0.1 mm, anticlockwise from (0, 0)) whose bottom side has a spike
    at x = 1 going ``length`` down and back, its two legs ``gap`` apart at the root, meeting at its
    tip. Returns the loop and the tip."""
    t = np.linspace(0.0, 2.0, 21)[:-1]
    tip = np.array([1.0 + 0.5 * gap, -length])
    down = np.column_stack([np.full(11, 1.0), np.linspace(0.0, -length, 11)])[:-1]
    up = np.column_stack([np.full(11, 1.0 + gap), np.linspace(-length, 0.0, 11)])[1:]
    bottom_l = np.column_stack([t[t < 1.0], np.zeros((t < 1.0).sum())])
    bottom_r = np.column_stack([t[t > 1.0], np.zeros((t > 1.0).sum())])
    right = np.column_stack([np.full(20, 2.0), t])
    top = np.column_stack([2.0 - t, np.full(20, 2.0)])
    left = np.column_stack([np.zeros(20), 2.0 - t])
    loop = np.concatenate([bottom_l, down, [tip], up, bottom_r, right, top, left])
    return loop, tip


def test_a_spike_out_and_back_along_itself_is_a_needle_as_long_as_the_spike():
    loop, tip = _square_with_spike(0.05, 1e-4)  # legs 0.1 um apart
    (needle,) = loop_needles(loop, WIDTH, BUDGET)
    assert needle[0] == pytest.approx(0.05, abs=1e-4)
    assert np.allclose(needle[1], tip)
    # either way round, and from any starting point
    back = np.roll(loop[::-1], 7, axis=0)
    (again,) = loop_needles(back, WIDTH, BUDGET)
    assert again[0] == pytest.approx(needle[0], abs=1e-9)


def test_a_slot_wider_than_the_width_a_short_spike_and_a_sharp_corner_are_no_needles():
    assert loop_needles(_square_with_spike(0.05, 5e-3)[0], WIDTH, BUDGET) == []  # a 5 um slot
    assert loop_needles(_square_with_spike(0.01, 1e-4)[0], WIDTH, BUDGET) == []  # shorter than the budget
    # a triangle with a 5.7 degree corner, sampled every 0.01 mm: its sides part by 1 um within
    # 0.01 mm of the corner, which is found as a (short) needle only below that length
    s = np.linspace(0.0, 1.0, 1001)[:-1, None]
    a, b, c = np.array([0.0, 0.0]), np.array([10.0, 0.5]), np.array([0.0, 1.0])
    tri = np.concatenate([a + s * (b - a), b + s * (c - b), c + s * (a - c)])
    assert loop_needles(tri, WIDTH, BUDGET) == []
    (short,) = loop_needles(tri, WIDTH, 1e-3)
    assert short[0] < 0.011 and np.allclose(short[1], b)
