"""Request and response bodies of the REST API (pydantic); the OpenAPI docs at /docs are generated from them."""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Annotated, Any, Literal

from pydantic import AfterValidator, AwareDatetime, BaseModel, ConfigDict, Field, HttpUrl, StringConstraints

from scorer.versions import VersionName

SQL_INT_MAX = 2**31 - 1  # PostgreSQL's INTEGER: ids and counts beyond it cannot be stored


def _printable(text: str) -> str:
    if any(ord(character) < 0x20 or ord(character) == 0x7F for character in text):
        raise ValueError("must not contain control characters")
    return text


def _in_utc(value: datetime) -> datetime:
    try:
        return value.astimezone(UTC)
    except OverflowError:
        raise ValueError("out of range once converted to UTC") from None


# A time given by a user: with its time zone (ISO 8601 offset), stored in UTC.
Timestamp = Annotated[AwareDatetime, AfterValidator(_in_utc)]


# Names shown in pages, file names and the audit log (whose target ids hold 64 characters for splits and phases).
TeamName = Annotated[str, StringConstraints(min_length=1, max_length=200), AfterValidator(_printable)]
ObjectName = Annotated[str, StringConstraints(min_length=1, max_length=64), AfterValidator(_printable)]


class Problem(BaseModel):
    token: str | None = Field(description="the token the problem concerns, if any")
    field: str | None = Field(description="the field or key of the file, e.g. predictions[3].poses")
    message: str


class ValidationReport(BaseModel):
    valid: bool
    sha256: str | None = None
    seed_count: int | None = None
    token_count: int | None = None
    problems: list[Problem] = []


class SubmissionAccepted(BaseModel):
    id: int
    status: str
    replayed: bool = Field(
        description="true when an earlier request with the same Idempotency-Key created it"
    )
    url: str


class Seeds(BaseModel):
    count: int
    mean: float
    std: float
    max: float


class SeedResult(BaseModel):
    """One seed's means over a subset, with the provenance of the numbers."""

    seed: int
    score: float | None
    tokens: int
    failed_tokens: int
    engine_version: str
    split_hash: str
    workers: str
    duration_s: float


class SubsetResult(BaseModel):
    """Results of a submission on one subset; the devkit's subscore columns are extra fields."""

    model_config = ConfigDict(extra="allow")

    score: float | None
    seeds: Seeds
    ci95: list[float]
    tokens: int
    failed_tokens: int
    per_seed: list[SeedResult]


class SubmissionOut(BaseModel):
    id: int
    team: str
    phase: str | None
    split: str
    baseline: bool
    status: str = Field(description="queued, running, scored, failed or cancelled")
    progress: int = Field(description="0-100")
    error: str | None = Field(description="sanitised error summary")
    method: str
    authors: str
    institution: str
    country: str
    tech_report_url: str
    code_url: str
    seed_count: int
    token_count: int
    filename: str
    sha256: str
    size_bytes: int
    hidden: bool = Field(description="hidden from the leaderboard by its team")
    admin_hidden: bool = Field(
        description="hidden from the leaderboard by an organiser (the team cannot undo it)"
    )
    disqualified: bool = Field(description="disqualified by an organiser: never on the leaderboard")
    disqualified_reason: str = Field(description="the organiser's reason for the disqualification")
    selected: bool = Field(description="chosen by its team as the final entry of the phase")
    final_refusal: str | None = Field(
        description="why it cannot be the final entry (disqualified, hidden, failed...); null when it can"
    )
    on_leaderboard: list[VersionName] = Field(
        description="the metric versions whose leaderboard of the phase (default subset) shows this entry for "
        "its team: the final entry if it may be shown, else the team's best"
    )
    submitted_at: datetime
    started_at: datetime | None
    finished_at: datetime | None
    results: dict[str, dict[str, SubsetResult]] = Field(description="metric version -> subset -> results")


class AdminSubmissionOut(SubmissionOut):
    team_id: int
    queued_at: datetime = Field(description="when it was last queued: its upload, or its latest re-run")
    run: int
    attempts: int
    worker: str | None
    charged: bool
    failure_kind: str | None
    error_detail: str | None


class ComparableOut(SubmissionOut):
    """An entry a submission may be compared with, token by token."""

    kind: Literal["yours", "published", "baseline"] = Field(
        description="yours: another of the team's; published: an entry of a closed phase, open to all; baseline"
    )


class SubmissionPatch(BaseModel):
    model_config = ConfigDict(extra="forbid")

    method: str | None = Field(None, max_length=300)
    authors: str | None = None
    institution: str | None = Field(None, max_length=300)
    country: str | None = Field(None, max_length=100)
    tech_report_url: HttpUrl | None = None
    code_url: HttpUrl | None = None
    hidden: bool | None = None
    selected: bool | None = Field(None, description="true: this is the team's final entry of the phase")


class TokenRow(BaseModel):
    token: str
    metric_version: VersionName
    seed: int
    valid: bool
    error: str | None
    metrics: dict[str, float | None] = Field(description="the version's result columns; null where undefined")
    detail: dict[str, Any] = Field(
        default_factory=dict,
        description="how the row came about (v2.2: the human filter's overrides, two-frame comfort's partner)",
    )
    ec_undefined: str | None = Field(
        None,
        description="v2.2: why two-frame extended comfort (EC) is undefined on this row; null where it is not",
    )


class StageGroupOut(BaseModel):
    """One group of a two-stage split (a mapping entry), as a seed scored it."""

    original: str = Field(description="the logged frame (orig)")
    previous: str = Field(description="the logged frame 0.5 s before it (prev)")
    original_stage_one: float | None = Field(description="orig's stage-one score")
    original_stage_two: float | None = Field(description="orig's synthetic successors' weighted score (now2)")
    previous_stage_one: float | None = Field(description="prev's stage-one score")
    previous_stage_two: float | None = Field(
        description="prev's synthetic successors' weighted score (prev2)"
    )
    score: float | None = Field(description="(orig stage one x stage two + prev stage one x stage two) / 2")
    weights: dict[str, dict[str, float | None]] = Field(
        description="per frame (original, previous), each synthetic token's weight: a Gaussian of the distance "
        "between its start and the frame's submitted endpoint, normalised over the frame's tokens"
    )
    detail: dict[str, Any] = Field(
        description="what the value rests on beyond the official premises: failed, not_submitted, "
        "comfort_undefined tokens; uniform_weights where no synthetic start is near the endpoint"
    )


class StageSeedOut(BaseModel):
    """One seed of a two-stage run: the three summary rows and the groups."""

    seed: int
    score: float | None = Field(description="the combined EPDMS")
    stage_one: dict[str, float | None]
    stage_two: dict[str, float | None]
    official: bool = Field(description="the official script would have produced these numbers")
    notes: list[str] = Field(description="why not, where it would not (the first 200)")
    note_count: int
    groups: list[StageGroupOut]


class StageGroupsOut(BaseModel):
    """A two-stage submission's groups, per seed."""

    version: VersionName
    seeds: list[StageSeedOut]


class LeaderboardRow(BaseModel):
    """One entry; the devkit's subscore columns of the version are extra fields."""

    model_config = ConfigDict(extra="allow")

    rank: int | None = Field(
        description="standing by the version's score (PDMS or EPDMS) among team entries; null for baselines"
    )
    tied_with_above: bool = Field(
        description="its 95% interval overlaps the interval of the entry ranked above (statistically tied)"
    )
    team: str
    method: str
    tech_report_url: str = Field(description="given at upload; empty if none")
    code_url: str = Field(description="given at upload; empty if none")
    score: float | None
    seeds: Seeds
    baseline: bool
    ci95: list[float] = Field(description="bootstrap 95% interval of the score over tokens")
    submitted_at: datetime
    submission_id: int
    tokens: int
    failed_tokens: int


class LeaderboardOut(BaseModel):
    version: VersionName
    versions: list[VersionName] = Field(description="the versions the phase's split is scored under")
    two_stage: bool = Field(
        description="NAVSIM v2's two-stage EPDMS: `score` is the combined one; each row also has `stage_one` and "
        "`stage_two` (each stage's summary row, means over seeds), `groups` and `undefined_groups`"
    )
    interval_over: str = Field(description="what `ci95` resamples: tokens, or a two-stage split's groups")
    score_label: str = Field(description="the score's name in the papers: PDMS (v1.x) or EPDMS (v2.2)")
    official_code: str = Field(description="the official code whose results this version reproduces")
    phase: str
    split: str
    subset: str
    subsets: list[str]
    closed: bool = Field(description="the phase has closed: its entries are published (/published/{id})")
    sort: str
    columns: list[str] = Field(description="the devkit's subscore columns of this version, in order")
    rows: list[LeaderboardRow]


class PhaseOut(BaseModel):
    name: str
    split: str
    opens_at: datetime
    closes_at: datetime | None
    versions: list[VersionName] = Field(description="the versions the phase's split is scored under")
    open: bool
    per_day: int | None
    total: int | None
    in_flight: int | None


class SplitOut(BaseModel):
    name: str
    token_count: int
    content_hash: str
    scenes_public: bool = Field(description="teams may see its scenes in drill-down pictures")
    subsets: dict[str, int] = Field(description="subset name -> token count")
    phases: list[PhaseOut]


class QuotaOut(BaseModel):
    phase: str
    quota: str
    limit: int | None
    used: int
    resets_at: datetime | None


class MeOut(BaseModel):
    scope: str
    team: str | None
    approval: str | None
    token_prefix: str
    expires_at: datetime | None
    quotas: list[QuotaOut]


class HealthOut(BaseModel):
    status: str = Field(description="ok, or degraded when the broker or the workers do not answer")
    database: dict[str, Any]
    broker: dict[str, Any]
    workers: dict[str, Any]


class TeamIn(BaseModel):
    name: TeamName
    members: list[str] = []
    affiliation: str = Field("", max_length=300)


class TeamOut(BaseModel):
    model_config = ConfigDict(from_attributes=True)

    id: int
    name: str
    members: list[str]
    affiliation: str
    approval: str
    created_at: datetime


class TeamRegistered(BaseModel):
    team: TeamOut
    token: str = Field(description="shown once: store it now")


class TokenIn(BaseModel):
    name: str = Field("", max_length=200)
    expires_at: Timestamp | None = None


class TokenOut(BaseModel):
    model_config = ConfigDict(from_attributes=True)

    id: int
    scope: str
    team_id: int | None
    name: str
    prefix: str
    created_at: datetime
    expires_at: datetime | None
    revoked_at: datetime | None
    last_used_at: datetime | None


class TokenCreated(TokenOut):
    token: str = Field(description="shown once: store it now")


class QuotaIn(BaseModel):
    phase: str
    per_day: int | None = Field(None, ge=0, le=SQL_INT_MAX)
    total: int | None = Field(None, ge=0, le=SQL_INT_MAX)
    in_flight: int | None = Field(None, ge=0, le=SQL_INT_MAX)


class HideIn(BaseModel):
    hidden: bool = True


class DisqualifyIn(BaseModel):
    disqualified: bool = True
    reason: str = Field(min_length=1)


class RescoreIn(BaseModel):
    version: VersionName | None = Field(
        None,
        description="by default the phase's: the default version, or v2.2-two-stage on a two-stage split",
    )
    subset: str | None = None
    phase: str | None = None
    compare_with: VersionName | None = Field(
        None,
        description="the version whose ranking before the rescore the report compares with: by default `version`, "
        "or, when `version` has no entry yet (a version new on the board), the default version",
    )


class SplitIn(BaseModel):
    name: ObjectName
    directory: Annotated[str, StringConstraints(min_length=1, max_length=4096), AfterValidator(_printable)]
    public_tokens: list[str] | None = None
    baselines: bool = True
    scenes_public: bool = Field(False, description="teams may see its scenes in drill-down pictures")


class SplitAdded(BaseModel):
    name: str
    token_count: int
    content_hash: str
    baseline_submissions: list[int] = Field(description="the baselines' submissions, queued")


class RescoreStarted(BaseModel):
    id: int
    queued: int = Field(description="submissions queued for a new run")
    report: str = Field(description="URL of the rank-change report")


class RankMove(BaseModel):
    team: str
    method: str
    rank_before: int | None
    rank_after: int | None
    score_before: float | None
    score_after: float | None


class RescoreReport(BaseModel):
    id: int
    version: VersionName
    before_version: VersionName = Field(description="the version of the ranking before (usually `version`)")
    score_label: str = Field(description="PDMS or EPDMS: the score of `version`")
    before_score_label: str
    subset: str
    phase: str
    created_at: datetime
    submissions: int = Field(description="submissions re-run")
    pending: int = Field(description="of them still queued or running")
    failed: int
    complete: bool = Field(description="every re-run has ended")
    entries: int = Field(description="teams ranked both before and after")
    moved: list[RankMove] = Field(description="teams whose rank changed, by rank after")
    entered: list[str]
    left: list[str]
    kendall_tau: float | None = Field(description="rank correlation over the common teams (null below two)")


class PhaseIn(BaseModel):
    name: ObjectName
    split: str
    opens_at: Timestamp | None = None
    closes_at: Timestamp | None = None
    per_day: int | None = Field(None, ge=0, le=SQL_INT_MAX)
    total: int | None = Field(None, ge=0, le=SQL_INT_MAX)
    in_flight: int | None = Field(None, ge=0, le=SQL_INT_MAX)


class AuditOut(BaseModel):
    model_config = ConfigDict(from_attributes=True)

    id: int
    at: datetime
    actor: str
    action: str
    target_type: str
    target_id: str
    details: dict[str, Any]


class IntegrityCheckIn(BaseModel):
    model_config = ConfigDict(extra="forbid")

    split: str | None = Field(None, description="the split to check; every registered split when left out")


class IntegrityFlagOut(BaseModel):
    id: int
    kind: Literal["leaked_log", "near_duplicate", "probing"]
    submission_id: int
    other_submission_id: int | None = Field(description="near_duplicate: the earlier entry it copies")
    team: str
    method: str
    admin_hidden: bool
    disqualified: bool
    summary: str = Field(description="the suspicion in one sentence, with its figures")
    evidence: dict[str, Any] = Field(description="the figures behind it: quantiles, tokens, pairs")


class IntegrityCheckOut(BaseModel):
    id: int
    split: str
    started_at: datetime
    finished_at: datetime | None = Field(description="null while the check runs")
    entries: int = Field(description="the submissions read")
    skipped: list[dict[str, Any]] = Field(description="submissions that could not be read, and why")
    error: str | None
    flags: list[IntegrityFlagOut]


class IntegrityReport(BaseModel):
    """Organisers only: each split's latest integrity check and its flags; none acts by itself."""

    checks: list[IntegrityCheckOut]
