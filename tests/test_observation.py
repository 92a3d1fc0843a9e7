"""The 10 Hz evaluation observation built from a scene's 2 Hz boxes (spec 4), on hand-built scenes."""

from __future__ import annotations

import math

import numpy as np
import pytest
import shapely

from scorer.geometry import box_corners
from scorer.observation import (
    OBSERVATION_STEPS,
    Observation,
    ObservationBatch,
    joined_corners,
    observe_scene,
)
from scorer.scene import EgoStatus, Frame, MapExcerpt, Scene

CURRENT = 3  # NAVSIM: 3 history frames, then the current one
FRAMES = 14


def sighting(
    track: str,
    x: float,
    y: float = 0.0,
    heading: float = 0.0,
    category: str = "vehicle",
    velocity: tuple[float, float] = (0.0, 0.0),
    length: float = 4.0,
    width: float = 2.0,
) -> tuple:
    return track, category, [x, y, 0.0, length, width, 1.5, heading], list(velocity)


def scene_with(sightings: dict[int, list[tuple]]) -> Scene:
    """Return a scene whose frame `current + i` holds `sightings[i]` (negative i: history frames)."""
    frames = []
    for index in range(FRAMES):
        objects = sightings.get(index - CURRENT, [])
        frames.append(
            Frame(
                token=f"frame{index}",
                timestamp_us=1_000_000 + 500_000 * index,
                ego=EgoStatus(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
                driving_command=(0, 1, 0, 0),
                tracks=tuple(track for track, *_ in objects),
                categories=tuple(category for _, category, *_ in objects),
                boxes=np.array([box for *_, box, _ in objects], dtype=np.float64).reshape(-1, 7),
                velocities=np.array([velocity for *_, velocity in objects], dtype=np.float64).reshape(-1, 2),
                traffic_lights=(),
                route_roadblocks=(),
            )
        )
    return Scene("scene", "log", "map", 0.5, CURRENT, tuple(frames), MapExcerpt((), (), (), ()))


def box(x: float, y: float, heading: float, length: float = 4.0, width: float = 2.0) -> shapely.Polygon:
    return shapely.polygons(box_corners(x, y, heading, length / 2.0, width / 2.0))


def test_a_track_seen_once_stands_at_that_box_for_all_51_steps() -> None:
    observation = observe_scene(scene_with({4: [sighting("parked", 12.0, 3.0, 0.3)]}))
    assert observation.tokens == ("parked",)
    assert observation.present.shape == (OBSERVATION_STEPS, 1)
    assert observation.present.all()
    expected = box(12.0, 3.0, 0.3)
    assert all(
        shapely.equals_exact(polygon, expected, tolerance=0.0) for polygon in observation.polygons[:, 0]
    )


def test_a_track_exists_from_its_first_to_its_last_sighting_interpolated_linearly() -> None:
    # Seen at 0.5 s (x = 0) and 2.0 s (x = 15): maps 5..20, gap between sightings bridged.
    observation = observe_scene(scene_with({1: [sighting("car", 0.0)], 4: [sighting("car", 15.0)]}))
    present = observation.present[:, 0]
    assert np.flatnonzero(present).tolist() == list(range(5, 21))
    assert observation.polygons[4, 0] is None and observation.polygons[21, 0] is None
    for step in (5, 12, 20):
        x = (step - 5) * 1.0
        assert shapely.equals_exact(observation.polygons[step, 0], box(x, 0.0, 0.0), tolerance=1e-9)


def test_headings_are_interpolated_the_short_way_across_pi() -> None:
    # 3.1 -> -3.1 unwraps to 3.1 -> 2 pi - 3.1: the box turns through pi, not through 0.
    observation = observe_scene(
        scene_with({0: [sighting("car", 0.0, heading=3.1)], 1: [sighting("car", 0.0, heading=-3.1)]})
    )
    halfway = 3.1 + 0.4 * (2 * math.pi - 6.2)  # map 2 = 0.2 s of 0.5 s
    assert shapely.equals_exact(observation.polygons[2, 0], box(0.0, 0.0, halfway), tolerance=1e-9)


def test_objects_come_in_first_appearance_order_with_first_sighting_type_size_and_speed() -> None:
    observation = observe_scene(
        scene_with(
            {
                -1: [sighting("history_only", 0.0)],
                0: [
                    sighting("b", 0.0, velocity=(3.0, 4.0)),
                    sighting("a", 10.0, category="barrier", velocity=(1.0, 0.0)),
                ],
                1: [
                    sighting("c", 20.0, category="pedestrian"),
                    sighting("b", 1.0, length=9.0, category="bicycle"),
                ],
            }
        )
    )
    assert observation.tokens == ("b", "a", "c")
    assert observation.object_types == ("VEHICLE", "BARRIER", "PEDESTRIAN")
    assert observation.is_agent.tolist() == [True, False, True]
    assert observation.first_speed.tolist() == [5.0, 0.0, 0.0]  # static objects never move
    # "b" keeps its first length (4 m) at 0.5 s, where its second sighting had 9 m.
    assert shapely.equals_exact(observation.polygons[5, 0], box(1.0, 0.0, 0.0), tolerance=1e-9)


def test_a_scene_without_objects_has_an_empty_observation() -> None:
    observation = observe_scene(scene_with({}))
    assert observation.tokens == ()
    assert observation.present.shape == (OBSERVATION_STEPS, 0)
    assert ObservationBatch.of([observation]).extent.shape == (0, 4)


@pytest.mark.parametrize("widths", [[7], [0], [4], [5, 0, 1, 3, 9, 2, 0, 4]])
def test_joined_boxes_land_where_mask_assignments_put_them(widths: list[int]) -> None:
    """Observations of every width (none, one object, absent everywhere, all present) joined side by side hold
    the bits each one's boolean-mask assignment gives: -0.0, NaN, infinities and subnormals kept, NaN where
    absent."""
    rng = np.random.default_rng(7)
    steps = 41
    presents = [rng.random((steps, width)) < rng.choice([0.0, 0.6, 1.0]) for width in widths]
    specials = np.array([np.nan, np.inf, -np.inf, 1e308, 5e-324, -0.0])
    boxes = []
    for present in presents:
        values = rng.standard_normal((int(present.sum()), 4, 2)) * 10.0 ** rng.integers(-300, 300)
        chosen = rng.random(values.shape) < 0.05
        values[chosen] = rng.choice(specials, int(chosen.sum()))
        # Unaligned, as a cache file's view may be.
        boxes.append(np.frombuffer(b"\0" + values.tobytes(), np.float64, offset=1).reshape(values.shape))
    expected = []
    for present, values in zip(presents, boxes, strict=True):
        dense = np.full((steps, present.shape[1], 4, 2), np.nan)
        dense[present] = values
        expected.append(dense)
    assert joined_corners(presents, boxes).tobytes() == np.concatenate(expected, axis=1).tobytes()
    observation = Observation(
        tokens=("a",) * widths[0],
        object_types=("VEHICLE",) * widths[0],
        is_agent=np.ones(widths[0], dtype=bool),
        first_speed=np.zeros(widths[0]),
        present=presents[0],
        boxes=boxes[0],
    )
    assert observation.corners.tobytes() == expected[0].tobytes()
