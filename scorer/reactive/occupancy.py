"""The IDM's occupancy map, built lazily: each geometry is made and simplified only when a lead search needs it
(docs/engine.md, "Reactive traffic: speed").

NAVSIM's `NavsimIDMAgentManager` keeps a dict name -> geometry (the simulated vehicles in building order, "ego"
after them) and, before every vehicle's lead search, replaces each geometry by its shapely `simplify(1e-5,
preserve_topology=True)`; the search asks which geometries the buffered path ahead meets. Most searches meet
nothing but the vehicle's own geometry, so here an entry holds, besides the function that builds its
geometry, a bound made of capsules (segments with a radius) computed without GEOS from the numbers that
define it, and an envelope around those (cheaper to test, looser): a box lies within the capsule of its long
axis and half its width; a buffered polyline within the capsules of its segments and the buffer's distance,
widened by what GEOS's simplification of a buffer's input line may add (1% of the distance); simplifying a
geometry moves its boundary by at most the tolerance. A geometry whose capsules all stay farther than the
radii (plus a margin) from the path ahead's cannot meet it, so the search needs it only where they come
closer.

A geometry a search needs is built then and simplified as many times as the devkit has simplified it by then
(the rounds since its insertion), stopping early at a fixed point: when `simplify` gives back the same
coordinates in the same structure (`equals_exact` with tolerance 0), every later round gives them back too.
So every geometry a lead search reads is the one the devkit reads, bit for bit, and none is simplified more
than twice; a box (a vehicle's at the start, the ego's) is its own simplification (`box_is_simplified`) and is
not simplified at all. A vehicle standing still gets the same footprint at every step: it is built once.

What is built is shared by the process's simulations: a geometry's key names it (the numbers it is built
from), and every simulation that holds a geometry of that key (the other simulation of the token, or a token
starting from the same recorded traffic: the synthetic scenes of one stage-one frame differ in their ego
alone) reads the same built and simplified shapes and the same answers of the capsule test. GEOS gives the
same coordinates for the same input, so sharing changes no bit; the memos are bounded (least recently
used first out), so a worker's memory does not grow with its tokens.
"""

from __future__ import annotations

import itertools
import math
from collections import OrderedDict
from collections.abc import Callable, Hashable
from dataclasses import dataclass
from functools import partial
from typing import TypeVar

import numpy as np
import shapely

from scorer.reactive import geos
from scorer.reactive.paths import LanePath

SIMPLIFY_TOLERANCE = 1e-5
# Margin (m) on every bound: the bounds hold in real numbers; GEOS's buffers, the simplification and the
# rounding of the paths' interpolation move a boundary by far less.
BOUND_SLACK = 1e-3
# GEOS simplifies a buffer's input line on the buffered side by up to this fraction of the buffer distance
# (`BufferParameters` simplify factor): the buffer may reach that much farther than the distance; twice it.
BUFFER_REACH = 1.02

# Capsules: per segment its x0, y0, x1, y1 and a radius, in Python floats: the pre-check runs per lead
# search on a few dozen segments, where numpy's per-call cost outweighs its arithmetic.
Capsule = tuple[float, float, float, float, float]
Capsules = list[Capsule]
Envelope = tuple[float, float, float, float]  # min x, min y, max x, max y
Bound = tuple[Capsules, list[Envelope]]  # capsules holding a geometry and the envelope of each
T = TypeVar("T")
# A box is its own simplification where each corner lies farther than this many tolerances from the diagonal
# between its neighbours (`box_is_simplified`).
BOX_SIMPLIFY_MARGIN = 1000.0
# Where the capsule test's own distance decides (`_end_within`): beyond a billionth of the reach, Python's
# hypot and numpy's (each within an ulp of the true distance) agree on the side.
HYPOT_TIE = 1e-9


def _segment_bound(path: LanePath, radius: float) -> Bound:
    """Return the capsules of the path's segments between consecutive vertices with `radius`, and their
    envelopes (memoised: the searches of a path read slices of them)."""
    return _SEGMENTS.get_or_make(
        (path.identity, radius), lambda: bound_of([(*segment, radius) for segment in path.segments])
    )


def path_to_go_bound(path: LanePath, progress: float, distance: float) -> Bound:
    """Return the capsules holding the buffer at `distance` of `path.to_go(progress)`: its segments."""
    radius = distance * BUFFER_REACH
    start, first = path.to_go_parts(progress)
    capsules, envelopes = _segment_bound(path, radius)
    if start is None:
        return capsules[first:], envelopes[first:]
    head = (*start, *path.vertices[first], radius)
    return [head, *capsules[first:]], [_envelope(head), *envelopes[first:]]


def path_between_bound(path: LanePath, start: float, end: float, distance: float) -> Bound:
    """Return the capsules holding the buffer at `distance` of `path.between(start, end)`: its segments."""
    radius = distance * BUFFER_REACH
    ends, first, last = path.between_parts(start, end)
    capsules, envelopes = _segment_bound(path, radius)
    if ends is None:
        return capsules[first:last], envelopes[first:last]
    start_point, end_point = ends
    if last < first:
        alone = (*start_point, *end_point, radius)
        return [alone], [_envelope(alone)]
    head = (*start_point, *path.vertices[first], radius)
    tail = (*path.vertices[last], *end_point, radius)
    return (
        [head, *capsules[first:last], tail],
        [_envelope(head), *envelopes[first:last], _envelope(tail)],
    )


def box_capsule(x: float, y: float, heading: float, length: float, width: float) -> Capsule:
    """Return the capsule holding a box: its long axis and half its width. The axis turned by Python's cosine
    and sine, not numpy's that place the box's corners (`box_trigonometry`): they differ by an ulp or so, which
    moves the capsule by about 1e-15 m per metre of the box, nothing against `BOUND_SLACK`; and numpy's cost a
    few microseconds for every heading not met before, most of them for boxes never built."""
    cos, sin = math.cos(heading), math.sin(heading)
    half_x, half_y = length / 2 * cos, length / 2 * sin
    return (x - half_x, y - half_y, x + half_x, y + half_y, width / 2)


def _envelope(capsule: Capsule) -> Envelope:
    """Return the envelope of a capsule, widened by the slack."""
    x0, y0, x1, y1, radius = capsule
    reach = radius + BOUND_SLACK
    low_x, high_x = (x0, x1) if x0 <= x1 else (x1, x0)
    low_y, high_y = (y0, y1) if y0 <= y1 else (y1, y0)
    return low_x - reach, low_y - reach, high_x + reach, high_y + reach


def _end_within(
    x: float, y: float, x0: float, y0: float, dx: float, dy: float, squared: float, reach: float
) -> bool:
    """Return whether the point (x, y) lies within `reach` of the segment from (x0, y0) by (dx, dy) (its
    squared length `squared`), measured as numpy measured it: hypot of the offset from the clamped
    projection; numpy's hypot where the distance is a near-tie."""
    along = (x - x0) * dx + (y - y0) * dy
    fraction = along / (squared if squared > 0 else 1.0)
    # min(max(fraction, 0.0), 1.0) as comparisons (a NaN and -0.0 pass as through those): runs per capsule pair.
    if fraction < 0.0:
        fraction = 0.0
    elif fraction > 1.0:
        fraction = 1.0
    off_x, off_y = x - x0 - fraction * dx, y - y0 - fraction * dy
    distance = math.hypot(off_x, off_y)
    if abs(distance - reach) <= reach * HYPOT_TIE:
        distance = float(np.hypot(off_x, off_y))
    return distance <= reach


def capsules_meet(first: Capsule, second: Capsule, origin_x: float, origin_y: float) -> bool:
    """Return whether two capsules come within the slack of each other: the segments cross (strictly;
    touching and overlapping ones have an end on the other) or an end lies within the two radii of the other
    segment. Measured from a local origin (the first capsule's start of the search), so that the crossing
    test's products stay well within float precision.

    Most pairs whose envelopes meet do not meet (six in seven on the benchmark's split), and nearly all of
    those (97%) have one segment wholly on one side of the other's line, farther from it than the reach: the
    crossing test's cross products, over the line's length, are those distances, so such a pair is refused
    before the four end tests. Every point of that segment lies at least that far from the line, hence from
    the other segment: the pair meets in no case the end tests would accept (the margin of a billionth of
    the reach covers the products' rounding, about 1e-13 m, as in `_end_within`), and the bounds' argument,
    which `BOUND_SLACK` carries, is unchanged."""
    ax0, ay0, ax1, ay1 = first[0] - origin_x, first[1] - origin_y, first[2] - origin_x, first[3] - origin_y
    bx0, by0, bx1, by1 = (
        second[0] - origin_x,
        second[1] - origin_y,
        second[2] - origin_x,
        second[3] - origin_y,
    )
    adx, ady, bdx, bdy = ax1 - ax0, ay1 - ay0, bx1 - bx0, by1 - by0
    # Twice the signed areas of each segment's ends with the other segment: its ends' sides of that line.
    b0_across, b1_across = adx * (by0 - ay0) - ady * (bx0 - ax0), adx * (by1 - ay0) - ady * (bx1 - ax0)
    a0_across, a1_across = bdx * (ay0 - by0) - bdy * (ax0 - bx0), bdx * (ay1 - by0) - bdy * (ax1 - bx0)
    b_sides, a_sides = b0_across * b1_across, a0_across * a1_across
    if b_sides < 0 and a_sides < 0:
        return True
    reach = first[4] + second[4] + BOUND_SLACK
    a_squared, b_squared = adx * adx + ady * ady, bdx * bdx + bdy * bdy
    beyond = reach * (1.0 + HYPOT_TIE)
    if b_sides > 0 and min(abs(b0_across), abs(b1_across)) > beyond * math.sqrt(a_squared):
        return False
    if a_sides > 0 and min(abs(a0_across), abs(a1_across)) > beyond * math.sqrt(b_squared):
        return False
    return (
        _end_within(bx0, by0, ax0, ay0, adx, ady, a_squared, reach)
        or _end_within(bx1, by1, ax0, ay0, adx, ady, a_squared, reach)
        or _end_within(ax0, ay0, bx0, by0, bdx, bdy, b_squared, reach)
        or _end_within(ax1, ay1, bx0, by0, bdx, bdy, b_squared, reach)
    )


def bound_of(capsules: Capsules) -> Bound:
    """Return capsules with their envelopes."""
    return capsules, [_envelope(capsule) for capsule in capsules]


def envelope_of(envelopes: list[Envelope]) -> Envelope:
    """Return the envelope of the union of capsules, given their envelopes."""
    if len(envelopes) == 1:  # a box's (the ego's at every step): its own
        return envelopes[0]
    low_x, low_y, high_x, high_y = zip(*envelopes, strict=True)
    return min(low_x), min(low_y), max(high_x), max(high_y)


def box_is_simplified(length: float, width: float) -> bool:
    """Return whether GEOS's `simplify(box, SIMPLIFY_TOLERANCE, preserve_topology=True)` of a box of `length` x
    `width` (a polygon of 4 corners, `box_polygon`'s or the ego's) surely gives back the same coordinates in the
    same order, and so does every further round.

    GEOS's topology-preserving simplifier runs Douglas-Peucker on the ring, from its first corner to the same
    corner again: the vertex farthest from that corner is the opposite one (at the diagonal's length), kept;
    each of the two others lies at the height length * width / diagonal from the diagonal between its
    neighbours, kept where that exceeds the tolerance; the ring's first corner is dropped only where it lies
    within the tolerance of the segment between its neighbours, the other diagonal, at the same height. The
    corners' rounding moves these distances by ulps of the coordinates, nothing against a margin of a thousand
    tolerances (1 cm)."""
    return length * width / math.hypot(length, width) > BOX_SIMPLIFY_MARGIN * SIMPLIFY_TOLERANCE


class _Simplified:
    """A geometry and its simplifications, round by round, up to a fixed point."""

    def __init__(self, build: Callable[[], shapely.Geometry], fixed: bool) -> None:
        self._build = build
        self._rounds: list[shapely.Geometry] = []  # the geometry after 0, 1, ... rounds
        self._fixed = fixed  # the last one is a fixed point of the simplification

    def after(self, rounds: int) -> shapely.Geometry:
        """Return the geometry simplified `rounds` times."""
        if not self._rounds:
            self._rounds.append(self._build())
        while len(self._rounds) <= rounds and not self._fixed:
            last = self._rounds[-1]
            simplified = geos.simplify(last, SIMPLIFY_TOLERANCE)
            self._fixed = geos.equals_exactly(simplified, last)
            self._rounds.append(simplified)
        return self._rounds[min(rounds, len(self._rounds) - 1)]


class Recent(OrderedDict[Hashable, T]):
    """A dict of at most `limit` items that forgets the least recently used."""

    def __init__(self, limit: int) -> None:
        super().__init__()
        self._limit = limit

    def get_or_make(self, key: Hashable, make: Callable[[], T]) -> T:
        """Return the value of `key`, made (and kept) if absent."""
        value = self.get(key)
        if value is None:
            value = make()
            self.put(key, value)
        else:
            self.move_to_end(key)
        return value

    def put(self, key: Hashable, value: T) -> None:
        """Keep `value` for `key`, forgetting the least recently used beyond the limit."""
        self[key] = value
        if len(self) > self._limit:
            self.popitem(last=False)


# What tokens of one process share: a key names one geometry wherever it appears (the same vehicle in
# another simulation of the scene, or of a scene that starts from the same recorded traffic, as the
# synthetic scenes of one stage-one frame do), and the same question gets the same answer. Bounded, so
# that a worker's memory does not grow with its tokens.
_SHAPES: Recent[_Simplified] = Recent(2048)  # by key identity
_ANSWERS: Recent[list[str]] = Recent(8192)
# Each key's identity, a number no other key ever gets: a memo keyed by identities hashes integers, not the
# key's numbers (a forgotten key gets a new identity, and what was kept under its old one is not read).
_IDENTITIES: Recent[int] = Recent(4096)
_NEXT_IDENTITY = itertools.count()
_SEGMENTS: Recent[Bound] = Recent(1024)  # by path and radius


@dataclass(slots=True)
class _Entry:
    key: Hashable  # equal keys: the same geometry, built alike, in every simulation of the process
    envelope: Envelope  # holds the geometry
    bound: Callable[[], Bound]
    build: Callable[[], shapely.Geometry]
    inserted_round: int
    fixed: bool  # what `build` gives is its own simplification
    _identity: int | None = None
    _simplified: _Simplified | None = None
    _capsules: tuple[Capsules, list[Envelope], Envelope] | None = None

    def identity(self) -> int:
        """Return the key's identity (looked up only when a search first needs it: most keys never are)."""
        if self._identity is None:
            self._identity = _IDENTITIES.get_or_make(self.key, _NEXT_IDENTITY.__next__)
        return self._identity

    def simplified(self) -> _Simplified:
        """Return the shared simplifications of the key's geometry, made from `build` where no other holds
        them."""
        if self._simplified is None:
            self._simplified = _SHAPES.get_or_make(
                self.identity(), partial(_Simplified, self.build, self.fixed)
            )
        return self._simplified

    def capsules(self) -> tuple[Capsules, list[Envelope], Envelope]:
        """Return the capsules holding the geometry, their envelopes and the envelope of them all (the entry's
        own: computed in microseconds, most geometries are asked about in one simulation only)."""
        if self._capsules is None:
            capsules, envelopes = self.bound()
            self._capsules = capsules, envelopes, envelope_of(envelopes)
        return self._capsules


class LazyOccupancy:
    """The occupancy map of one simulation, in the devkit's dict order."""

    def __init__(self) -> None:
        self._entries: dict[str, _Entry] = {}
        self._rounds = 0

    def set(
        self,
        name: str,
        key: Hashable,
        envelope: Envelope,
        bound: Callable[[], Bound],
        build: Callable[[], shapely.Geometry],
        fixed: bool = False,
    ) -> None:
        """Insert or replace the geometry of `name`, held within `envelope` and within the capsules `bound`
        gives (a replaced name keeps its place, as in a dict); `fixed`: what `build` gives is its own
        simplification, every round. `key` names the geometry process-wide: what
        was built and simplified of a geometry of the same key (a vehicle standing still, the same vehicle in
        another simulation) serves again: the devkit builds the same coordinates anew and simplifies them from
        the start, and so do its rounds here."""
        previous = self._entries.get(name)
        if previous is not None and previous.key == key:
            previous.inserted_round = self._rounds
        else:
            self._entries[name] = _Entry(key, envelope, bound, build, self._rounds, fixed)

    def remove(self, name: str) -> None:
        """Remove `name` (a vehicle that left the radius)."""
        del self._entries[name]

    def simplify_round(self) -> None:
        """Count one devkit round of simplifying every geometry (before each lead search)."""
        self._rounds += 1

    def names(self) -> list[str]:
        """Return every name, in the devkit's order."""
        return list(self._entries)

    def around(self, envelope: Envelope, excluded: str) -> list[str]:
        """Return the names but `excluded` whose geometry's envelope meets `envelope`, in the devkit's order."""
        # The envelopes' overlap test (touching counts) written out: this runs per lead search and entry.
        low_x, low_y, high_x, high_y = envelope
        return [
            name
            for name, entry in self._entries.items()
            if name != excluded
            and (held := entry.envelope)[0] <= high_x
            and low_x <= held[2]
            and held[1] <= high_y
            and low_y <= held[3]
        ]

    def near(self, names: list[str], shape: Hashable, bound: Callable[[], Bound]) -> list[str]:
        """Return those of `names` (`around` a shape) whose geometry may meet the shape (`shape` names it
        process-wide) held within the capsules `bound` gives, in the devkit's order."""
        # The same shape asked about the same geometries has the same answer.
        question = (shape, *names, *[self._entries[name].identity() for name in names])
        return _ANSWERS.get_or_make(question, lambda: self._near(names, *bound()))

    def _near(self, names: list[str], capsules: Capsules, pieces: list[Envelope]) -> list[str]:
        # The (piece, owner, capsule) triples whose envelopes meet, as numpy's (piece, capsule) grid listed
        # them: the first piece among them is the origin every capsule test measures from.
        held = [self._entries[name].capsules() for name in names]
        # One comprehension, the envelopes' overlap test written out: this is most of the pre-check's Python.
        # A piece meets a capsule's envelope only where it meets the envelope of all of the owner's: tested
        # first.
        meeting_envelopes = [
            (index, owner, capsule)
            for owner, (owned, envelopes, (low_x, low_y, high_x, high_y)) in enumerate(held)
            for index, (piece_low_x, piece_low_y, piece_high_x, piece_high_y) in enumerate(pieces)
            if piece_low_x <= high_x
            and low_x <= piece_high_x
            and piece_low_y <= high_y
            and low_y <= piece_high_y
            for capsule, (other_low_x, other_low_y, other_high_x, other_high_y) in zip(
                owned, envelopes, strict=True
            )
            if piece_low_x <= other_high_x
            and other_low_x <= piece_high_x
            and piece_low_y <= other_high_y
            and other_low_y <= piece_high_y
        ]
        if not meeting_envelopes:
            return []
        origin_x, origin_y = capsules[min(index for index, _, _ in meeting_envelopes)][:2]
        meeting: set[int] = set()
        for index, owner, capsule in meeting_envelopes:
            if owner not in meeting and capsules_meet(capsules[index], capsule, origin_x, origin_y):
                meeting.add(owner)
        return [name for position, name in enumerate(names) if position in meeting]

    def geometry(self, name: str) -> shapely.Geometry:
        """Return the geometry of `name` as the devkit holds it now: built, and simplified once per round."""
        entry = self._entries[name]
        return entry.simplified().after(self._rounds - entry.inserted_round)
