"""Metric versions as data: one frozen config per NAVSIM release, in one registry
(docs/engine.md, "Metric versions").

Adding a version means adding a `MetricVersion` here; code branches only where a metric truly differs,
and then on a field of this config (e.g. `ddc_window_axis`), never on the version name.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from enum import StrEnum
from typing import Literal

DdcRole = Literal["multiplier", "weighted"]
DdcWindowAxis = Literal["proposal", "time"]


class VersionName(StrEnum):
    """The name of a registered metric version: the one type the API, the CLI, the workers and the database
    use, so that an unknown name is refused (422, a CLI usage error) wherever it comes in."""

    V1_0 = "v1.0"
    V1_1 = "v1.1"


DEFAULT_VERSION = VersionName.V1_1  # NAVSIM's current release: what a leaderboard shows unless asked


@dataclass(frozen=True)
class ScorerConfig:
    """The devkit's `PDMScorerConfig` plus the two structural DDC choices that changed between releases."""

    progress_weight: float = 5.0
    ttc_weight: float = 5.0
    comfortable_weight: float = 2.0
    driving_direction_weight: float = 0.0
    driving_direction_horizon: float = 1.0
    driving_direction_compliance_threshold: float = 2.0
    driving_direction_violation_threshold: float = 6.0
    stopped_speed_threshold: float = 5e-3
    progress_distance_threshold: float = 5.0
    # v1.0 multiplies by DDC and sums its window over the proposal axis (a devkit bug reproduced on purpose).
    ddc_role: DdcRole = "weighted"
    ddc_window_axis: DdcWindowAxis = "time"


@dataclass(frozen=True)
class MetricVersion:
    """A NAVSIM metric release: the evaluation scorer, PDM-Closed's internal scorer and the result columns."""

    name: VersionName
    evaluation: ScorerConfig  # default_scoring_parameters.yaml
    planner: ScorerConfig  # PDMScorerConfig() dataclass defaults, used inside PDM-Closed
    result_columns: tuple[str, ...]  # PDMResults field order

    @property
    def ddc_role(self) -> str:
        """How driving direction compliance enters the score, in words for tables."""
        if self.evaluation.ddc_role == "multiplier":
            return "multiplier"
        weight = self.evaluation.driving_direction_weight
        return "logged, not weighted" if weight == 0 else f"weight {weight:g}"


_V1_0_SCORER = ScorerConfig(ddc_role="multiplier", ddc_window_axis="proposal")
_V1_1_SCORER = ScorerConfig(ddc_role="weighted", ddc_window_axis="time")

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

# Short names as in the NAVSIM paper, for tables a person reads; the devkit's names stay in data and APIs.
METRIC_LABELS = {
    "no_at_fault_collisions": "NC",
    "drivable_area_compliance": "DAC",
    "driving_direction_compliance": "DDC",
    "ego_progress": "EP",
    "time_to_collision_within_bound": "TTC",
    "comfort": "C",
    "score": "PDMS",
}

VERSIONS: dict[VersionName, MetricVersion] = {
    VersionName.V1_0: MetricVersion(
        name=VersionName.V1_0,
        evaluation=_V1_0_SCORER,
        planner=replace(_V1_0_SCORER, progress_distance_threshold=0.1),
        result_columns=METRIC_COLUMNS,
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
    ),
}


def get_version(name: str) -> MetricVersion:
    """Return the registered metric version `name`, or raise with the list of known versions."""
    try:
        return VERSIONS[VersionName(name)]
    except ValueError:
        raise ValueError(f"unknown metric version {name!r}; known: {', '.join(VERSIONS)}") from None
