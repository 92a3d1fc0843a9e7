"""Metric versions as data: one frozen config per NAVSIM release, in one registry
(docs/engine.md, "Metric versions").

Adding a version means adding a `MetricVersion` here; code branches only where a metric truly differs,
and then on a field of this config (e.g. `ddc_window_axis`), never on the version name.

The configs are named tuples rather than frozen dataclasses: as immutable and compared by value alike, and
built in a tenth of the time at import, which every command's start-up pays (docs/engine.md, "Start-up").
"""

# Annotations are evaluated, not kept as strings (no `from __future__ import annotations`): a named tuple
# compiles each string annotation of its fields at import (docs/engine.md, "Start-up").
from collections.abc import Iterable
from enum import StrEnum
from typing import Literal, NamedTuple

DdcWindowAxis = Literal["proposal", "time"]
ProgressNormalisation = Literal["masked", "clipped"]


class VersionName(StrEnum):
    """The name of a registered metric version: the one type the API, the CLI, the workers and the database
    use, so that an unknown name is refused (422, a CLI usage error) wherever it comes in."""

    V1_0 = "v1.0"
    V1_1 = "v1.1"
    V2_2 = "v2.2"
    V2_2_PREFIX = "v2.2-prefix"
    V2_2_TWO_STAGE = "v2.2-two-stage"


DEFAULT_VERSION = VersionName.V1_1  # NAVSIM's current release: what a leaderboard shows unless asked
OFFICIAL_REPOSITORY = "https://github.com/autonomousvision/navsim"


class ScorerConfig(NamedTuple):
    """The devkit's `PDMScorerConfig` of a release, with the rows it scores and the structural choices that
    changed between releases.

    Rows carry the devkit's own names (`MultiMetricIndex`, `WeightedMetricIndex`) in its order; which rows a
    version has decides which metrics are computed (`scorer.pdm_scorer`).
    """

    multiplier_rows: tuple[str, ...]
    weighted_rows: tuple[tuple[str, float], ...]  # (row, weight)
    driving_direction_horizon: float = 1.0
    driving_direction_compliance_threshold: float = 2.0
    driving_direction_violation_threshold: float = 6.0
    stopped_speed_threshold: float = 5e-3
    progress_distance_threshold: float = 5.0
    lane_keeping_deviation_limit: float = 0.5  # m
    lane_keeping_horizon_window: float = 2.0  # s
    # v1.0 sums the DDC window over the proposal axis (a devkit bug reproduced on purpose).
    ddc_window_axis: DdcWindowAxis = "time"
    # v2 leaves out the steps whose centre is inside an intersection from DDC's window.
    ddc_excludes_intersections: bool = False
    # v1 zeroes EP where a multiplier fails; v2 clips raw / normaliser to [0, 1] and never zeroes it.
    progress_normalisation: ProgressNormalisation = "masked"
    # TTC's time indices: v2 stops at 40 - 9 so that the 0.9 s projection stays inside its 4 s observation.
    ttc_evaluated_steps: int = 41

    @property
    def weights(self) -> dict[str, float]:
        """Return the weight of each weighted row, by name."""
        return dict(self.weighted_rows)


class IdmTraffic(NamedTuple):
    """NAVSIM's reactive traffic (`NavsimIDMTrafficAgents`, `navsim_IDM_traffic_agents.yaml` at v2.2): the
    current frame's vehicles follow their starting lane or connector under an IDM and react to the ego
    (`scorer.reactive`; docs/engine.md, "Reactive traffic")."""

    target_velocity: float = 10.0  # m/s where the segment has no speed limit (leaked between vehicles)
    min_gap_to_lead_agent: float = 1.0  # m
    headway_time: float = 1.5  # s
    accel_max: float = 1.0  # m/s²
    decel_max: float = 2.0  # m/s²
    radius: float = 100.0  # m around the ego's rear axle; a vehicle beyond it leaves the simulation for good
    idm_snap_threshold: float = 3.0  # m, the largest distance from the baseline a vehicle is snapped over
    add_open_loop_parked_vehicles: bool = True  # vehicles that are not simulated stay at their recorded pose


class MetricVersion(NamedTuple):
    """A NAVSIM metric release: the evaluation scorer, PDM-Closed's internal scorer, what the metric cache
    observes and the result columns."""

    name: VersionName
    evaluation: ScorerConfig  # the scoring yaml
    planner: ScorerConfig  # PDMScorerConfig() dataclass defaults, used inside PDM-Closed
    result_columns: tuple[str, ...]  # the result CSV's columns, in its order
    official_code: str  # the devkit release whose results the version reproduces
    official_ref: str  # the tag or commit of OFFICIAL_REPOSITORY that code is
    official_script: str  # the devkit's script there whose numbers the version reproduces
    score_label: str = "PDMS"  # the score's name in the papers
    average_row: str = "average"  # the token column of the result CSV's mean row
    observation_frames: int = 10  # 2 Hz frames after the current one in the observation (x 5 steps at 10 Hz)
    # v2's non-reactive traffic drops every track whose box touches the ego's at t = 0, from every step.
    drops_tracks_on_ego: bool = False
    # v2: where the logged human also scores 0 in a column, the agent gets 1 there (original scenes only).
    human_penalty_filter: bool = False
    # v2's two-frame extended comfort between adjacent tokens of a log; None where the version has none.
    two_frame_extended_comfort_weight: float | None = None
    # v2's reactive traffic in place of the log replay (None): the vehicles react to the scored trajectory.
    reactive_traffic: IdmTraffic | None = None
    # NAVSIM's fix of its issue 151 (commit 359c7f7): the score is computed from the columns after the human filter.
    # Before it (False), the filter sets the columns shown, but the score stays the agent's unfiltered one.
    human_filter_rescores: bool = True
    # The version whose metric cache this one reads, when the two caches are the same (None: its own).
    shares_cache_of: VersionName | None = None
    # Scored and shown by the board by default; a variant kept for comparison with papers is not.
    published_by_default: bool = True
    # NAVSIM v2's two-stage EPDMS: scored over a split's stage mapping (`scorer.two_stage`), whose pairs give
    # the two-frame comfort, the synthetic scenes weighted by where the stage-one plans end.
    two_stage: bool = False

    @property
    def ddc_role(self) -> str:
        """How driving direction compliance enters the score, in words for tables."""
        if "driving_direction" in self.evaluation.multiplier_rows:
            return "multiplier"
        weight = self.evaluation.weights["driving_direction"]
        return "logged, not weighted" if weight == 0 else f"weight {weight:g}"


_V1_0_SCORER = ScorerConfig(
    multiplier_rows=("no_collision", "drivable_area", "driving_direction"),
    weighted_rows=(("progress", 5.0), ("ttc", 5.0), ("comfortable", 2.0)),
    ddc_window_axis="proposal",
)
_V1_1_SCORER = ScorerConfig(
    multiplier_rows=("no_collision", "drivable_area"),
    weighted_rows=(("progress", 5.0), ("ttc", 5.0), ("comfortable", 2.0), ("driving_direction", 0.0)),
)
# pdm_scorer.yaml of v2.2; its two-frame extended comfort (weight 2) is joined per split, not per token.
_V2_2_SCORER = ScorerConfig(
    multiplier_rows=("no_collision", "drivable_area", "traffic_light_compliance", "driving_direction"),
    weighted_rows=(("progress", 5.0), ("ttc", 5.0), ("lane_keeping", 2.0), ("history_comfort", 2.0)),
    ddc_excludes_intersections=True,
    progress_normalisation="clipped",
    ttc_evaluated_steps=32,
)

# The devkit v1.0 result CSV column order; v1.1 moves DDC after comfort.
METRIC_COLUMNS = (
    "no_at_fault_collisions",
    "drivable_area_compliance",
    "driving_direction_compliance",
    "ego_progress",
    "time_to_collision_within_bound",
    "comfort",
    "score",
)
# The official one-stage CSV of v2.2.
EPDMS_COLUMNS = (
    "no_at_fault_collisions",
    "drivable_area_compliance",
    "driving_direction_compliance",
    "traffic_light_compliance",
    "ego_progress",
    "time_to_collision_within_bound",
    "lane_keeping",
    "history_comfort",
    "two_frame_extended_comfort",
    "score",
)

# Short names as in the NAVSIM papers, for tables a person reads; the devkit's names stay in data and APIs.
METRIC_LABELS = {
    "no_at_fault_collisions": "NC",
    "drivable_area_compliance": "DAC",
    "driving_direction_compliance": "DDC",
    "traffic_light_compliance": "TLC",
    "ego_progress": "EP",
    "time_to_collision_within_bound": "TTC",
    "comfort": "C",
    "lane_keeping": "LK",
    "history_comfort": "HC",
    "two_frame_extended_comfort": "EC",
    "score": "PDMS",
}
# Their names in full, as the papers spell them out, for the people reading the short ones.
METRIC_NAMES = {
    "no_at_fault_collisions": "no at-fault collisions",
    "drivable_area_compliance": "drivable area compliance",
    "driving_direction_compliance": "driving direction compliance",
    "traffic_light_compliance": "traffic light compliance",
    "ego_progress": "ego progress",
    "time_to_collision_within_bound": "time to collision within bound",
    "comfort": "comfort",
    "lane_keeping": "lane keeping",
    "history_comfort": "history comfort",
    "two_frame_extended_comfort": "two-frame extended comfort",
    "score": "PDM score",
}

# NAVSIM v2.2's one-stage EPDMS, and the base of its pre-fix variant below.
_V2_2 = MetricVersion(
    name=VersionName.V2_2,
    evaluation=_V2_2_SCORER,
    planner=_V2_2_SCORER,
    result_columns=EPDMS_COLUMNS,
    official_code="NAVSIM v2.2 (tag v2.2, commit 359c7f7, one-stage, non-reactive, human filter on)",
    official_ref="v2.2",
    official_script="navsim/planning/script/run_pdm_score_one_stage.py",
    score_label="EPDMS",
    average_row="average_all_frames",
    observation_frames=8,
    drops_tracks_on_ego=True,
    human_penalty_filter=True,
    two_frame_extended_comfort_weight=2.0,
)

VERSIONS: dict[VersionName, MetricVersion] = {
    VersionName.V1_0: MetricVersion(
        name=VersionName.V1_0,
        evaluation=_V1_0_SCORER,
        planner=_V1_0_SCORER._replace(progress_distance_threshold=0.1),
        result_columns=METRIC_COLUMNS,
        official_code="NAVSIM v1.0 (tag v1.0), nuplan-devkit v1.2",
        official_ref="v1.0",
        official_script="navsim/planning/script/run_pdm_score.py",
    ),
    VersionName.V1_1: MetricVersion(
        name=VersionName.V1_1,
        evaluation=_V1_1_SCORER,
        planner=_V1_1_SCORER,
        result_columns=(
            "no_at_fault_collisions",
            "drivable_area_compliance",
            "ego_progress",
            "time_to_collision_within_bound",
            "comfort",
            "driving_direction_compliance",
            "score",
        ),
        official_code="NAVSIM v1.1 (tag v1.1), nuplan-devkit v1.2",
        official_ref="v1.1",
        official_script="navsim/planning/script/run_pdm_score.py",
    ),
    VersionName.V2_2: _V2_2,
    # The v2.2 tree before the human-filter fix, whose results papers published before 2025-09-29 report: the same
    # cache (the fix changes how a row's score is formed, nothing cached), the score unfiltered.
    VersionName.V2_2_PREFIX: _V2_2._replace(
        name=VersionName.V2_2_PREFIX,
        official_code=(
            "NAVSIM v2.2 before the human-filter fix (commit 8021f918b907360ac5ae6fbc252b5f96f04db966, the parent of "
            "359c7f7; one-stage, non-reactive, human filter on, score unfiltered)"
        ),
        official_ref="8021f918b907360ac5ae6fbc252b5f96f04db966",
        human_filter_rescores=False,
        shares_cache_of=VersionName.V2_2,
        published_by_default=False,
    ),
    # The scoring of each token of navhard's two stages: v2.2's scorer with the vehicles reacting to the scored
    # trajectory (and, for the human filter, to the logged human); no track is dropped at t = 0.
    VersionName.V2_2_TWO_STAGE: MetricVersion(
        name=VersionName.V2_2_TWO_STAGE,
        evaluation=_V2_2_SCORER,
        planner=_V2_2_SCORER,
        result_columns=EPDMS_COLUMNS,
        official_code=(
            "NAVSIM v2.2 (tag v2.2, commit 359c7f7, run_pdm_score_from_submission.py: two-stage, reactive IDM "
            "traffic, human filter on)"
        ),
        official_ref="v2.2",
        official_script="navsim/planning/script/run_pdm_score_from_submission.py",
        score_label="EPDMS",
        average_row="average_all_frames",
        observation_frames=8,
        human_penalty_filter=True,
        two_frame_extended_comfort_weight=2.0,
        reactive_traffic=IdmTraffic(),
        two_stage=True,
    ),
}


# Every version's result columns, in result-table order: what the board stores per token and per entry.
ALL_RESULT_COLUMNS = tuple(
    sorted(
        {column for version in VERSIONS.values() for column in version.result_columns},
        key=list(METRIC_LABELS).index,
    )
)


def get_version(name: str) -> MetricVersion:
    """Return the registered metric version `name`, or raise with the list of known versions."""
    try:
        return VERSIONS[VersionName(name)]
    except ValueError:
        raise ValueError(f"unknown metric version {name!r}; known: {', '.join(VERSIONS)}") from None


def cache_source(name: str) -> VersionName:
    """Return the version whose metric cache `name` reads: its own, or the one it shares."""
    version = get_version(name)
    return version.shares_cache_of or version.name


def cached_together(names: Iterable[str]) -> list[VersionName]:
    """Return the versions whose metric caches are built with those of `names`: every version with a cache of
    its own that sees the traffic as one of them does (a version that shares another's cache reads that one).
    One PDM-Closed unroll serves all of them; a reactive version's cache adds a simulation of the human per
    scene (about twice the rest of a scene's cache), so it is built only where a reactive version is asked for."""
    reactive = {get_version(name).reactive_traffic is not None for name in names}
    return [
        name
        for name, version in VERSIONS.items()
        if version.shares_cache_of is None and (version.reactive_traffic is not None) in reactive
    ]


# The versions whose other agents replay the log and that the board publishes by default: what a one-stage
# split is cached and scored under.
LOG_REPLAY_VERSIONS = tuple(
    name for name in cached_together([DEFAULT_VERSION]) if VERSIONS[name].published_by_default
)
# The versions of NAVSIM's two-stage EPDMS: what a two-stage split is cached and scored under.
TWO_STAGE_VERSIONS = tuple(
    name for name, version in VERSIONS.items() if version.two_stage and version.published_by_default
)
