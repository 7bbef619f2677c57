"""The sag estimates and segment selections of ``chords``, on hand-made samples and polylines whose
curves' distances are known in closed form."""

from __future__ import annotations

import math

import numpy as np
import pytest

from worker.dst.chords import (
    end_bend_segments,
    end_segments,
    inflected_segments,
    parabola_peak,
    run_successors,
    zero_end_peak,
)


def test_segments_with_an_inflection_inside_are_told_from_those_of_a_convex_arc():
    """``inflected_segments``: on a convex arc only each run's first and last segments (whose
    turn beyond the run's end is unknown); on an S-curve also the segment across the inflection;
    on a straight line (turns of rounding noise) the ends only."""
    t = np.linspace(0.0, 1.0, 9)
    arc = np.column_stack([np.cos(t), np.sin(t), np.zeros_like(t)])
    line = np.column_stack([t, 1e-17 * np.sin(40.0 * t), np.zeros_like(t)])
    x = np.linspace(-1.0, 1.0, 8)  # no point on the inflection at x = 0: segment 3 spans it
    s_curve = np.column_stack([x, np.tanh(3.0 * x), np.zeros_like(x)])
    xyz = np.concatenate([arc, line, s_curve])
    ri = np.repeat([0, 1, 2], [9, 9, 8])
    got = inflected_segments(ri, xyz).tolist()
    assert got == [0, 7, 9, 16, 18, 18 + 3, 18 + 6]


def test_a_runs_end_segments_are_judged_by_the_turn_across_its_corner_where_the_next_run_is_known():
    """``inflected_segments`` with each run's successor: a circle sampled as one run that ends
    where it starts has no segment to check; a circle in two runs joined both ways neither; with
    one of the links unknown, the two segments at that corner are checked."""

    a = np.linspace(0.0, 2.0 * math.pi, 13)
    circle = np.column_stack([np.cos(a), np.sin(a), np.zeros_like(a)])
    assert len(inflected_segments(np.zeros(13, dtype=np.int64), circle, np.array([0]))) == 0
    halves = np.concatenate([circle[:7], circle[6:]])  # run 0: points 0..6, run 1: 6..12 (= 0)
    ri = np.repeat([0, 1], 7)
    first, last = np.array([10, 16]), np.array([16, 10])  # vertex ids of the runs' ends
    np.testing.assert_array_equal(run_successors(first, last), [1, 0])
    assert len(inflected_segments(ri, halves, run_successors(first, last))) == 0
    assert inflected_segments(ri, halves, np.array([1, -1])).tolist() == [0, 12]


def test_a_segments_largest_distance_is_estimated_where_its_bend_is_off_centre():
    """``parabola_peak`` from three samples of a segment's distance from its chord. A bend off
    centre (the curve's distance t (1 - t)(1 + 3 t), peak 0.674 at t = 0.62, as a fillet running
    into the segment's end corner): the parabola through the samples at 1/4, 1/2, 3/4 peaks at
    0.657, 2.6% low (boxed_sphere turned (16.7, -95.9, 65.9) had a segment 0.0251 mm from its curve,
    sampled at 0.0239, against a 0.025 budget); the estimate is the peak within 0.1%. A circular arc
    of 90 degrees, sampled unevenly, is estimated within 0.5% of its exact sag, not above it by more
    (no point wasted on it)."""

    def peak(t, f):
        return float(parabola_peak(np.asarray([t]), np.asarray([f]), np.array([True]))[0])

    def skewed(t):
        return t * (1.0 - t) * (1.0 + 3.0 * t)

    t = np.array([0.25, 0.5, 0.75])
    fine = np.linspace(0.0, 1.0, 100_001)
    parabola = np.polyfit(t, skewed(t), 2)
    assert np.polyval(parabola, fine).max() < 0.975 * skewed(fine).max()
    assert peak(t, skewed(t)) == pytest.approx(skewed(fine).max(), rel=1e-3)

    # the arc of radius 1 from -45 to +45 degrees over its chord (y = cos 45 deg), sampled at
    # uneven angles: chord position t and distance of each sample
    half = math.radians(45.0)
    ang = np.radians([-30.0, 5.0, 32.0])
    x, y = np.sin(ang), np.cos(ang)
    t_s = (x + math.sin(half)) / (2.0 * math.sin(half))
    assert peak(t_s, y - math.cos(half)) == pytest.approx(1.0 - math.cos(half), rel=5e-3)


def test_a_segments_largest_distance_is_estimated_from_two_samples_where_a_quarter_point_is_lost():
    """``zero_end_peak``: a segment round a tight bend whose midpoint (placed along the seed path)
    lies at t = 0.24 of its chord and one of whose quarter points lands past its end (saying nothing),
    the other at t = 0.62. An arc of 57 degrees over the chord: the larger sample is 5% below the
    arc's sag, the estimate within 1% of it (Ventilator turned (105.4, 22.5, -109.3): 0.0242 and
    0.0253). Samples too close together or to an end say nothing (0)."""

    half = math.radians(28.5)  # the arc of radius 1 from -28.5 to +28.5 degrees over its chord

    def sample(t):  # the arc's distance from its chord over chord position t
        x = (2.0 * np.asarray(t) - 1.0) * math.sin(half)
        return np.sqrt(1.0 - x * x) - math.cos(half)

    sag = 1.0 - math.cos(half)
    t = np.array([[0.24, 0.62], [0.62, 0.24], [0.3, 0.3], [0.01, 0.5]])
    est = zero_end_peak(t, sample(t))
    assert sample(t[0]).max() < 0.96 * sag
    assert est[0] == pytest.approx(sag, rel=1e-2) and est[1] == est[0]
    assert est[2] == 0.0 and est[3] == 0.0


def test_an_end_segment_leaving_its_corner_steeper_than_a_shallow_arc_is_told():
    """``end_bend_segments``: a run's first or last segment whose curve leaves the corner at more
    than 1.5 times the angle a shallow arc within the chord makes with its chord (4 e / L). Runs of
    a circle's arc, 0.6 mm segments at a 0.025 mm chord: an arc at the budget (tangent 0.167 rad
    off the chord) is not; the same points with the start tangent turned 0.44 rad off (the bend
    next to boxed_sphere's corner) are, at the start only; a segment no longer than the chord, or an
    unknown tangent (NaN), is not."""

    e, length = 0.025, 0.6
    radius = length**2 / (8.0 * e)  # the arc whose sag over a 0.6 mm chord is the budget
    half = math.asin(0.5 * length / radius)  # its end tangents' angle with the chord
    assert half == pytest.approx(4.0 * e / length, rel=0.02)
    ang = np.linspace(-3.0 * half, 3.0 * half, 4)  # three 0.6 mm chords
    arc = np.column_stack([radius * np.sin(ang), radius * np.cos(ang), np.zeros(4)])
    ri = np.zeros(4, dtype=np.int64)
    start_t = np.array([math.cos(ang[0]), -math.sin(ang[0])])
    end_t = np.array([math.cos(ang[-1]), -math.sin(ang[-1])])
    tangents = np.array([[start_t, end_t]])
    a, b = end_bend_segments(arc, end_segments(ri, arc), tangents, e)
    assert len(a) == 0
    turn = 0.44
    steep = np.array([math.cos(ang[0] - turn), -math.sin(ang[0] - turn)])
    a, b = end_bend_segments(arc, end_segments(ri, arc), np.array([[steep, end_t]]), e)
    assert a.tolist() == [0] and b.tolist() == [1]
    short = arc * (0.9 * e / length)  # every segment shorter than the chord
    assert len(end_bend_segments(short, end_segments(ri, short), np.array([[steep, end_t]]), e)[0]) == 0
    assert (
        len(end_bend_segments(arc, end_segments(ri, arc), np.array([[[np.nan, np.nan], end_t]]), e)[0]) == 0
    )
