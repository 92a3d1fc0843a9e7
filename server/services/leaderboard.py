"""The leaderboard as it is read: per team its selected (else best) entry and the baselines, ranked by score
with statistical ties; the board's body for a query, cached briefly; the rank changes between two rankings.
Runs write the summaries it reads (server.runs)."""

from __future__ import annotations

import json
from collections.abc import Collection, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from sqlalchemy import case, func, or_, select
from sqlalchemy.orm import Session, sessionmaker

from scorer.versions import ALL_RESULT_COLUMNS, DEFAULT_VERSION, get_version
from server.models import Phase, Status, Submission, Summary, Team
from server.runs import run_versions
from server.services.errors import Forbidden, Invalid, NotFound
from server.services.splits import (
    ALL_SUBSET,
    PUBLIC_SUBSET,
    has_closed,
    resolve_phase,
    subset_names,
    visible_subsets,
)
from server.ttl_cache import TTLCache

HIDDEN_STATUSES = (Status.failed, Status.cancelled)


def subscore_columns(version: str) -> tuple[str, ...]:
    """Return the devkit's subscore columns of a metric version, in its result-table order."""
    try:
        columns = get_version(version).result_columns
    except ValueError as error:
        raise Invalid(str(error), [{"token": None, "field": "version", "message": str(error)}]) from None
    return tuple(column for column in columns if column != "score")


def summary_figures(summary: Any, columns: tuple[str, ...]) -> dict[str, Any]:
    """Return the figures of a summary as the API shows them: the score (PDMS or EPDMS), the version's subscore `columns`, the seeds,
    the 95% interval and the token counts. `summary` is a Summary, or a row selecting its columns by name."""
    return {
        "score": summary.score,
        **{column: getattr(summary, column) for column in columns},
        "seeds": {
            "count": summary.seeds,
            "mean": summary.score,
            "std": summary.score_std,
            "max": summary.score_max,
        },
        "ci95": [summary.ci_low, summary.ci_high],
        "tokens": summary.tokens,
        "failed_tokens": summary.failed,
    }


STAGES = ("stage_one", "stage_two")


def stage_figures(two_stage: dict[str, Any] | None) -> dict[str, Any]:
    """Return the two-stage figures of a summary (empty for a one-stage one): each stage's summary row (means
    over seeds), its score apart for sorting, and the groups the combined score and its interval rest on."""
    if two_stage is None:
        return {}
    return {
        **{stage: two_stage[stage] for stage in STAGES},
        **{f"{stage}_score": two_stage[stage]["score"] for stage in STAGES},
        "groups": two_stage["groups"],
        "undefined_groups": two_stage["undefined_groups"],
        "official": two_stage["official"],
    }


def _row(entry: Any, columns: tuple[str, ...]) -> dict[str, Any]:
    return {
        "rank": None,
        "team": entry.team,
        "method": entry.method,
        "tech_report_url": entry.tech_report_url,
        "code_url": entry.code_url,
        **summary_figures(entry, columns),
        **stage_figures(entry.two_stage),
        "baseline": entry.is_baseline,
        "submitted_at": entry.created_at.isoformat(),
        "submission_id": entry.submission_id,
    }


def phase_summaries(phase: Phase, version: str, subset: str) -> tuple[Any, ...]:
    """Return the conditions selecting a phase's summaries for (version, subset): its entries and the split's baselines."""
    return (
        Summary.metric_version == version,
        Summary.subset == subset,
        Submission.split_id == phase.split_id,
        or_(Submission.phase_id == phase.id, Submission.is_baseline.is_(True)),
    )


def _entries(
    session: Session, phase: Phase, version: str, subset: str, team_ids: Collection[int] | None = None
) -> Sequence[Any]:
    """Return the visible entries of a phase, best first: per team its selected, else best, submission; baselines.
    With `team_ids`, those teams' entries only (each team's is chosen among its own submissions alone)."""
    # Each baseline is its own entry: partition it by its negated id, which no team id can equal.
    entry_key = case((Submission.is_baseline, -Submission.id), else_=Submission.team_id)
    standing = (Summary.score.desc(), Submission.created_at, Submission.id)
    choice = func.row_number().over(partition_by=entry_key, order_by=(Submission.selected.desc(), *standing))
    candidates = (
        select(
            Summary.submission_id,
            Team.name.label("team"),
            Submission.method,
            Submission.tech_report_url,
            Submission.code_url,
            Submission.is_baseline,
            Submission.created_at,
            Summary.seeds,
            Summary.score_std,
            Summary.score_max,
            Summary.ci_low,
            Summary.ci_high,
            Summary.tokens,
            Summary.failed,
            Summary.two_stage,
            *(getattr(Summary, column) for column in ALL_RESULT_COLUMNS),
            choice.label("choice"),
        )
        .join(Submission, Summary.submission_id == Submission.id)
        .join(Team, Team.id == Submission.team_id)
        .where(
            *phase_summaries(phase, version, subset),
            Submission.hidden.is_(False),
            Submission.admin_hidden.is_(False),
            Submission.disqualified.is_(False),
            Submission.status.not_in(HIDDEN_STATUSES),
            *(() if team_ids is None else (Submission.team_id.in_(team_ids),)),
        )
        .subquery()
    )
    query = (
        select(candidates)
        .where(candidates.c.choice == 1)
        .order_by(candidates.c.score.desc(), candidates.c.created_at, candidates.c.submission_id)
    )
    return session.execute(query).all()


def shown_entries(
    session: Session, phase: Phase, version: str, subset: str, team_ids: Collection[int]
) -> set[int]:
    """Return the submissions of these teams that the phase's leaderboard shows for (version, subset): by the
    board's own choice, so that a team's pages and the API name the entry the board ranks."""
    return {entry.submission_id for entry in _entries(session, phase, version, subset, team_ids)}


def default_subset(phase: Phase, admin: bool = False) -> str:
    """Return the subset a leaderboard shows when none is asked: the public tokens while they are all a team
    may see, else every token."""
    return PUBLIC_SUBSET if PUBLIC_SUBSET in visible_subsets(phase.split, phase, admin) else ALL_SUBSET


def _overlap(interval: list[float], other: list[float]) -> bool:
    """Return whether two intervals share a point (NaN bounds, from entries without tokens, share none)."""
    return bool(interval[1] >= other[0] and other[1] >= interval[0])


def leaderboard(
    session: Session, phase: Phase, version: str, subset: str, sort: str = "score"
) -> list[dict[str, Any]]:
    """Return the leaderboard rows: ranked by the version's score (ties: earlier submission, then id), ordered by `sort`."""
    columns = subscore_columns(version)
    stages = tuple(f"{stage}_score" for stage in STAGES) if get_version(version).two_stage else ()
    sortable = ("score", *stages, *columns, "submitted_at")
    if sort not in sortable:
        message = f"cannot sort by {sort!r}; choose one of {', '.join(sortable)}"
        raise Invalid(message, [{"token": None, "field": "sort", "message": message}])
    rows = [_row(entry, columns) for entry in _entries(session, phase, version, subset)]
    rank, above = 0, None
    for row in rows:
        row["tied_with_above"] = False
        if not row["baseline"]:
            rank += 1
            row["rank"] = rank
            # Statistically tied: its 95% interval reaches into the interval of the entry ranked above.
            row["tied_with_above"] = above is not None and _overlap(row["ci95"], above["ci95"])
            above = row
    if sort == "submitted_at":
        return sorted(rows, key=lambda row: (row["submitted_at"], row["submission_id"]))
    if sort != "score":
        # Python's sort is stable: equal values keep the score's order.
        return sorted(rows, key=lambda row: -(row[sort] if row[sort] is not None else float("-inf")))
    return rows


def rank_change_report(before: list[dict[str, Any]], after: list[dict[str, Any]]) -> dict[str, Any]:
    """Compare two rankings of teams: who moved, who entered or left, and Kendall's tau over the common teams."""
    old = {row["team"]: row for row in before if not row["baseline"]}
    new = {row["team"]: row for row in after if not row["baseline"]}
    common = [team for team in old if team in new]
    moved = [
        {
            "team": team,
            "method": new[team]["method"],
            "rank_before": old[team]["rank"],
            "rank_after": new[team]["rank"],
            "score_before": old[team]["score"],
            "score_after": new[team]["score"],
        }
        for team in common
        if old[team]["rank"] != new[team]["rank"]
    ]
    tau = None
    if len(common) >= 2:
        from scipy.stats import kendalltau  # seconds to import: only when a rescore is reported

        statistic = kendalltau([old[t]["rank"] for t in common], [new[t]["rank"] for t in common]).statistic
        tau = None if np.isnan(statistic) else float(statistic)
    return {
        "entries": len(common),
        "moved": sorted(moved, key=lambda m: m["rank_after"]),
        "entered": sorted(team for team in new if team not in old),
        "left": sorted(team for team in old if team not in new),
        "kendall_tau": tau,
    }


def phase_version(phase: Phase, version: str | None) -> str:
    """Return the version a phase's board shows for a query: the one asked, or by default the default version
    where the phase's split is scored under it, else the first of its split's versions. A version of the other
    kind of split (one-stage on a two-stage split, or the reverse) is refused, naming the phase's versions."""
    versions = run_versions(phase.split)
    if version is None:
        return DEFAULT_VERSION if DEFAULT_VERSION in versions else versions[0]
    subscore_columns(version)  # an unknown version is refused first
    if get_version(version).two_stage != get_version(versions[0]).two_stage:
        raise NotFound(
            f"phase {phase.name!r} is on {phase.split.kind} split {phase.split.name!r}, scored under "
            f"{', '.join(versions)}: it has no {version} leaderboard"
        )
    return version


def leaderboard_view(
    session: Session,
    version: str | None,
    subset: str | None,
    sort: str,
    phase_name: str | None,
    admin: bool = False,
) -> dict[str, Any]:
    """Return the leaderboard body for the query (shared by the REST route and the web page); `version` None
    is the phase's default (`phase_version`)."""
    phase = resolve_phase(session, phase_name)
    version = phase_version(phase, version)
    columns = subscore_columns(version)
    visible = visible_subsets(phase.split, phase, admin)
    if subset is None:
        subset = default_subset(phase, admin)
    known = subset_names(phase.split)
    if subset not in known:
        raise NotFound(f"split {phase.split.name!r} has no subset {subset!r}; it has {', '.join(known)}")
    if subset not in visible:
        closes = phase.closes_at.isoformat() if phase.closes_at else "an admin closes it"
        raise Forbidden(
            f"subset {subset!r} of phase {phase.name!r} is revealed when the phase closes ({closes})"
        )
    metric_version = get_version(version)
    return {
        "version": version,
        "versions": list(run_versions(phase.split)),
        "two_stage": metric_version.two_stage,
        "interval_over": "groups" if metric_version.two_stage else "tokens",
        "score_label": metric_version.score_label,
        "official_code": metric_version.official_code,
        "phase": phase.name,
        "split": phase.split.name,
        "subset": subset,
        "subsets": visible,
        "closed": has_closed(phase),
        "sort": sort,
        "columns": list(columns),
        "rows": leaderboard(session, phase, version, subset, sort),
    }


def _json(view: dict[str, Any]) -> bytes:
    """Return the body as the API sends it (Starlette's JSONResponse encoding)."""
    return json.dumps(view, ensure_ascii=False, allow_nan=False, separators=(",", ":")).encode("utf-8")


@dataclass(frozen=True)
class Board:
    """A leaderboard body and its JSON encoding, computed once per cache period."""

    view: dict[str, Any]
    body: bytes


def cached_board(
    cache: TTLCache[Board],
    sessions: sessionmaker[Session],
    version: str | None,
    subset: str | None,
    sort: str,
    phase: str | None,
) -> Board:
    """Return the public leaderboard for the query, from the short-lived `cache` (computed once at a time,
    the expired board served meanwhile: `TTLCache.get_or_compute`)."""

    def compute() -> Board:
        with sessions() as session:
            view = leaderboard_view(session, version, subset, sort, phase)
        return Board(view, _json(view))

    return cache.get_or_compute((version, subset, sort, phase), compute)
