"""Chords against the curves they stand for: the largest distance of a segment's curve from its
chord estimated from samples along it, and which segments need more than their midpoint checked.

Pure numpy on points already solved on the exact curve (``refine`` solves them). Segments are given
as rows: points ``p`` with chord ends ``a`` and ``b``, or a run's points sorted by run and arc length.
"""

from __future__ import annotations

import numpy as np

# Segments are accepted with their sampled largest distance from the curve at most this share of the
# chord budget: the samples (midpoint, quarter points, the parabola through them) can miss the true
# largest distance by a few per cent where the bend is off-centre.
CHORD_FILL = 0.97
# A shallow arc within the chord budget e leaves its chord at ~4 e / L (L: the chord's length). A run's
# end segment whose curve leaves the corner at more than this many times that (by its own face's
# tangent there) hides a bend next to the corner that its midpoint does not show: checked at its
# quarter points and split where it fails, round after round on the new end segments
END_BEND_FACTOR = 1.5
# where ``zero_end_peak`` is evaluated; samples this close to an end give it no shape
_QUARTIC_GRID = np.linspace(0.0, 1.0, 65)
_QUARTIC_END = 0.02


def parabola_peak(t: np.ndarray, f: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """Row-wise estimate of the largest distance of a segment's curve from its chord, from three
    samples (t, f) (any order of t): the peak of the parabola through them where it opens downwards
    and peaks between them (capped at 1.5 times the largest sample: nearly collinear samples would
    extrapolate wildly), beyond the outer samples the bound of a concave distance, and the peak of
    the quartic through the samples and the chord's ends (same cap). 0 if none.

    The quartic (zero at t = 0 and 1, where the curve meets its chord) follows a bend off-centre
    that the parabola through the samples alone flattens: boxed_sphere turned (16.7, -95.9, 65.9)
    at z = 8.9, samples 0.0121, 0.0239, 0.0143 at t = 0.30, 0.61, 0.91 of a segment ending in a
    corner, whose curve peaks at 0.0251 at t = 0.72 (a tighter bend towards the corner): the
    parabola says 0.0239, the quartic 0.0252. (At z = 10.9 a 0.055 mm segment across a small lobe,
    sampled at 0.0241, was 0.0257 from its curve.)"""
    order = np.argsort(t, axis=1)
    t, f = np.take_along_axis(t, order, axis=1), np.take_along_axis(f, order, axis=1)
    (t1, t2, t3), (f1, f2, f3) = t.T, f.T
    with np.errstate(divide="ignore", invalid="ignore"):
        d12, d23 = (f2 - f1) / (t2 - t1), (f3 - f2) / (t3 - t2)
        a = (d23 - d12) / (t3 - t1)
        ts = 0.5 * (t1 + t2) - d12 / (2.0 * a)  # where the derivative d12 + a (2 t - t1 - t2) vanishes
        peak = f1 + d12 * (ts - t1) + a * (ts - t1) * (ts - t2)
        # beyond the outer samples, a concave distance (a convex arc) stays under the line through the
        # two samples on that side: a bend at the segment's end (a line running into a small fillet)
        # rises there after three samples on the straight part
        start = np.where(f1 > f2, f1 + (f1 - f2) * np.clip(t1, 0.0, 1.0) / (t2 - t1), 0.0)
        end = np.where(f3 > f2, f3 + (f3 - f2) * np.clip(1.0 - t3, 0.0, 1.0) / (t3 - t2), 0.0)
    spaced = (t2 - t1 > 1e-9) & (t3 - t2 > 1e-9)
    good = ok & (a < 0) & (ts > t1) & (ts < t3) & spaced & np.isfinite(peak)
    cap = 1.5 * f.max(axis=1)
    out = np.where(good, np.minimum(peak, cap), 0.0)
    out = np.maximum(out, np.where(ok, zero_end_peak(t, f), 0.0))  # the quartic
    return np.maximum(out, np.where(ok & spaced, np.maximum(start, end), 0.0))


def zero_end_peak(t: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Row-wise estimate of the largest distance of a segment's curve from its chord from k samples
    (t, f) ((n, k), t ascending or not): the peak of t (1 - t) g(t), g the polynomial of degree k - 1
    through g_i = f_i / (t_i (1 - t_i)), zero at the chord's ends as the curve is (a circular arc's
    distance is c t (1 - t) to second order: g constant), evaluated on a grid and capped at 1.5 times
    the largest sample. Three samples give ``parabola_peak``'s quartic; two (a quarter point lost)
    a cubic. 0 where two samples are not apart or one lies within ``_QUARTIC_END`` of an end (no
    shape there)."""
    order = np.argsort(t, axis=1)
    t, f = np.take_along_axis(t, order, axis=1), np.take_along_axis(f, order, axis=1)
    k = t.shape[1]
    x = _QUARTIC_GRID[None, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        g = f / (t * (1.0 - t))
        lag = []  # the Lagrange basis on the samples, on the grid
        for i in range(k):
            num: np.ndarray | float = 1.0
            den: np.ndarray | float = 1.0
            for j in range(k):
                if j != i:
                    num = num * (x - t[:, j, None])
                    den = den * (t[:, i] - t[:, j])
            lag.append(num / np.asarray(den)[:, None])
        value = (x * (1.0 - x) * sum(g[:, i, None] * lag[i] for i in range(k))).max(axis=1)
    spaced = (np.diff(t, axis=1) > 1e-9).all(axis=1)
    good = spaced & (t[:, 0] > _QUARTIC_END) & (t[:, -1] < 1.0 - _QUARTIC_END) & np.isfinite(value)
    return np.where(good, np.minimum(value, 1.5 * f.max(axis=1)), 0.0)


def chord_position(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise position of the projection of ``p`` on the line a-b (0 at a, 1 at b)."""
    ab = b - a
    denom = np.einsum("ij,ij->i", ab, ab)
    return np.einsum("ij,ij->i", p - a, ab) / np.where(denom > 0, denom, 1.0)


def point_segment_offset(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise vector from the nearest point of each segment ``a``-``b`` to its point ``p``; all (n, 3)."""
    t = np.clip(chord_position(p, a, b), 0.0, 1.0)
    return p - (a + t[:, None] * (b - a))


def point_segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise distance (mm) from points ``p`` to segments ``a``-``b``; all (n, 3)."""
    return np.linalg.norm(point_segment_offset(p, a, b), axis=1)


def end_segments(
    ri: np.ndarray, xyz: np.ndarray, longer: float = 0.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The first and last segments of each run (points ``ri``/``xyz`` sorted by run and arc
    length) longer than ``longer``: their first and second points (indices), their run (its id in
    ``ri``) and which end of it (0: start, 1: end)."""
    if len(ri) < 2:
        none = np.zeros(0, dtype=np.int64)
        return none, none, none, none
    first = np.flatnonzero(np.concatenate([[True], ri[1:] != ri[:-1]]))
    last = np.concatenate([first[1:], [len(ri)]]) - 1
    two = last > first  # runs with a segment
    first, last = first[two], last[two]
    a = np.concatenate([first, last - 1])
    b = np.concatenate([first + 1, last])
    end = np.repeat([0, 1], len(first))
    long = np.hypot(*(xyz[b, :2] - xyz[a, :2]).T) > longer
    return a[long], b[long], ri[a[long]], end[long]


def end_bend_segments(
    xyz: np.ndarray, ends: tuple[np.ndarray, ...], tangents: np.ndarray, chord: float
) -> tuple[np.ndarray, np.ndarray]:
    """Of the runs' end segments ``ends`` (``end_segments`` of the points ``xyz``, sorted by run
    and arc length), those (first and last points, as indices into ``xyz``) whose curve leaves the
    corner at their end (``tangents``: (n_runs, 2, 2) at start and end, NaN where unknown) at more
    than END_BEND_FACTOR times the angle a shallow arc within ``chord`` of its chord makes with it
    (4 chord / L). Segments no longer than the chord are within it whatever their arc."""
    a, b, run, end = ends
    at = tangents[run, end]
    c = xyz[b, :2] - xyz[a, :2]
    length = np.hypot(c[:, 0], c[:, 1])
    with np.errstate(invalid="ignore", divide="ignore"):
        sin = np.abs(at[:, 0] * c[:, 1] - at[:, 1] * c[:, 0]) / length
        steep = (length > chord) & (sin > END_BEND_FACTOR * 4.0 * chord / length)
    steep &= np.isfinite(sin)
    return a[steep], b[steep]


def run_successors(first: np.ndarray, last: np.ndarray) -> np.ndarray:
    """For each run (first and last vertex ids), the run that starts where it ends (the next piece
    of its loop past the corner between them; itself for a loop that is one run), or -1 where no
    run or more than one does (a vertex two loops share)."""
    starts: dict[int, list[int]] = {}
    for q, v in enumerate(first.tolist()):
        starts.setdefault(v, []).append(q)
    out = np.full(len(first), -1, dtype=np.int64)
    for r, v in enumerate(last.tolist()):
        if len(qs := starts.get(v, [])) == 1:
            out[r] = qs[0]
    return out


def inflected_segments(
    ri: np.ndarray, xyz: np.ndarray, after: np.ndarray | None = None, gap: np.ndarray | None = None
) -> np.ndarray:
    """The segments (index of their first point) of runs ``ri`` (points sorted by run and arc
    length, at ``xyz``) whose polyline turns one way at one end and the other way at the other: the
    curve has an inflection inside, where the midpoint can lie on the chord while the curve is off it
    on either side (r103ec turned (5.4, -134.3, 135.1), the report's reference at z = 12.1: a 1.67 mm
    segment with its midpoint on the chord and the curve 5 um off it at a quarter and three quarters
    of the way). At a run's end the turn is taken with the first segment of the run ``after`` it
    (``run_successors``; runs numbered 0 .. n - 1, each with two points or more); a segment ending
    where that is not known counts as inflected. Turns of under 1e-9 rad count as none (a straight
    line's points in a row). ``gap``: the points added next to run ends off their curve
    (``_gap_end_points``): the turn there is not known, and the jump from the run's end to one is
    no curve to check."""
    if len(ri) < 2:
        return np.empty(0, dtype=np.int64)
    d = np.diff(xyz[:, :2], axis=0)
    same = ri[1:] == ri[:-1]  # segment k: points k, k + 1 of one run
    length = np.hypot(d[:, 0], d[:, 1])

    def sign_of_turn(d0: np.ndarray, d1: np.ndarray) -> np.ndarray:
        cross = d0[..., 0] * d1[..., 1] - d0[..., 1] * d1[..., 0]
        size = np.hypot(d0[..., 0], d0[..., 1]) * np.hypot(d1[..., 0], d1[..., 1])
        return np.where(np.abs(cross) > 1e-9 * size, np.sign(cross), 0.0)

    turn = np.zeros(len(ri))  # at each point, where ``known``
    turn[1:-1] = sign_of_turn(d[:-1], d[1:])
    known = np.concatenate([[False], same[:-1] & same[1:], [False]])  # points inside their run
    if after is not None and len(after):
        bounds = np.searchsorted(ri, np.arange(len(after) + 1))
        linked = np.flatnonzero(after >= 0)
        end, start = bounds[linked + 1] - 1, bounds[after[linked]]  # the same vertex, in two runs
        ok = (end - 1 >= bounds[linked]) & (start + 1 < bounds[after[linked] + 1])
        end, start = end[ok], start[ok]
        across = sign_of_turn(xyz[end, :2] - xyz[end - 1, :2], xyz[start + 1, :2] - xyz[start, :2])
        turn[end], turn[start] = across, across
        known[end], known[start] = True, True
    if gap is not None:
        known &= ~gap
        run_end = np.concatenate([[True], ~same]) | np.concatenate([~same, [True]])
        jump = np.concatenate([(gap[1:] & run_end[:-1]) | (gap[:-1] & run_end[1:]), [False]])
        same = same & ~jump[:-1]
    k = np.flatnonzero(same & (length > 1e-9))
    flip = ~known[k] | ~known[k + 1] | (turn[k] * turn[k + 1] < 0)
    return k[flip]


def distances_to_segments(q: np.ndarray, seg: np.ndarray, chunk: int = 256) -> np.ndarray:
    """Distance (mm) from each of the points ``q`` (k, 2) to the nearest of the segments ``seg``
    (m, 2, 2): (k,)."""
    a, ab = seg[:, 0], seg[:, 1] - seg[:, 0]
    denom = np.maximum((ab * ab).sum(axis=1), 1e-300)
    out = np.empty(len(q))
    for s in range(0, len(q), chunk):
        d = q[s : s + chunk, None, :] - a  # (c, m, 2)
        t = np.clip((d * ab).sum(axis=2) / denom, 0.0, 1.0)
        out[s : s + chunk] = np.sqrt(((d - t[..., None] * ab) ** 2).sum(axis=2).min(axis=1))
    return out
