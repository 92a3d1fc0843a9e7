"""The rules page's content: each metric version, its subscores in words, its formula and weights, what it
reproduces, and how the board forms and ranks an entry.

Everything numeric comes from the versions' data (`scorer.versions`): the formula is written from a version's
multiplier and weighted rows, so the page cannot drift from what the engine computes. The sentences here only
say in words what each subscore and each of a version's structural choices means.
"""

from __future__ import annotations

from dataclasses import dataclass

from scorer.ec_undefined import UNPAIRED
from scorer.trajectory import SCORING_POSES
from scorer.versions import (
    METRIC_LABELS,
    METRIC_NAMES,
    OFFICIAL_REPOSITORY,
    VERSIONS,
    MetricVersion,
)

SIMULATED_STEPS = SCORING_POSES + 1  # 4 s at 10 Hz, the initial state included

PAPERS = (
    (
        "NAVSIM: Data-Driven Non-Reactive Autonomous Vehicle Simulation and Benchmarking (NeurIPS 2024)",
        "https://arxiv.org/abs/2406.15349",
    ),
    (
        "Pseudo-Simulation for Autonomous Driving (NAVSIM v2, EPDMS and the two-stage benchmark)",
        "https://arxiv.org/abs/2506.04218",
    ),
)

# Each result column in words: what the subscore rewards and how it is measured (4 s, 10 Hz simulation).
METRIC_MEANINGS = {
    "no_at_fault_collisions": "1 without a collision the ego is to blame for; an at-fault collision makes it "
    "0 with a vehicle, pedestrian or cyclist, 0.5 with a static object",
    "drivable_area_compliance": "1 while the ego's corners stay on the drivable area (road, car park, "
    "intersection), 0 once one leaves it",
    "driving_direction_compliance": "how far the ego drives against the traffic flow of its lane over 1 s: "
    "1 up to 2 m, 0.5 up to 6 m, 0 beyond",
    "traffic_light_compliance": "1 unless the ego enters a lane connector whose light is red, then 0",
    "ego_progress": "the distance the ego makes along the route, as a fraction of what the PDM-Closed "
    "reference planner makes (progress under 5 m for both counts as full)",
    "time_to_collision_within_bound": "1 unless, at some step, the ego pushed ahead at its speed and "
    "heading for up to 0.9 s would touch an object in front of it, then 0",
    "comfort": "1 if the trajectory's accelerations, jerks, yaw rates and yaw accelerations stay within "
    "nuPlan's comfort bounds, else 0",
    "lane_keeping": "0 if the ego stays more than 0.5 m off its lane's centreline for over 2 s in a row "
    "(not counted inside intersections), else 1",
    "history_comfort": "comfort measured over the logged past and the planned future together: 0 where "
    "the plan breaks the motion the car had",
    "two_frame_extended_comfort": "1 if the plan agrees with the plan made at the log's frame 0.5 s "
    "earlier (RMS of the differences of acceleration, jerk, yaw rate and yaw acceleration within bounds); "
    f"undefined where there is no such frame ({UNPAIRED}), and then its weight drops out",
    "score": "the entry's score: the product of the multipliers times the weighted mean of the rest, per "
    "token, then the mean over tokens",
}


@dataclass(frozen=True)
class Subscore:
    """A subscore as the rules page and the board headers name it."""

    column: str
    label: str
    name: str
    meaning: str

    @property
    def anchor(self) -> str:
        """Return the rules page's section of this subscore."""
        return f"metric-{self.label}"


@dataclass(frozen=True)
class VersionRules:
    """One metric version as the rules page shows it."""

    name: str
    score_label: str
    formula: str
    multipliers: tuple[Subscore, ...]
    weighted: tuple[tuple[Subscore, float], ...]
    notes: tuple[str, ...]
    official_code: str
    official_script: str
    script_url: str
    published_by_default: bool

    @property
    def anchor(self) -> str:
        """Return the rules page's section of this version."""
        return f"version-{self.name}"


def _column(row: str) -> str:
    """Return the result column of a scorer row (the engine's module, imported when the rules are first read)."""
    from scorer.pdm_scorer import RESULT_COLUMN_OF_ROW

    return RESULT_COLUMN_OF_ROW[row]


def subscore(column: str) -> Subscore:
    """Return the words for a result column."""
    return Subscore(column, METRIC_LABELS[column], METRIC_NAMES[column], METRIC_MEANINGS[column])


SUBSCORES = tuple(subscore(column) for column in METRIC_LABELS)


def _weighted(version: MetricVersion) -> tuple[tuple[Subscore, float], ...]:
    rows = [(subscore(_column(row)), weight) for row, weight in version.evaluation.weighted_rows]
    if version.two_frame_extended_comfort_weight is not None:
        rows.append((subscore("two_frame_extended_comfort"), version.two_frame_extended_comfort_weight))
    return tuple(rows)


def formula(version: MetricVersion) -> str:
    """Return a version's per-token score in symbols: the product of its multipliers times the weighted mean
    of its weighted subscores, written from its rows and weights."""
    multipliers = [METRIC_LABELS[_column(row)] for row in version.evaluation.multiplier_rows]
    weighted = _weighted(version)
    total = sum(weight for _, weight in weighted)
    terms = " + ".join(f"{weight:g}·{item.label}" for item, weight in weighted)
    return f"{version.score_label} = {' × '.join(multipliers)} × ({terms}) / {total:g}"


def _notes(version: MetricVersion) -> tuple[str, ...]:
    """Return, in words, what the version's structural choices do to its numbers (one per choice it makes)."""
    config = version.evaluation
    steps = config.ttc_evaluated_steps
    notes = [
        f"DDC in the score: {version.ddc_role}.",
        "EP is 0 wherever a multiplier fails (progress masked by the multipliers)."
        if config.progress_normalisation == "masked"
        else "EP is the raw progress over the reference's, clipped to [0, 1]; a failing multiplier does not zero it.",
        "TTC is checked at every one of the 41 simulated steps (0 to 4 s)."
        if steps == SIMULATED_STEPS
        else f"TTC is checked at the first {steps} of the {SIMULATED_STEPS} simulated steps, so that its 0.9 s "
        "projection stays inside the 4 s observed.",
    ]
    if config.ddc_window_axis == "proposal":
        notes.append(
            "DDC's 1 s window is summed over the proposal axis: a devkit bug, reproduced on purpose."
        )
    if config.ddc_excludes_intersections:
        notes.append("DDC leaves out the steps whose centre is inside an intersection.")
    if version.drops_tracks_on_ego:
        notes.append("Tracks whose box touches the ego at t = 0 are dropped from every step (log replay).")
    if version.human_penalty_filter:
        rescored = (
            "and the score is formed from the filtered columns"
            if version.human_filter_rescores
            else "but the score stays the agent's unfiltered one (before NAVSIM's fix of its issue 151)"
        )
        notes.append(
            "Human filter: in every column where the logged human driver also scores 0, the entry gets 1, "
            f"{rescored}."
        )
    if version.reactive_traffic is not None:
        traffic = version.reactive_traffic
        notes.append(
            "Reactive traffic: the vehicles follow their lanes under an IDM policy and react to the ego "
            f"(target {traffic.target_velocity:g} m/s, headway {traffic.headway_time:g} s, "
            f"radius {traffic.radius:g} m)."
        )
    else:
        notes.append("The other agents replay the log (non-reactive).")
    if version.two_stage:
        notes.append(
            "Two stages: each original scene is followed by synthetic scenes, weighted by how close their "
            "start is to where the first-stage plan ends; EC pairs the stages' frames."
        )
    if not version.published_by_default:
        notes.append(
            "Kept to compare with papers published before the fix; the board does not show it by default."
        )
    return tuple(notes)


def version_rules(version: MetricVersion) -> VersionRules:
    """Return a metric version as the rules page shows it."""
    return VersionRules(
        name=version.name,
        score_label=version.score_label,
        formula=formula(version),
        multipliers=tuple(subscore(_column(row)) for row in version.evaluation.multiplier_rows),
        weighted=_weighted(version),
        notes=_notes(version),
        official_code=version.official_code,
        official_script=version.official_script,
        script_url=f"{OFFICIAL_REPOSITORY}/blob/{version.official_ref}/{version.official_script}",
        published_by_default=version.published_by_default,
    )


def all_version_rules() -> list[VersionRules]:
    """Return every registered version's rules, in registry order."""
    return [version_rules(version) for version in VERSIONS.values()]


def header_title(column: str) -> str:
    """Return a board header's explanation: the subscore's full name and what it measures."""
    item = subscore(column)
    return f"{item.label}: {item.name}. {item.meaning[0].upper()}{item.meaning[1:]}."
