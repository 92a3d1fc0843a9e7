"""Leaderboard from per-token rows written through the worker services: ordering, ties, best or selected entry
per team, multi-seed spread, unscored tokens counting 0, bootstrap intervals, baselines, subsets, moderation."""

from __future__ import annotations

import html
import math
from datetime import timedelta
from decimal import ROUND_HALF_UP, Decimal

import numpy as np
import pytest
from server_testing import (
    World,
    add_phase,
    add_team,
    phase_row,
    reference_tokens,
    score_run,
    submit_scored,
    team_row,
    uniform,
    upload_of,
)

from scorer.ec_undefined import NO_TOKEN_PAIRED, UNPAIRED
from scorer.evaluate import TokenResult
from scorer.versions import EPDMS_COLUMNS, LOG_REPLAY_VERSIONS, VERSIONS
from server.db import transaction
from server.models import Submission, utc_now
from server.numbers import counted, percent
from server.routes import web
from server.runs import claim_submission, mark_scored, write_chunk_results
from server.runs._aggregate import bootstrap_cis
from server.services.leaderboard import rank_change_report
from server.services.submissions import add_baselines, create_submission
from server.ttl_cache import TTLCache

TOKENS = reference_tokens()


def bootstrap_ci(token_scores: np.ndarray, samples: int) -> tuple[float, float]:
    """The bootstrap 95% interval of one series' mean (the runs compute every version's at once)."""
    return bootstrap_cis(token_scores[np.newaxis], samples)[0]


def _board(world: World, **params: str) -> dict:
    response = world.client.get("/api/v1/leaderboard", params=params)
    assert response.status_code == 200, response.text
    return response.json()


def test_rows_are_ranked_by_pdms_with_ties_to_the_earlier_submission(world: World) -> None:
    beta, _ = add_team(world.factory, "beta")
    gamma, _ = add_team(world.factory, "gamma")
    start = utc_now() - timedelta(hours=3)
    submit_scored(world, gamma, b"g", [uniform(0.8)], "G", now=start + timedelta(hours=2))
    submit_scored(world, world.team_id, b"a", [uniform(0.8)], "A", now=start)
    submit_scored(world, beta, b"b", [uniform(0.9)], "B", now=start + timedelta(hours=1))
    board = _board(world, version="v1.1", sort="score")
    assert board["version"] == "v1.1"
    assert [(r["rank"], r["team"], r["method"]) for r in board["rows"]] == [
        (1, "beta", "B"),
        (2, "alpha", "A"),  # tie with gamma at 0.8: alpha submitted first
        (3, "gamma", "G"),
    ]
    assert board["rows"][0]["score"] == pytest.approx(0.9)
    v11_columns = [
        "no_at_fault_collisions",
        "drivable_area_compliance",
        "ego_progress",
        "time_to_collision_within_bound",
        "comfort",
        "driving_direction_compliance",
    ]
    assert board["columns"] == v11_columns
    assert all(column in board["rows"][0] for column in v11_columns)
    assert {"rank", "team", "method", "score", "seeds", "baseline", "ci95", "submitted_at"} <= set(
        board["rows"][0]
    )


def test_one_entry_per_team_best_unless_one_is_selected(world: World) -> None:
    worse = submit_scored(world, world.team_id, b"1", [uniform(0.7)], "worse")
    submit_scored(world, world.team_id, b"2", [uniform(0.8)], "better")
    rows = _board(world)["rows"]
    assert [(r["team"], r["method"]) for r in rows] == [("alpha", "better")]
    response = world.client.patch(
        f"/api/v1/submissions/{worse}", json={"selected": True}, headers=world.team_headers()
    )
    assert response.status_code == 200 and response.json()["selected"] is True
    assert [r["method"] for r in _board(world)["rows"]] == ["worse"]


def test_multi_seed_mean_std_max(world: World) -> None:
    seeds = [0.6, 0.7, 0.85]
    submit_scored(world, world.team_id, b"s", [uniform(s) for s in seeds], "three seeds")
    row = _board(world)["rows"][0]
    assert row["score"] == pytest.approx(np.mean(seeds))
    assert row["seeds"] == pytest.approx(
        {"count": 3, "mean": np.mean(seeds), "std": np.std(seeds), "max": 0.85}
    )


def test_unscored_tokens_count_zero_and_are_counted(world: World) -> None:
    scores = {token: (None if index < 4 else 1.0) for index, token in enumerate(TOKENS)}
    submission_id = submit_scored(world, world.team_id, b"f", [scores])
    row = _board(world)["rows"][0]
    assert row["score"] == pytest.approx(36 / 40)
    assert (row["tokens"], row["failed_tokens"]) == (40, 4)
    detail = world.client.get(f"/api/v1/submissions/{submission_id}", headers=world.team_headers()).json()
    assert detail["status"] == "scored" and detail["progress"] == 100
    assert detail["results"]["v1.0"]["all"]["failed_tokens"] == 4
    failed = world.client.get(
        f"/api/v1/submissions/{submission_id}/tokens",
        params={"only_failed": True},
        headers=world.team_headers(),
    ).json()
    assert (
        sorted(r["token"] for r in failed) == TOKENS[:4] and failed[0]["error"] == "poses: non-finite value"
    )


def test_bootstrap_interval_from_token_rows(world: World) -> None:
    rng = np.random.default_rng(7)
    scores = dict(zip(TOKENS, rng.uniform(0.3, 1.0, len(TOKENS)).round(3).tolist(), strict=True))
    submit_scored(world, world.team_id, b"ci", [scores])
    row = _board(world)["rows"][0]
    low, high = row["ci95"]
    assert low < row["score"] < high
    assert (low, high) == pytest.approx(bootstrap_ci(np.array([scores[t] for t in TOKENS]), 300))
    assert _board(world)["rows"][0]["ci95"] == row["ci95"]  # deterministic


def test_bootstrap_interval_properties() -> None:
    constant = bootstrap_ci(np.full(50, 0.4), 200)
    assert constant == pytest.approx((0.4, 0.4))
    rng = np.random.default_rng(0)
    small, large = rng.uniform(size=30), rng.uniform(size=3000)
    small_ci, large_ci = bootstrap_ci(small, 500), bootstrap_ci(large, 500)
    assert small_ci[0] < small.mean() < small_ci[1]
    assert large_ci[1] - large_ci[0] < small_ci[1] - small_ci[0]
    assert bootstrap_ci(small, 500) == small_ci


def test_bootstrap_intervals_of_stacked_series_are_each_alone() -> None:
    """The versions of a subset share one resampling: each gets the bits of its interval computed alone, the
    bits one series at a time gave before they were stacked (golden, from that code)."""
    rng = np.random.default_rng(3)
    series = rng.uniform(size=(3, 700))
    assert bootstrap_cis(series, 600) == [
        (0.4690682899643758, 0.51190087371109),
        (0.491400506911528, 0.5349596595318092),
        (0.4612729304561877, 0.5061724079008281),
    ]
    assert bootstrap_cis(series, 600) == [bootstrap_ci(row, 600) for row in series]
    assert bootstrap_cis(series[:, :0], 600)[0] != bootstrap_cis(series[:, :0], 600)[0]  # NaN: no tokens


def test_baselines_are_marked_and_take_no_rank(world: World) -> None:
    submit_scored(world, world.team_id, b"t", [uniform(0.5)], "team entry")
    with transaction(world.factory) as session:
        from server.models import Split

        split = session.query(Split).filter_by(name="reference").one()
        baselines = [s.id for s in add_baselines(session, split, world.settings.submission_store)]
    score_run(world.factory, baselines[0], [uniform(0.3)])
    score_run(world.factory, baselines[1], [uniform(0.9)])
    rows = _board(world)["rows"]
    assert [(r["method"], r["baseline"], r["rank"]) for r in rows] == [
        ("Human", True, None),
        ("team entry", False, 1),
        ("Constant Velocity", True, None),
    ]


def test_hidden_and_disqualified_entries_leave_the_board(world: World) -> None:
    beta, _ = add_team(world.factory, "beta")
    hidden = submit_scored(world, world.team_id, b"h", [uniform(0.9)], "hidden by team")
    shown = submit_scored(world, world.team_id, b"s", [uniform(0.5)], "shown")
    cheat = submit_scored(world, beta, b"c", [uniform(0.99)], "cheat")
    world.client.patch(f"/api/v1/submissions/{hidden}", json={"hidden": True}, headers=world.team_headers())
    response = world.client.post(
        f"/api/v1/admin/submissions/{cheat}/disqualify",
        json={"reason": "used the test labels"},
        headers=world.admin_headers(),
    )
    assert response.status_code == 200 and response.json()["disqualified_reason"] == "used the test labels"
    assert [(r["team"], r["submission_id"], r["rank"]) for r in _board(world)["rows"]] == [
        ("alpha", shown, 1)
    ]
    world.client.post(
        f"/api/v1/admin/submissions/{shown}/hide", json={"hidden": True}, headers=world.admin_headers()
    )
    assert _board(world)["rows"] == []


def _team_entry(world: World, version: str) -> int:
    return next(r["submission_id"] for r in _board(world, version=version)["rows"] if r["team"] == "alpha")


def _as_team_sees(world: World, submission_id: int) -> dict:
    response = world.client.get(f"/api/v1/submissions/{submission_id}", headers=world.team_headers())
    assert response.status_code == 200, response.text
    return response.json()


def _select(world: World, submission_id: int, **changes: bool):
    return world.client.patch(
        f"/api/v1/submissions/{submission_id}",
        json={"selected": True, **changes},
        headers=world.team_headers(),
    )


def _moderate(world: World, submission_id: int, action: str, body: dict) -> None:
    response = world.client.post(
        f"/api/v1/admin/submissions/{submission_id}/{action}", json=body, headers=world.admin_headers()
    )
    assert response.status_code == 200, response.text


def test_a_team_sees_its_sanctions_and_the_entry_the_board_counts(world: World) -> None:
    worst = submit_scored(world, world.team_id, b"w", [uniform(0.5)], "worst")
    middle = submit_scored(world, world.team_id, b"m", [uniform(0.6)], "middle")
    best = submit_scored(world, world.team_id, b"b", [uniform(0.7)], "best")

    def counted() -> dict[int, list[str]]:
        """Per submission the versions the team's API says the board shows it in; checked against each board."""
        listing = world.client.get("/api/v1/submissions", headers=world.team_headers()).json()
        shown = {entry["id"]: entry["on_leaderboard"] for entry in listing}
        for version in LOG_REPLAY_VERSIONS:
            assert [i for i, versions in shown.items() if version in versions] == [
                _team_entry(world, version)
            ]
        return shown

    assert counted()[best] == list(LOG_REPLAY_VERSIONS)  # no final entry chosen: the best
    assert _select(world, worst).status_code == 200
    assert counted()[worst] == list(LOG_REPLAY_VERSIONS)

    # Disqualified, the final entry leaves the board and the team sees why; it cannot be chosen again.
    _moderate(world, worst, "disqualify", {"reason": "trained on the test logs"})
    seen = _as_team_sees(world, worst)
    assert (seen["disqualified"], seen["disqualified_reason"], seen["on_leaderboard"]) == (
        True,
        "trained on the test logs",
        [],
    )
    assert "trained on the test logs" in seen["final_refusal"]
    assert counted()[best] == list(LOG_REPLAY_VERSIONS)
    refused = _select(world, worst)
    assert refused.status_code == 409
    assert "disqualified by an organiser: trained on the test logs" in refused.json()["detail"]

    # Hidden by an organiser: the same, with no reason to give.
    _moderate(world, best, "hide", {"hidden": True})
    seen = _as_team_sees(world, best)
    assert seen["admin_hidden"] is True and seen["on_leaderboard"] == []
    assert counted()[middle] == list(LOG_REPLAY_VERSIONS)
    refused = _select(world, best)
    assert (
        refused.status_code == 409
        and "hidden from the leaderboard by an organiser" in refused.json()["detail"]
    )

    # Hidden by the team: shown again in the same request, it may become final.
    world.client.patch(f"/api/v1/submissions/{middle}", json={"hidden": True}, headers=world.team_headers())
    refused = _select(world, middle)
    assert refused.status_code == 409 and "hidden by your team; show it first" in refused.json()["detail"]
    assert _as_team_sees(world, middle)["selected"] is False  # the refused request changed nothing
    assert _select(world, middle, hidden=False).status_code == 200
    assert counted()[middle] == list(LOG_REPLAY_VERSIONS)


def test_private_subset_is_revealed_when_the_phase_closes(world: World) -> None:
    public = TOKENS[:10]
    add_phase(
        world.factory,
        "split-phase",
        split="halves",
        public_tokens=public,
        opens_at=utc_now() - timedelta(days=2),
    )
    scores = {token: (1.0 if token in public else 0.0) for token in TOKENS}
    submit_scored(world, world.team_id, b"p", [scores], phase="split-phase")
    board = _board(world, phase="split-phase")
    assert (board["subset"], board["subsets"]) == ("public", ["public"])
    assert board["rows"][0]["score"] == pytest.approx(1.0) and board["rows"][0]["tokens"] == 10
    closed = world.client.get("/api/v1/leaderboard", params={"phase": "split-phase", "subset": "private"})
    assert closed.status_code == 403 and "revealed when the phase closes" in closed.json()["detail"]
    assert (
        world.client.get("/api/v1/leaderboard", params={"phase": "split-phase", "subset": "x"}).status_code
        == 404
    )
    with transaction(world.factory) as session:
        from server.models import Phase

        session.query(Phase).filter_by(name="split-phase").one().closes_at = utc_now() - timedelta(seconds=1)
    private = _board(world, phase="split-phase", subset="private")
    assert private["rows"][0]["score"] == pytest.approx(0.0) and private["rows"][0]["tokens"] == 30
    assert _board(world, phase="split-phase", subset="all")["rows"][0]["score"] == pytest.approx(0.25)


def test_sorting_by_a_subscore_keeps_the_pdms_rank(world: World) -> None:
    beta, _ = add_team(world.factory, "beta")
    submit_scored(world, world.team_id, b"a", [uniform(0.9)], "A")
    submit_scored(world, beta, b"b", [uniform(0.5)], "B")
    by_time = _board(world, sort="submitted_at")["rows"]
    assert [(r["method"], r["rank"]) for r in by_time] == [("A", 1), ("B", 2)]
    assert world.client.get("/api/v1/leaderboard", params={"sort": "pdms"}).status_code == 422
    assert world.client.get("/api/v1/leaderboard", params={"version": "v9"}).status_code == 422


def test_v1_0_is_served_with_its_own_columns(world: World) -> None:
    submit_scored(world, world.team_id, b"a", [uniform(0.75)], "A")
    v10 = _board(world, version="v1.0")
    assert v10["version"] == "v1.0" and v10["rows"][0]["score"] == pytest.approx(0.75)
    assert v10["columns"][:3] == [
        "no_at_fault_collisions",
        "drivable_area_compliance",
        "driving_direction_compliance",
    ]


# A token where the logged human fails lane keeping too: the filter set the agent's 0 to 1.
FILTERED = {
    "human_filter": {
        "overridden": ["lane_keeping"],
        "agent_before": {"lane_keeping": 0.0, "ego_progress": 0.7},
        "human": {"lane_keeping": 0.0, "ego_progress": 1.0},
    }
}


def _scored_with_undefined_ec(world: World, undefined: set[str]) -> int:
    """Score a submission whose v2.2 rows leave EC undefined (NaN: no frame before) on `undefined` tokens."""
    with transaction(world.factory) as session:
        upload = upload_of(f"ec {len(undefined)}".encode(), method="EC")
        submission, _ = create_submission(
            session,
            team_row(session, world.team_id),
            phase_row(session, "test"),
            upload,
            world.settings.submission_store,
        )
        run = claim_submission(session, submission.id, "w")
        assert run is not None
        for version in LOG_REPLAY_VERSIONS:
            rows = [
                TokenResult(
                    token,
                    0,
                    True,
                    dict.fromkeys(VERSIONS[version].result_columns, 0.5)
                    | {"two_frame_extended_comfort": math.nan if token in undefined else 1.0},
                    detail=FILTERED | {"two_frame_extended_comfort": {"previous_token": "x"}}
                    if token not in undefined
                    else {},
                )
                for token in TOKENS
            ]
            assert write_chunk_results(session, submission.id, run, version, rows, "w", 1.0)
        assert mark_scored(session, submission.id, run, "test-engine", 100)
        return submission.id


def test_v2_2_board_has_its_columns_its_official_code_and_ec_over_the_tokens_that_define_it(
    world: World,
) -> None:
    submission_id = _scored_with_undefined_ec(world, set(TOKENS[:30]))
    board = _board(world, version="v2.2")
    assert board["score_label"] == "EPDMS" and "tag v2.2, commit 359c7f7" in board["official_code"]
    assert board["columns"] == [column for column in EPDMS_COLUMNS if column != "score"]  # the official CSV's
    (row,) = board["rows"]
    # EC's mean skips the 30 tokens without a pair, as the official average row does; the rest count all tokens.
    assert row["two_frame_extended_comfort"] == 1.0 and row["lane_keeping"] == 0.5
    assert "two_frame_extended_comfort" not in _board(world, version="v1.1")["columns"]
    team = world.team_headers()
    tokens = world.client.get(
        f"/api/v1/submissions/{submission_id}/tokens", params={"version": "v2.2"}, headers=team
    )
    by_token = {r["token"]: r for r in tokens.json()}
    assert by_token[TOKENS[0]]["metrics"]["two_frame_extended_comfort"] is None
    # An undefined EC says why: this token was never paired (the first of its log in the split).
    assert by_token[TOKENS[0]]["ec_undefined"] == UNPAIRED and by_token[TOKENS[-1]]["ec_undefined"] is None
    # The team reads the filter's overrides and its own values there, not the human's scores on a hidden log.
    team_filter = {"overridden": ["lane_keeping"], "agent_before": {"lane_keeping": 0.0}}
    assert by_token[TOKENS[-1]]["detail"] == {
        "human_filter": team_filter,
        "two_frame_extended_comfort": {"previous_token": "x"},
    }
    admin_rows = world.client.get(
        f"/api/v1/admin/submissions/{submission_id}/tokens",
        params={"version": "v2.2"},
        headers=world.admin_headers(),
    ).json()
    assert {r["token"]: r for r in admin_rows}[TOKENS[-1]]["detail"]["human_filter"] == FILTERED[
        "human_filter"
    ]
    v11 = world.client.get(
        f"/api/v1/submissions/{submission_id}/tokens", params={"version": "v1.1"}, headers=team
    ).json()
    assert "two_frame_extended_comfort" not in v11[0]["metrics"]

    undefined_everywhere = _scored_with_undefined_ec(world, set(TOKENS))
    seen = world.client.get(f"/api/v1/submissions/{undefined_everywhere}", headers=team).json()
    summary = seen["results"]["v2.2"]["all"]
    assert summary["two_frame_extended_comfort"] is None and summary["score"] == pytest.approx(0.5)

    page = world.client.get("/", params={"version": "v2.2"})
    assert page.status_code == 200
    assert "EPDMS v2.2" in page.text and "commit 359c7f7" in page.text and ">EC<" in page.text
    assert "#ec-undefined" not in page.text  # the entry shown has an EC
    chosen = {"selected": True}
    path = f"/api/v1/submissions/{undefined_everywhere}"
    assert world.client.patch(path, json=chosen, headers=team).status_code == 200
    page = world.client.get("/", params={"version": "v2.2"})
    # The entry whose EC is undefined on every token says why where its – stands.
    assert f'#ec-undefined" title="EC {NO_TOKEN_PAIRED}">–</a>' in html.unescape(page.text)


def test_web_page_shows_rows_baseline_flag_and_interval(world: World) -> None:
    submit_scored(world, world.team_id, b"a", [uniform(0.755)], "Page method")
    page = world.client.get("/", params={"version": "v1.1"})
    assert page.status_code == 200
    assert "Page method" in page.text and "75.5" in page.text and "95% CI" in page.text
    assert "<caption>" in page.text and 'scope="col"' in page.text and 'aria-sort="descending"' in page.text
    unknown = world.client.get("/", params={"version": "v9"})
    assert (
        unknown.status_code == 422
        and "unknown metric version &#39;v9&#39;; known: v1.0, v1.1, v2.2" in unknown.text
    )


def test_the_board_page_is_rendered_once_per_cache_period_and_address(
    world: World, monkeypatch: pytest.MonkeyPatch
) -> None:
    state = world.client.app.state  # type: ignore[attr-defined]
    state.page_cache, state.leaderboard_cache = TTLCache(60), TTLCache(60)  # as in production, with 60 s
    renders: list[str] = []
    phases = web.list_phases
    monkeypatch.setattr(web, "list_phases", lambda *args, **kw: renders.append("page") or phases(*args, **kw))
    first = world.client.get("/")
    submit_scored(world, world.team_id, b"a", [uniform(0.755)], "Later method")
    again = world.client.get("/")
    assert first.status_code == again.status_code == 200 and renders == ["page"]
    assert again.text == first.text and "Later method" not in again.text  # until the period ends
    # Its links are absolute: a page asked at another address is its own.
    elsewhere = world.client.get("/", headers={"Host": "elsewhere.example"})
    assert (
        renders == ["page", "page"] and 'href="http://elsewhere.example/static/style.css"' in elsewhere.text
    )


def test_the_page_rounds_as_every_page_and_the_command_line_do_and_counts_in_words(world: World) -> None:
    # 0.9525 × 100 is 95.25 exactly: Python's "%.1f" wrote 95.2, JavaScript's toFixed 95.3 (the other pages).
    submit_scored(world, world.team_id, b"a", [uniform(0.9525)], "Tie")
    page = world.client.get("/", params={"version": "v1.1"}).text
    assert '<td class="num score" data-value="0.9525">95.3</td>' in page.replace("\n", "")
    assert "1 entry" in page and "1 entries" not in page
    assert [percent(v) for v in (0.9525, 0.95249999, 1.0, -0.0004, None, math.nan)] == [
        "95.3",
        "95.2",
        "100.0",
        "0.0",
        "–",
        "–",
    ]
    # The exact product rounded as decimal's ROUND_HALF_UP rounds it, ties and their neighbours included.
    values = [k / 20_000 for k in range(-20_001, 20_001)]
    values += np.random.default_rng(0).uniform(-2, 2, 20_000).tolist()
    for value in values + [math.nextafter(value, 2.0) for value in values]:
        exact = Decimal(100 * value).quantize(Decimal("0.1"), rounding=ROUND_HALF_UP)
        assert percent(value) == str(exact if exact else Decimal("0.0")), value
    assert (counted(1, "entry", "entries"), counted(2, "entry", "entries"), counted(3, "token")) == (
        "1 entry",
        "2 entries",
        "3 tokens",
    )


def test_a_page_the_product_does_not_have_is_a_404_page_and_the_api_keeps_json(world: World) -> None:
    submission_id = submit_scored(world, world.team_id, b"a", [uniform(0.5)], "Real")
    assert world.client.get(f"/submissions/{submission_id}").status_code == 200
    for path, says in (
        ("/no-such-page", "There is no page at /no-such-page."),
        (f"/submissions/{submission_id + 1000}", f"Submission {submission_id + 1000} does not exist."),
        ("/submissions/abc", "There is no page at /submissions/abc."),
    ):
        response = world.client.get(path)
        assert response.status_code == 404 and response.headers["content-type"].startswith("text/html"), path
        assert "<h1>Page not found</h1>" in response.text and says in response.text, path
        assert '/team">your team' in response.text  # a way on
    for path in ("/api/v1/no-such-route", f"/api/v1/published/{submission_id + 1000}"):
        response = world.client.get(path)
        assert response.status_code == 404 and "detail" in response.json(), path
    assert "detail" in world.client.get("/api/v1/submissions/abc", headers=world.team_headers()).json()


def test_entries_with_overlapping_intervals_are_marked_tied(world: World) -> None:
    beta, _ = add_team(world.factory, "beta")
    gamma, _ = add_team(world.factory, "gamma")
    tokens = reference_tokens()
    spread = {token: (0.6 if index % 2 else 1.0) for index, token in enumerate(tokens)}  # mean 0.8, wide CI
    submit_scored(world, world.team_id, b"a", [spread], "Wide")
    submit_scored(world, beta, b"b", [uniform(0.79)], "Inside the interval above")
    submit_scored(world, gamma, b"c", [uniform(0.2)], "Far below")
    rows = _board(world)["rows"]
    assert [(row["method"], row["tied_with_above"]) for row in rows] == [
        ("Wide", False),
        ("Inside the interval above", True),
        ("Far below", False),
    ]
    assert world.client.get("/").text.count('class="tied"') == 2  # the mark on one row, and in the legend


def test_method_links_are_shown_only_for_web_addresses(world: World) -> None:
    first = submit_scored(world, world.team_id, b"a", [uniform(0.7)], "Linked")
    beta, _ = add_team(world.factory, "beta")
    second = submit_scored(world, beta, b"b", [uniform(0.6)], "Not linked")
    with world.session() as session:
        session.get(Submission, first).tech_report_url = "https://example.org/paper"
        session.get(Submission, second).code_url = "javascript:alert(1)"  # stored before uploads were checked
        session.commit()
    rows = {row["method"]: row for row in _board(world, sort="submitted_at")["rows"]}
    assert rows["Linked"]["tech_report_url"] == "https://example.org/paper"
    page = world.client.get("/", params={"phase": world.phase}).text
    assert 'href="https://example.org/paper"' in page and "javascript:alert" not in page


def test_rank_change_report() -> None:
    def rows(order: list[tuple[str, float]]) -> list[dict]:
        return [
            {"team": t, "method": t, "rank": i + 1, "score": s, "baseline": False}
            for i, (t, s) in enumerate(order)
        ]

    before = rows([("a", 0.9), ("b", 0.8), ("c", 0.7), ("d", 0.6)])
    same = rank_change_report(before, before)
    assert (same["moved"], same["kendall_tau"]) == ([], pytest.approx(1.0))
    reversed_report = rank_change_report(before, rows([("d", 0.9), ("c", 0.8), ("b", 0.7), ("a", 0.6)]))
    assert reversed_report["kendall_tau"] == pytest.approx(-1.0) and len(reversed_report["moved"]) == 4
    swap = rank_change_report(before, rows([("b", 0.9), ("a", 0.8), ("c", 0.7), ("e", 0.5)]))
    assert [(m["team"], m["rank_before"], m["rank_after"]) for m in swap["moved"]] == [
        ("b", 2, 1),
        ("a", 1, 2),
    ]
    assert (swap["entered"], swap["left"]) == (["e"], ["d"])
    assert swap["kendall_tau"] == pytest.approx(1 / 3)  # pairs among a, b, c: one discordant of three


def test_every_route_that_takes_a_metric_version_refuses_an_unknown_one(world: World) -> None:
    submission_id = submit_scored(world, world.team_id, b"a", [uniform(0.75)], "A")
    requests = [
        ("get", "/api/v1/leaderboard", {"params": {"version": "v9"}}),
        ("get", f"/api/v1/submissions/{submission_id}/tokens", {"params": {"version": "v9"}}),
        ("get", "/api/v1/admin/export", {"params": {"version": "v9"}}),
        ("post", "/api/v1/admin/rescore", {"json": {"version": "v9"}}),
    ]
    for method, url, arguments in requests:
        headers = world.admin_headers() if "/admin/" in url else world.team_headers()
        response = world.client.request(method, url, headers=headers, **arguments)
        assert response.status_code == 422, url
        assert "'v1.0', 'v1.1', 'v2.2', 'v2.2-prefix' or 'v2.2-two-stage'" in response.text, url
    known = world.client.get(
        f"/api/v1/submissions/{submission_id}/tokens",
        params={"version": "v1.0"},
        headers=world.team_headers(),
    )
    assert known.status_code == 200 and {row["metric_version"] for row in known.json()} == {"v1.0"}
