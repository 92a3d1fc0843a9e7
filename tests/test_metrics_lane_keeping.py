"""Lane keeping's cut centerlines give GEOS's comparison with the limit, centres on the limit included."""

from __future__ import annotations

import numpy as np
import shapely

from scorer.metrics.lane_keeping import nearby_centerlines

ORIGIN = np.array([665328.6352374122, 3996354.5321324635])  # UTM-sized coordinates, as in the logs
LIMIT = 0.5


def winding_centerline(rng: np.random.Generator, count: int) -> np.ndarray:
    heading = np.cumsum(rng.normal(0.0, 0.08, count))
    steps = rng.uniform(1.0, 2.5, count)[:, None] * np.stack([np.cos(heading), np.sin(heading)], axis=1)
    return ORIGIN + np.cumsum(steps, axis=0)


def centres_around(rng: np.random.Generator, line: np.ndarray, rows: int) -> np.ndarray:
    """Rows of 41 centres on points of the line's segments, pushed sideways by about the limit: by it exactly,
    by it and an ulp to a micrometre more or less, or by anything up to 3 m."""
    segment = rng.integers(0, len(line) - 41, rows)[:, None] + np.arange(41)
    start, end = line[segment], line[segment + 1]
    along = rng.choice([0.0, 0.5, rng.uniform()], (rows, 41))[..., None]
    direction = end - start
    normal = np.stack([-direction[..., 1], direction[..., 0]], axis=-1)
    normal /= np.hypot(normal[..., 0], normal[..., 1])[..., None]
    nudge = rng.choice([0.0, 1e-15, 1e-12, 1e-9, 1e-6], (rows, 41)) * rng.choice([-1.0, 1.0], (rows, 41))
    offset = np.where(rng.random((rows, 41)) < 0.8, LIMIT + nudge, rng.uniform(0.0, 3.0, (rows, 41)))
    side = rng.choice([-1.0, 1.0], (rows, 41))
    return start + direction * along + normal * (offset * side)[..., None]


def test_cut_centerlines_compare_with_the_limit_as_the_whole_ones() -> None:
    rng = np.random.default_rng(17)
    lines = [winding_centerline(rng, count) for count in (120, 160, 200)]
    centerlines = np.array([shapely.LineString(line) for line in lines], dtype=object)
    row_token = np.repeat(np.arange(3), 200)
    centers = np.concatenate([centres_around(rng, line, 200) for line in lines])
    points = shapely.points(centers)
    whole = shapely.distance(points, centerlines[row_token][:, None])
    cut = nearby_centerlines(centers, centerlines, row_token, LIMIT)
    near = shapely.distance(points, cut[:, None])
    assert 0.2 < (whole > LIMIT).mean() < 0.8
    assert np.array_equal(near > LIMIT, whole > LIMIT)
    within = whole <= LIMIT
    assert np.array_equal(near[within], whole[within])
    # The cut keeps the part of the line that the row's centres span, not the whole line.
    assert np.median(shapely.get_num_coordinates(cut)) < 0.5 * np.median(
        shapely.get_num_coordinates(centerlines)
    )


def test_rows_far_from_the_centerline_keep_all_of_it() -> None:
    rng = np.random.default_rng(19)
    line = winding_centerline(rng, 60)
    centerlines = np.array([shapely.LineString(line)], dtype=object)
    far = np.full((2, 41, 2), ORIGIN - 1000.0)
    far[1, 3] = np.nan
    cut = nearby_centerlines(far, centerlines, np.zeros(2, dtype=np.intp), LIMIT)
    assert shapely.equals_exact(cut, centerlines[0], tolerance=0.0).all()


def test_a_segment_exactly_the_limit_away_is_kept() -> None:
    # The nearest segment lies exactly the limit below the centre (or an ulp more or less), with its bounds as
    # far: only a cut that keeps it gives the whole line's distance; a later segment comes nearer in bounds only.
    line = np.array([[0.0, 0.0], [10.0, 0.0], [6.0, 1.5], [5.4, 0.9]])
    centerlines = np.array([shapely.LineString(line)], dtype=object)
    heights = [np.nextafter(LIMIT, 0.0), LIMIT, np.nextafter(LIMIT, 1.0)]
    centers = np.array([[[5.0, height]] * 41 for height in heights])
    row_token = np.zeros(len(heights), dtype=np.intp)
    whole = shapely.distance(shapely.points(centers), centerlines[row_token][:, None])
    near = shapely.distance(
        shapely.points(centers), nearby_centerlines(centers, centerlines, row_token, LIMIT)[:, None]
    )
    assert (whole <= LIMIT).any()
    assert np.array_equal(near, whole)
