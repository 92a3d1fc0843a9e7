"""A synthetic map under construction: nuPlan-like layers in creation order, and road builders.

Roads are built on a reference line sampled every GRID_STEP metres. A carriageway (one direction)
is a chain of roadblocks joined by short roadblock connectors, as in nuPlan maps; its lanes lie to
the right of the reference line. Roadblock polygons reach the middle of the connector gaps so
that the road is drivable without seams (connector polygons are not drivable for DAC).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from scorer.geometry import FloatArray
from scorer.scene import AREA_LAYERS
from scorer.synth.polyline import Polyline, sample_indices

BASELINE_STRIDE = 2  # exported lane baselines and polygons keep every 2nd vertex of the 1 m grid
CONNECTOR_GAP = 2  # grid steps between consecutive roadblocks of a carriageway


@dataclass(eq=False)
class LaneRecord:
    """A lane or lane connector; `centre` is the dense centre line agents drive along."""

    id: str
    block: str
    centre: FloatArray
    baseline: FloatArray
    polygon: FloatArray
    speed_limit: float | None
    incoming: list[str] = field(default_factory=list)
    outgoing: list[str] = field(default_factory=list)


@dataclass(eq=False)
class BlockRecord:
    """A roadblock or roadblock connector."""

    id: str
    polygon: FloatArray
    incoming: list[str] = field(default_factory=list)
    outgoing: list[str] = field(default_factory=list)
    lanes: list[str] = field(default_factory=list)


@dataclass(eq=False)
class AreaRecord:
    """A polygon-only map object."""

    id: str
    polygon: FloatArray


class RoadMap:
    """Map layers in creation order; ids are consecutive decimal integers."""

    def __init__(self, first_id: int) -> None:
        self._next_id = first_id
        self.lanes: list[LaneRecord] = []
        self.lane_connectors: list[LaneRecord] = []
        self.roadblocks: list[BlockRecord] = []
        self.roadblock_connectors: list[BlockRecord] = []
        self.areas: dict[str, list[AreaRecord]] = {layer: [] for layer in AREA_LAYERS}

    def new_id(self) -> str:
        """Return the next unused map id."""
        self._next_id += 1
        return str(self._next_id)

    def add_block(self, polygon: FloatArray, connector: bool) -> BlockRecord:
        """Add a roadblock (or a roadblock connector)."""
        block = BlockRecord(self.new_id(), polygon)
        (self.roadblock_connectors if connector else self.roadblocks).append(block)
        return block

    def add_lane(
        self,
        block: BlockRecord,
        centre: FloatArray,
        polygon: FloatArray,
        stride: int,
        speed_limit: float | None,
        connector: bool,
    ) -> LaneRecord:
        """Add a lane (or lane connector) of `block`; its baseline keeps every `stride`-th centre vertex."""
        baseline = centre[sample_indices(len(centre), stride)]
        lane = LaneRecord(self.new_id(), block.id, centre, baseline, polygon, speed_limit)
        (self.lane_connectors if connector else self.lanes).append(lane)
        block.lanes.append(lane.id)
        return lane

    def add_area(self, layer: str, polygon: FloatArray) -> AreaRecord:
        """Add a polygon to an area layer (intersections, carpark_areas, drivable_areas, crosswalks, walkways)."""
        area = AreaRecord(self.new_id(), polygon)
        self.areas[layer].append(area)
        return area


def ring(left: FloatArray, right: FloatArray) -> FloatArray:
    """Return the polygon between two boundaries given in the same direction."""
    return np.concatenate([left, right[::-1]])


def _join(
    before: BlockRecord | LaneRecord, connector: BlockRecord | LaneRecord, after: BlockRecord | LaneRecord
) -> None:
    before.outgoing.append(connector.id)
    connector.incoming.append(before.id)
    connector.outgoing.append(after.id)
    after.incoming.append(connector.id)


def connect(
    road_map: RoadMap,
    before: BlockRecord,
    after: BlockRecord,
    pairs: Sequence[tuple[LaneRecord, LaneRecord]],
    centres: Sequence[FloatArray],
    width: float,
    speed_limit: float | None,
    bounds: Sequence[tuple[FloatArray, FloatArray]] | None = None,
) -> BlockRecord:
    """Add a roadblock connector from `before` to `after` with one lane connector per (lane, lane) pair.

    Pairs run from the left-most to the right-most lane; the connector's polygon spans them. The lane
    connectors' left and right boundaries are `bounds`, by default the centres offset by half a width.
    """
    if bounds is None:
        paths = [Polyline.from_points(centre) for centre in centres]
        bounds = [(path.offset(0.5 * width), path.offset(-0.5 * width)) for path in paths]
    block = road_map.add_block(ring(bounds[0][0], bounds[-1][1]), connector=True)
    _join(before, block, after)
    for (lane_in, lane_out), centre, (left, right) in zip(pairs, centres, bounds, strict=True):
        lane = road_map.add_lane(block, centre, ring(left, right), 1, speed_limit, connector=True)
        _join(lane_in, lane, lane_out)
    return block


@dataclass(frozen=True, eq=False)
class Carriageway:
    """One direction of a road along `reference`: blocks alternate roadblock, connector, roadblock, ..."""

    reference: Polyline
    sections: list[tuple[int, int]]  # first and last reference vertex of each roadblock's lanes
    blocks: list[BlockRecord]
    lanes: list[list[LaneRecord]]  # per roadblock; lane k is the k-th from the reference line
    width: float
    _paths: dict[int, Polyline] = field(default_factory=dict)

    @property
    def n_lanes(self) -> int:
        """Return the number of lanes."""
        return len(self.lanes[0])

    def lane_path(self, k: int) -> Polyline:
        """Return the dense centre line of lane k over the whole carriageway (same vertex indices as the reference)."""
        if k not in self._paths:
            self._paths[k] = Polyline.from_points(self.reference.offset(-(k + 0.5) * self.width))
        return self._paths[k]

    def block_index(self, vertex: int) -> int:
        """Return the index in `blocks` of the roadblock (or connector) at a reference vertex."""
        for index, (first, last) in enumerate(self.sections):
            if vertex <= last:
                return 2 * index if vertex >= first else 2 * index - 1
        return len(self.blocks) - 1


def cut_sections(n_points: int, lengths: Sequence[int]) -> list[tuple[int, int]]:
    """Return (first, last) grid indices of consecutive roadblocks of the given lengths, CONNECTOR_GAP apart.

    The last roadblock takes whatever remains of the n_points.
    """
    sections, start = [], 0
    for length in lengths:
        if start + length + CONNECTOR_GAP + length // 2 >= n_points - 1:
            break
        sections.append((start, start + length))
        start += length + CONNECTOR_GAP
    sections.append((start, n_points - 1))
    return sections


def carriageway(
    road_map: RoadMap,
    reference: Polyline,
    sections: Sequence[tuple[int, int]],
    n_lanes: int,
    width: float,
    speed_limit: float | None,
) -> Carriageway:
    """Build one direction of a road: n_lanes lanes right of `reference`, one roadblock per section."""
    # Half-lane offsets: boundary j at index 2j, centre of lane k at index 2k + 1.
    lines = [reference.offset(-0.5 * width * j) for j in range(2 * n_lanes + 1)]
    outer = 2 * n_lanes
    blocks: list[BlockRecord] = []
    lanes: list[list[LaneRecord]] = []
    for index, (first, last) in enumerate(sections):
        # The roadblock reaches the middle of the neighbouring connector gaps: the road has no seams.
        block_first = first - CONNECTOR_GAP // 2 if index > 0 else first
        block_last = last + CONNECTOR_GAP // 2 if index < len(sections) - 1 else last
        keep = block_first + sample_indices(block_last - block_first + 1, BASELINE_STRIDE)
        block = road_map.add_block(ring(lines[0][keep], lines[outer][keep]), connector=False)
        keep = first + sample_indices(last - first + 1, BASELINE_STRIDE)
        block_lanes = [
            road_map.add_lane(
                block,
                lines[2 * k + 1][first : last + 1],
                ring(lines[2 * k][keep], lines[2 * k + 2][keep]),
                BASELINE_STRIDE,
                speed_limit,
                connector=False,
            )
            for k in range(n_lanes)
        ]
        if blocks:
            previous_last = sections[index - 1][1]
            gap = slice(previous_last, first + 1)
            blocks.append(
                connect(
                    road_map,
                    blocks[-1],
                    block,
                    list(zip(lanes[-1], block_lanes, strict=True)),
                    [lines[2 * k + 1][gap] for k in range(n_lanes)],
                    width,
                    speed_limit,
                    [(lines[2 * k][gap], lines[2 * k + 2][gap]) for k in range(n_lanes)],
                )
            )
        blocks.append(block)
        lanes.append(block_lanes)
    return Carriageway(reference, list(sections), blocks, lanes, width)


def two_way_road(
    road_map: RoadMap,
    reference: Polyline,
    sections: Sequence[tuple[int, int]],
    n_forward: int,
    n_backward: int,
    width: float,
    speed_limit: float | None,
) -> tuple[Carriageway, Carriageway]:
    """Build a road with n_forward lanes right of `reference` and n_backward oncoming lanes left of it."""
    forward = carriageway(road_map, reference, sections, n_forward, width, speed_limit)
    last = len(reference.points) - 1
    mirrored = [(last - end, last - start) for start, end in reversed(sections)]
    backward = carriageway(road_map, reference.reversed(), mirrored, n_backward, width, speed_limit)
    return forward, backward
