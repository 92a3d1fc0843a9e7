"""The web pages in a real browser: Debian's chromium, driven by Playwright, against `navsim-lb demo`.

The demo is the whole service as a user meets it (SQLite, the embedded broker, a worker, the API and the
pages) on a small synthetic split, with its baselines and demo entry scored. Screenshots of every page at
desktop width and at 390 px go to tests/artifacts/screenshots/ (look at them).
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import httpx
import pytest
from playwright.sync_api import Browser, Page, Route, expect, sync_playwright

pytestmark = pytest.mark.browser

SCREENSHOTS = Path(__file__).parent / "artifacts" / "screenshots"
CHROMIUM_ARGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]
STARTUP_TIMEOUT_S = 240.0
PHASE, TWO_STAGE_PHASE = "demo", "demo-two-stage"
SCORING_TIMEOUT_MS = 180_000


@dataclass(frozen=True)
class Demo:
    url: str
    team_token: str
    admin_token: str
    data_dir: Path


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def _scored_entries(url: str, phase: str | None = None) -> int:
    try:
        params = {"phase": phase} if phase else {}
        rows = httpx.get(f"{url}/api/v1/leaderboard", params=params, timeout=5).json()["rows"]
    except (httpx.HTTPError, KeyError, ValueError):
        return 0
    return sum(row["score"] is not None for row in rows)


@pytest.fixture(scope="module")
def demo(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Demo]:
    data_dir = tmp_path_factory.mktemp("demo")
    port = _free_port()
    url = f"http://127.0.0.1:{port}"
    command = [
        str(Path(sys.executable).with_name("navsim-lb")),
        "demo",
        "--scenes",
        "12",
        "--concurrency",
        "1",
    ]
    environment = {**os.environ, "DATA_DIR": str(data_dir), "PORT": str(port)}
    environment.pop("DATABASE_URL", None)
    environment.pop("BROKER_URL", None)
    log = (data_dir / "demo.log").open("wb")
    process = subprocess.Popen(command, env=environment, stdout=log, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + STARTUP_TIMEOUT_S
        # The two baselines and the demo entry, on the one-stage and the two-stage phase.
        while _scored_entries(url) < 3 or _scored_entries(url, TWO_STAGE_PHASE) < 3:
            assert process.poll() is None, (data_dir / "demo.log").read_text()[-3000:]
            assert time.monotonic() < deadline, "the demo did not score its entries in time"
            time.sleep(1.0)
        tokens = json.loads((data_dir / "demo-tokens.json").read_text())
        yield Demo(url, tokens["team"], tokens["admin"], data_dir)
    finally:
        process.send_signal(signal.SIGTERM)  # stops the worker and the API as Ctrl-C does
        try:
            process.wait(timeout=60)
        except subprocess.TimeoutExpired:
            process.kill()
        log.close()


@pytest.fixture(scope="module")
def browser() -> Iterator[Browser]:
    chromium = shutil.which("chromium")
    assert chromium, "Debian's chromium is missing: `make test` installs it (.ci/browser)"
    with sync_playwright() as playwright:
        launched = playwright.chromium.launch(executable_path=chromium, args=CHROMIUM_ARGS)
        yield launched
        launched.close()


def _page(browser: Browser, width: int = 1280) -> Page:
    page = browser.new_page(viewport={"width": width, "height": 900})
    page.set_default_timeout(30_000)
    return page


def _screenshot(page: Page, name: str, full_page: bool = True) -> None:
    SCREENSHOTS.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=SCREENSHOTS / f"{name}.png", full_page=full_page)


def _scores(page: Page) -> list[float]:
    return [
        float(value)
        for value in page.locator("#leaderboard tbody td.score").evaluate_all(
            "cells => cells.map(cell => cell.dataset.value)"
        )
    ]


def test_leaderboard_rows_sort_both_ways_by_any_column(demo: Demo, browser: Browser) -> None:
    page = _page(browser)
    page.goto(demo.url)
    assert page.locator("#leaderboard tbody tr").count() == 3
    assert page.locator("#leaderboard caption").inner_text().startswith("demo")
    descending = _scores(page)
    assert descending == sorted(descending, reverse=True) and len(set(descending)) == 3
    pdms = page.locator('th[data-key="score"]')
    assert pdms.get_attribute("aria-sort") == "descending"
    pdms.locator("button").click()
    assert pdms.get_attribute("aria-sort") == "ascending" and _scores(page) == sorted(descending)
    pdms.locator("button").click()
    assert pdms.get_attribute("aria-sort") == "descending" and _scores(page) == descending
    method = page.locator('th[data-key="method"]')
    method.locator("button").click()
    names = page.locator("#leaderboard tbody .method-name").all_inner_texts()
    assert method.get_attribute("aria-sort") == "ascending" and names == sorted(names, key=str.lower)
    assert pdms.get_attribute("aria-sort") is None
    assert "sort=method" in page.url  # the order survives a reload and a shared link
    page.reload()
    assert page.locator("#leaderboard tbody .method-name").all_inner_texts() == names
    assert "logged, not weighted" in page.locator('th[data-key="driving_direction_compliance"]').inner_text()
    _screenshot(page, "leaderboard-desktop")
    page.get_by_role("link", name="PDMS v1.0").click()
    expect(page.locator('th[data-key="driving_direction_compliance"]')).to_contain_text("multiplier")
    assert "version=v1.0" in page.url
    page.get_by_role("link", name="EPDMS v2.2").click()
    caption = page.locator("#leaderboard caption")
    expect(caption).to_contain_text("EPDMS v2.2")
    expect(caption).to_contain_text("tag v2.2, commit 359c7f7")  # the exact official code it reproduces
    headers = page.locator("#leaderboard thead th").all_inner_texts()
    assert [h.split("\n")[0] for h in headers[4:13]] == [
        "NC",
        "DAC",
        "DDC",
        "TLC",
        "EP",
        "TTC",
        "LK",
        "HC",
        "EC",
    ]
    assert page.locator('th[data-key="score"]').inner_text().startswith("EPDMS")
    _screenshot(page, "leaderboard-v2.2")


def test_leaderboard_at_390_px_keeps_rank_and_pdms_in_view_without_sideways_scroll(
    demo: Demo, browser: Browser
) -> None:
    page = _page(browser, 390)
    page.goto(demo.url)
    assert page.evaluate("document.documentElement.scrollWidth") <= 390
    for cell in (page.locator("td.score").first, page.locator('th[data-key="rank"]')):
        box = cell.bounding_box()
        assert box is not None and box["x"] >= 0 and box["x"] + box["width"] <= 390
    assert page.locator("td.wide").first.is_hidden()
    _screenshot(page, "leaderboard-390")


def test_api_docs_render_without_internet(demo: Demo, browser: Browser) -> None:
    page = _page(browser)
    outside: list[tuple[str, str]] = []

    def local_only(route: Route) -> None:
        if route.request.url.startswith(demo.url):
            route.continue_()
        else:
            outside.append((route.request.resource_type, route.request.url))
            route.abort()

    page.route("**/*", local_only)
    page.goto(f"{demo.url}/docs")
    page.wait_for_selector(".opblock")
    assert page.locator(".opblock").count() > 20
    assert page.get_by_text("/api/v1/submissions:validate").count() >= 1
    _screenshot(page, "docs")
    assert outside == []
    page.goto(f"{demo.url}/redoc")
    page.wait_for_selector("h1")
    assert "NAVSIM Leaderboard" in page.locator("h1").first.inner_text()
    assert page.get_by_text("Upload a submission").count() >= 1
    # ReDoc's footer links Redocly's logo from its CDN: an image the page renders without.
    assert [kind for kind, _ in outside] in ([], ["image"])


def test_a_team_signs_in_sees_every_problem_then_watches_its_upload_scored(
    demo: Demo, browser: Browser, tmp_path: Path
) -> None:
    broken = tmp_path / "broken.json"
    broken.write_text(
        json.dumps({"format": "navsim-lb/submission", "version": 1, "predictions": {"x": [[0, 0, "a"]]}})
    )
    entry = json.loads((demo.data_dir / "demo-submission.json").read_text())
    entry["method"] = "Uploaded in a browser"
    valid = tmp_path / "valid.json"
    valid.write_text(json.dumps(entry))

    page = _page(browser)
    page.goto(f"{demo.url}/team")
    _screenshot(page, "team-signed-out")
    page.fill("#token", "nlb_not_a_token")
    page.click("#signin button[type=submit]")
    expect(page.locator("#signin-error")).to_contain_text("not valid")
    page.fill("#token", demo.team_token)
    page.click("#signin button[type=submit]")
    page.wait_for_selector("#signed-in:not([hidden])")
    expect(page.locator("#team-name")).to_have_text("demo-team")

    page.set_input_files("#upload input[type=file]", broken)
    page.click("#upload-button")
    problems = page.locator("#problems")
    problems.wait_for()
    text = problems.inner_text()
    assert "poses must be numbers, found text where a number was expected" in text
    assert "token of the split is missing" in text and "show all 13 problems" not in text
    expect(page.locator("#history tbody tr")).not_to_have_count(0)
    history_before = page.locator("#history tbody tr").count()
    _screenshot(page, "team-problems")

    page.set_input_files("#upload input[type=file]", valid)
    page.click("#upload-button")
    page.wait_for_selector("#progress:not([hidden])")
    assert problems.is_hidden()
    page.wait_for_function(
        "document.querySelector('#upload-status').textContent.includes('is scored')",
        timeout=SCORING_TIMEOUT_MS,
    )
    assert page.locator("#progress-bar").get_attribute("value") == "100"
    expect(page.locator("#history tbody tr")).to_have_count(history_before + 1)
    assert page.locator("#history tbody tr").first.inner_text().startswith(str(_latest_id(demo)))
    _screenshot(page, "team-scored")

    page.get_by_role("link", name="see its results").click()
    page.wait_for_selector("#histograms figure")
    assert page.locator("#histograms figure").count() == 1 + 6  # PDMS and every subscore of v1.1
    expect(page.locator("#breakdown thead")).to_contain_text("Constant Velocity")  # next to the baselines
    assert page.locator("#worst tbody tr").count() == 12  # fewer tokens than the list shows
    page.locator("#worst tbody td.token a").first.click()
    page.wait_for_selector("#scene:not([hidden])")
    page.wait_for_function("document.querySelector('#scene-image').naturalWidth > 0")
    expect(page.locator("#scene-caption")).to_contain_text("PDMS v1.1")
    demo_entry = page.locator("#other option", has_text="Noisy human (demo)")
    expect(demo_entry).to_have_count(1)  # the entries of this split alone: not the two-stage demo entry
    page.select_option("#other", value=demo_entry.get_attribute("value"))
    expect(page.locator("#diff-counts")).to_contain_text("of 12 tokens both scored")
    _screenshot(page, "submission")
    page.get_by_role("link", name="EPDMS v2.2").click()
    expect(page.locator("#histograms figure")).to_have_count(1 + 9)  # EPDMS and its nine subscores
    expect(page.locator("#worst thead")).to_contain_text("EPDMS")
    _screenshot(page, "submission-v2.2")

    narrow = _page(browser, 390)
    narrow.goto(f"{demo.url}/team")  # the token is per tab: this one signs in again
    narrow.fill("#token", demo.team_token)
    narrow.click("#signin button[type=submit]")
    narrow.wait_for_selector("#history tbody tr")
    assert narrow.evaluate("document.documentElement.scrollWidth") <= 390
    _screenshot(narrow, "team-390")
    narrow.goto(f"{demo.url}/submissions/{_latest_id(demo)}")
    narrow.wait_for_selector("#histograms figure")
    assert narrow.evaluate("document.documentElement.scrollWidth") <= 390
    # The breakdown's numbers, the submission's and the baselines', are on screen without scrolling sideways.
    values = narrow.locator("#breakdown tbody tr").first.locator("td").all()
    assert len(values) >= 2
    for value in values:
        box = value.bounding_box()
        assert box is not None and box["x"] + box["width"] <= 390, box
    _screenshot(narrow, "submission-390")


def _latest_id(demo: Demo) -> int:
    headers = {"Authorization": f"Bearer {demo.team_token}"}
    return int(httpx.get(f"{demo.url}/api/v1/submissions", headers=headers, timeout=5).json()[0]["id"])


def test_team_registration_shows_its_token_once(demo: Demo, browser: Browser) -> None:
    page = _page(browser)
    page.goto(f"{demo.url}/team")
    page.fill("#register input[name=name]", "browser-team")
    page.fill("#register input[name=members]", "Ada, Grace")
    page.click("#register button[type=submit]")
    page.wait_for_selector("#registered:not([hidden])")
    token = page.locator("#new-token").inner_text()
    me = httpx.get(f"{demo.url}/api/v1/me", headers={"Authorization": f"Bearer {token}"}, timeout=5).json()
    assert me["team"] == "browser-team" and me["approval"] == "pending"
    page.click("#register button[type=submit]")  # the same name again
    expect(page.locator("#register-error")).to_contain_text("browser-team")


def test_the_admin_console_follows_a_rerun_and_a_rescore_without_a_reload(
    demo: Demo, browser: Browser
) -> None:
    page = _page(browser)
    page.goto(f"{demo.url}/admin")
    page.fill("#token", demo.admin_token)
    page.click("#login button[type=submit]")
    page.wait_for_selector("#dashboard:not([hidden])")
    expect(page.locator("#workers")).to_contain_text("Broker: answers")
    expect(page.locator("#workers")).to_contain_text("alive (heartbeats in the database): navsim-lb-1@")
    row = page.locator("#submissions tbody tr", has_text="Noisy human (demo)")
    expect(row).to_contain_text("scored")
    page.evaluate("window.notReloaded = true")
    row.get_by_role("button", name="re-run").click()
    # Every action that changes data asks first.
    page.locator("#confirm").get_by_role("button", name="Re-run it").click()
    queue = page.locator("#queue tbody")
    expect(row.locator(".status")).not_to_have_text("scored", timeout=10_000)  # queued or running, live
    expect(row.locator(".status")).to_have_text("scored", timeout=SCORING_TIMEOUT_MS)
    expect(queue).to_contain_text("Nothing is waiting.", timeout=SCORING_TIMEOUT_MS)
    assert page.evaluate("window.notReloaded") is True
    page.check("#failed-only")
    expect(page.locator("#submissions tbody tr")).to_have_count(0)
    page.uncheck("#failed-only")
    page.get_by_role("button", name="tokens and quotas").first.click()
    expect(page.locator("#tokens tbody")).to_contain_text("active")
    page.fill("#audit-filter", "rerun")
    expect(page.locator("#audit tbody")).to_contain_text("rerun")
    _screenshot(page, "admin")

    row.get_by_role("link").click()  # the submission page, read with the organiser's token
    page.wait_for_selector("#histograms figure")
    expect(page.locator("#title")).to_contain_text("Noisy human (demo)")
    page.locator("#worst tbody td.token a").first.click()
    page.wait_for_function("document.querySelector('#scene-image').naturalWidth > 0")
    page.go_back()
    page.wait_for_selector("#dashboard:not([hidden])")

    page.click("#rescore button[type=submit]")
    page.locator("#confirm").get_by_role("button", name="Rescore all").click()
    page.get_by_role("link", name="open its rank-change report").click()
    expect(page.locator("#summary")).to_contain_text("complete", timeout=SCORING_TIMEOUT_MS)
    expect(page.locator("#summary")).to_contain_text("Kendall's tau")
    _screenshot(page, "rescore-report")


DESKTOP, PHONE = 1366, 390


def _api(demo: Demo, method: str, path: str, token: str, **kwargs: object) -> httpx.Response:
    headers = {"Authorization": f"Bearer {token}"}
    return httpx.request(method, f"{demo.url}/api/v1{path}", headers=headers, timeout=10, **kwargs)  # type: ignore[arg-type]


def _fits(page: Page) -> None:
    assert page.evaluate("document.documentElement.scrollWidth") <= page.viewport_size["width"]  # type: ignore[index]


def _team_page(browser: Browser, demo: Demo, width: int, token: str) -> Page:
    page = _page(browser, width)
    page.goto(f"{demo.url}/team")
    page.fill("#token", token)
    page.click("#signin button[type=submit]")
    page.wait_for_selector("#signed-in:not([hidden])")
    return page


@pytest.mark.parametrize("width", [DESKTOP, PHONE])
def test_a_team_sees_a_disqualification_with_its_reason_and_the_entry_the_board_counts(
    demo: Demo, browser: Browser, width: int
) -> None:
    entries = [
        s for s in _api(demo, "GET", "/submissions", demo.team_token).json() if s["status"] == "scored"
    ]
    sanctioned = entries[0]["id"]
    reason = "its trajectories copy the logged future"
    moderate = f"/admin/submissions/{sanctioned}/disqualify"
    assert _api(demo, "POST", moderate, demo.admin_token, json={"reason": reason}).status_code == 200
    try:
        page = _team_page(browser, demo, width, demo.team_token)
        row = page.locator("#history tbody tr", has_text=f"{sanctioned}").first
        expect(row.locator(".sanction")).to_have_text(f"disqualified by an organiser: {reason}")
        expect(row).to_contain_text("cannot be final")
        assert row.get_by_role("button", name="make final").count() == 0
        # The row the team page says is shown is the one the board ranks.
        # One entry per phase: the one-stage demo phase's and the two-stage one's.
        counted = [
            r["submission_id"]
            for phase in (PHASE, TWO_STAGE_PHASE)
            for r in httpx.get(f"{demo.url}/api/v1/leaderboard", params={"phase": phase}, timeout=10).json()[
                "rows"
            ]
            if r["team"] == "demo-team"
        ]
        shown = page.locator("#history tbody tr", has_text="✓ shown")
        expect(shown).to_have_count(len(counted))
        assert sorted(int(text) for text in shown.locator("td:first-child").all_inner_texts()) == sorted(
            counted
        )
        assert sanctioned not in counted
        _fits(page)
        _screenshot(page, f"team-sanction-{width}")
        page.goto(f"{demo.url}/submissions/{sanctioned}")
        expect(page.locator("#sanctions")).to_have_text(f"Disqualified by an organiser: {reason}.")
        _screenshot(page, f"submission-sanction-{width}")
    finally:
        _api(demo, "POST", moderate, demo.admin_token, json={"disqualified": False, "reason": "lifted"})


@pytest.mark.parametrize("width", [DESKTOP, PHONE])
def test_a_pending_team_is_told_before_it_fills_a_form(demo: Demo, browser: Browser, width: int) -> None:
    registered = httpx.post(f"{demo.url}/api/v1/teams", json={"name": f"pending-{width}"}, timeout=10).json()
    page = _team_page(browser, demo, width, registered["token"])
    expect(page.locator("#cannot-upload")).to_contain_text("waiting for an organiser's approval")
    assert page.locator("#upload").is_hidden()
    _fits(page)
    _screenshot(page, f"team-pending-{width}")


@pytest.mark.parametrize("width", [DESKTOP, PHONE])
def test_an_unknown_page_or_submission_is_a_404_page(demo: Demo, browser: Browser, width: int) -> None:
    page = _page(browser, width)
    for path in ("/no-such-page", "/submissions/99999"):
        response = page.goto(f"{demo.url}{path}")
        assert response is not None and response.status == 404
        expect(page.locator("h1")).to_have_text("Page not found")
        expect(page.get_by_role("link", name="leaderboard").last).to_be_visible()
    expect(page.locator("main")).to_contain_text("Submission 99999 does not exist.")
    _fits(page)
    _screenshot(page, f"not-found-{width}")


def test_every_page_writes_a_score_as_the_server_does(demo: Demo, browser: Browser) -> None:
    from server.numbers import percent

    page = _page(browser, DESKTOP)
    page.goto(f"{demo.url}/admin")
    # Halves (95.25 is exact), near-halves, ends and undefined values, through common.js's pct.
    values = [0.9525, 0.95249999, 0.12345, 0.0005, 1.0, 0.0, -0.0004, 1 / 3, 2 / 3, 0.8875, 0.1235]
    assert page.evaluate("values => values.map(pct)", values) == [percent(v) for v in values]
    assert page.evaluate("[pct(null), pct(undefined), counted(1, 'entry', 'entries')]") == [
        "–",
        "–",
        "1 entry",
    ]
    # The board and the submission page show the same figure for the same entry.
    page.goto(demo.url)
    row = page.locator("#leaderboard tbody tr", has_text="demo-team").first
    on_board = row.locator("td.score").inner_text()
    team = _team_page(browser, demo, DESKTOP, demo.team_token)
    board = httpx.get(f"{demo.url}/api/v1/leaderboard", timeout=10).json()["rows"]
    counted = next(r for r in board if r["team"] == "demo-team")
    assert on_board == percent(counted["score"])
    team.goto(f"{demo.url}/submissions/{counted['submission_id']}")
    team.wait_for_selector("#breakdown tbody tr")
    assert team.locator("#breakdown tbody tr").first.locator(".meter").first.inner_text() == on_board


def _admin(browser: Browser, demo: Demo, width: int) -> Page:
    page = _page(browser, width)
    page.goto(f"{demo.url}/admin")
    page.fill("#token", demo.admin_token)
    page.click("#login button[type=submit]")
    page.wait_for_selector("#dashboard:not([hidden])")
    return page


@pytest.mark.parametrize("width", [DESKTOP, PHONE])
def test_the_admin_console_asks_before_it_changes_anything(demo: Demo, browser: Browser, width: int) -> None:
    page = _admin(browser, demo, width)
    row = page.locator("#submissions tbody tr", has_text="Noisy human (demo)")
    submission_id = int(row.locator("td").first.inner_text().split()[-1])
    dialog = page.locator("#confirm")

    def admin_view() -> dict:
        return _api(demo, "GET", f"/admin/submissions/{submission_id}", demo.admin_token).json()

    row.get_by_role("button", name="hide").click()
    expect(dialog).to_be_visible()
    expect(dialog).to_contain_text(f"Hide submission {submission_id}?")
    _screenshot(page, f"admin-confirm-{width}")
    dialog.get_by_role("button", name="Keep it as it is").click()
    expect(dialog).to_be_hidden()
    assert admin_view()["admin_hidden"] is False  # nothing changed
    row.get_by_role("button", name="hide").click()
    dialog.get_by_role("button", name="Hide it").click()
    expect(row).to_contain_text("hidden")
    assert admin_view()["admin_hidden"] is True
    row.get_by_role("button", name="show").click()
    dialog.get_by_role("button", name="Show it").click()
    expect(row.get_by_role("button", name="hide")).to_be_visible()

    # A disqualification needs its reason, which the audit log then shows readably.
    row.get_by_role("button", name="disqualify").click()
    dialog.get_by_role("button", name="Disqualify it").click()
    expect(dialog).to_be_visible()  # refused without a reason
    reason = f"a reason long enough to wrap in the audit log at {width} px, not run off the table"
    dialog.locator("textarea").fill(reason)
    dialog.get_by_role("button", name="Disqualify it").click()
    expect(row).to_contain_text(f"disqualified: {reason}")
    audit = page.locator("#audit tbody tr", has_text="disqualify").first
    expect(audit.locator("dd", has_text=reason)).to_be_visible()
    box, table = audit.locator("dd", has_text=reason).bounding_box(), page.locator("#audit").bounding_box()
    assert box is not None and table is not None and box["x"] + box["width"] <= table["x"] + table["width"]
    row.get_by_role("button", name="requalify").click()
    dialog.get_by_role("button", name="Lift it").click()
    expect(row.get_by_role("button", name="disqualify")).to_be_visible()
    assert admin_view()["disqualified"] is False
    _fits(page)
    _screenshot(page, f"admin-{width}")


@pytest.mark.parametrize("width", [DESKTOP, PHONE])
def test_a_new_token_is_shown_once_in_a_dialog_with_a_copy_button(
    demo: Demo, browser: Browser, width: int
) -> None:
    page = _admin(browser, demo, width)
    page.locator("#teams tbody tr", has_text="demo-team").get_by_role(
        "button", name="tokens and quotas"
    ).click()
    page.get_by_role("button", name="new token").click()
    dialog = page.locator("#token-dialog")
    expect(dialog).to_be_visible()
    secret = dialog.locator("#token-value").inner_text()
    assert secret.startswith("nlb_")
    dialog.get_by_role("button", name="Copy").click()
    expect(dialog.locator("#token-copied")).to_contain_text("not shown again")
    _fits(page)
    _screenshot(page, f"admin-new-token-{width}")
    dialog.get_by_role("button", name="Done").click()
    expect(dialog).to_be_hidden()
    expect(page.locator("#token-value")).to_have_text("")  # shown once: cleared when the dialog closes
    assert secret not in page.content()
    assert _api(demo, "GET", "/me", secret).json()["team"] == "demo-team"


def test_the_rescore_report_fits_a_phone(demo: Demo, browser: Browser) -> None:
    page = _admin(browser, demo, PHONE)
    page.click("#rescore button[type=submit]")
    page.locator("#confirm").get_by_role("button", name="Rescore all").click()
    page.get_by_role("link", name="open its rank-change report").click()
    expect(page.locator("#summary")).to_contain_text("complete", timeout=SCORING_TIMEOUT_MS)
    _fits(page)
    _screenshot(page, "rescore-report-390")


def _baseline_id(demo: Demo) -> int:
    rows = httpx.get(f"{demo.url}/api/v1/leaderboard", timeout=5).json()["rows"]
    return min(row["submission_id"] for row in rows if row["baseline"])


@pytest.mark.parametrize("width", [DESKTOP, PHONE])
def test_the_drill_down_fits_the_window_follows_the_version_and_the_diff_lists_every_token(
    demo: Demo, browser: Browser, width: int
) -> None:
    """A link with ?version=&token=&compare= opens the page on that token's picture under that version, the
    whole picture in the window (the phone's layout on a phone); the comparison with a baseline lists every
    differing token, page by page, each a link that draws its scene; the histograms' ticks read in %."""
    page = _team_page(browser, demo, width, demo.team_token)
    page.set_viewport_size({"width": width, "height": 768 if width == DESKTOP else 844})
    pictures: list[str] = []
    page.on("request", lambda request: pictures.append(request.url) if ".png?" in request.url else None)
    entry = next(  # the one-stage phase's: a two-stage entry is drawn by its groups
        s
        for s in _api(demo, "GET", "/submissions", demo.team_token).json()
        if s["status"] == "scored" and s["phase"] == PHASE
    )
    token = _api(demo, "GET", f"/submissions/{entry['id']}/tokens", demo.team_token).json()[0]["token"]
    baseline = _baseline_id(demo)
    # Two tokens a page, so that the demo's dozen tokens go over several pages.
    script = httpx.get(f"{demo.url}/static/submission.js", timeout=5).text
    assert "const DIFF_PAGE = 25;" in script
    paged = script.replace("const DIFF_PAGE = 25;", "const DIFF_PAGE = 2;")
    page.route(
        "**/static/submission.js", lambda route: route.fulfill(body=paged, content_type="text/javascript")
    )
    page.goto(f"{demo.url}/submissions/{entry['id']}?version=v2.2&token={token}&compare={baseline}")
    page.wait_for_function("document.querySelector('#scene-image').naturalWidth > 0")
    layout = "wide" if width == DESKTOP else "narrow"
    assert any("version=v2.2" in url and f"layout={layout}" in url for url in pictures), pictures
    assert page.evaluate("document.querySelector('#scene-image').naturalWidth") == (
        1100 if width == DESKTOP else 360
    )
    # A phone's picture ends under its last legend: few infractions, a shorter picture, no blank tail.
    height = page.evaluate("document.querySelector('#scene-image').naturalHeight")
    assert (height == 660) if width == DESKTOP else (500 < height < 740), height
    expect(page.locator("#scene-caption")).to_contain_text("EPDMS v2.2")
    expect(page.locator("#version-tabs [aria-current=page]")).to_have_text("EPDMS v2.2")
    box = page.locator("#scene-image").bounding_box()
    viewport = page.viewport_size
    assert box is not None and viewport is not None
    assert box["width"] <= viewport["width"] and box["height"] <= viewport["height"], box
    page.evaluate("document.querySelector('#scene-title').scrollIntoView({block: 'start'})")
    box = page.locator("#scene-image").bounding_box()
    assert box is not None and box["y"] >= 0 and box["y"] + box["height"] <= viewport["height"], box
    _fits(page)
    _screenshot(page, f"drilldown-{width}", full_page=False)  # the window as the user sees it

    # The comparison: every differing token over the pages, each a link to its drill-down here.
    expect(page.locator("#diff-counts")).to_contain_text("better")
    counts = page.locator("#diff-counts").inner_text()
    better, worse = (int(counts.split(" better")[0].split()[-1]), int(counts.split(" worse")[0].split()[-1]))
    listed = []
    for name in ("better", "worse"):
        while True:
            listed += page.locator(f"#diff-{name} tbody td.token a").all_inner_texts()
            following = page.locator(f"#diff-{name}-pages button", has_text="next")
            if following.count() == 0 or following.is_disabled():
                break
            following.click()
    assert len(listed) == len(set(listed)) == better + worse > 2
    for name, count in (("better", better), ("worse", worse)):
        assert page.locator(f"#diff-{name}-pages").is_visible() == (count > 2)
    link = page.locator("#diff-worse tbody td.token a, #diff-better tbody td.token a").first
    chosen = link.inner_text()
    assert f"token={chosen}" in (link.get_attribute("href") or "")
    link.click()
    expect(page.locator("#scene-title")).to_have_text(f"Scene drill-down: {chosen}")
    expect(page.locator("#scene-image")).to_have_attribute("alt", re.compile(f"scene {chosen} under"))
    assert f"token={chosen}" in page.url and f"compare={baseline}" in page.url
    page.locator("#diff").scroll_into_view_if_needed()
    _fits(page)
    _screenshot(page, f"diff-{width}")

    # Histograms: ticks in %, at least 11 px tall on screen.
    ticks = page.locator("#histograms figure").first.locator("text")
    assert "100 %" in ticks.all_text_contents()
    heights = [ticks.nth(i).bounding_box()["height"] for i in range(ticks.count())]  # type: ignore[index]
    assert min(heights) >= 11, heights


@pytest.mark.parametrize("width", [DESKTOP, PHONE])
def test_the_rules_are_one_click_from_every_page_and_the_board_explains_its_headers(
    demo: Demo, browser: Browser, width: int
) -> None:
    page = _page(browser, width)
    for path in ("/", "/team", "/admin"):
        page.goto(f"{demo.url}{path}")
        expect(page.locator("header.site").get_by_role("link", name="Rules")).to_be_visible()
    page.goto(f"{demo.url}/?version=v2.2")
    header = page.locator('th[data-key="lane_keeping"]')
    if width == DESKTOP:
        assert "lane keeping" in (header.locator("button").get_attribute("title") or "")
        # EC is undefined on every token of the demo (one token per log): its – says why and links the rules.
        dash = page.locator("#leaderboard tbody tr").first.locator("a.undefined")
        assert "no token has the frame of its log 0.5 s earlier" in (dash.get_attribute("title") or "")
        header.get_by_role("link", name="LK in the rules").click()
        expect(page.locator("#metric-LK")).to_contain_text("lane keeping")
        assert page.url.endswith("/rules#metric-LK")
    else:
        expect(page.locator("#ec-undefined")).to_contain_text(
            "no token has the frame of its log 0.5 s earlier"
        )
        page.locator("header.site").get_by_role("link", name="Rules").click()
    expect(page.locator("h1")).to_have_text("Rules and scores")
    section = page.locator("#version-v2\\.2")
    expect(section.locator(".formula")).to_have_text(
        "EPDMS = NC × DAC × TLC × DDC × (5·EP + 5·TTC + 2·LK + 2·HC + 2·EC) / 16"
    )
    expect(
        section.get_by_role("link", name="navsim/planning/script/run_pdm_score_one_stage.py")
    ).to_have_attribute(
        "href",
        "https://github.com/autonomousvision/navsim/blob/v2.2/navsim/planning/script/run_pdm_score_one_stage.py",
    )
    expect(page.locator("#seeds")).to_be_visible()
    expect(page.get_by_role("link", name="NAVSIM: Data-Driven Non-Reactive")).to_have_attribute(
        "href", "https://arxiv.org/abs/2406.15349"
    )
    _fits(page)
    _screenshot(page, f"rules-{width}")


def _new_team(demo: Demo, team: str) -> tuple[int, str]:
    """Register an approved team as an organiser; return its id and a token of it."""
    created = _api(demo, "POST", "/admin/teams", demo.admin_token, json={"name": team})
    assert created.status_code == 201, created.text
    team_id = created.json()["id"]
    token = _api(demo, "POST", f"/admin/teams/{team_id}/tokens", demo.admin_token, json={"name": "t"})
    return team_id, token.json()["token"]


@pytest.mark.parametrize("width", [DESKTOP, PHONE])
def test_a_team_reads_what_its_file_is_and_when_its_quota_resets_once(
    demo: Demo, browser: Browser, width: int, tmp_path: Path
) -> None:
    """A text file named .pkl is named for what it is; a quota's reset time is stated once, in the list and in
    the refusal; the history and the board write the entry's score alike (one rounding, one unit)."""
    from server.numbers import percent

    team = f"quota-{width}"
    team_id, token = _new_team(demo, team)
    limited = _api(
        demo, "PUT", f"/admin/teams/{team_id}/quotas", demo.admin_token, json={"phase": PHASE, "per_day": 1}
    )
    assert limited.status_code == 200, limited.text
    page = _team_page(browser, demo, width, token)
    daily = page.locator("#quotas li", has_text=f"{PHASE}, per day")
    expect(daily).to_contain_text("1 of 1 left")
    assert daily.inner_text().count("resets") == 1

    text = tmp_path / "entry.pkl"
    text.write_text("hello, this is no pickle")
    page.select_option("#phase", PHASE)
    page.set_input_files("#upload input[type=file]", text)
    page.click("#upload-button")
    expect(page.locator("#problems")).to_contain_text("entry.pkl is text starting 'hello, this is no pickle'")
    expect(page.locator("#upload-status")).to_contain_text("entry.pkl: 1 problem in the file")

    entry = json.loads((demo.data_dir / "demo-submission.json").read_text()) | {"method": f"Quota {width}"}
    valid = tmp_path / "valid.json"
    valid.write_text(json.dumps(entry))
    page.set_input_files("#upload input[type=file]", valid)
    page.click("#upload-button")
    page.wait_for_function(
        "document.querySelector('#upload-status').textContent.includes('is scored')",
        timeout=SCORING_TIMEOUT_MS,
    )
    again = tmp_path / "again.json"  # other bytes: the same file is refused as a repeat, before the quota
    again.write_text(json.dumps(entry | {"method": f"Quota {width}, again"}))
    page.set_input_files("#upload input[type=file]", again)
    page.click("#upload-button")
    refusal = page.locator("#upload-status")
    expect(refusal).to_contain_text("quota exhausted: 1 submission per UTC day")
    assert refusal.inner_text().count("resets") == 1, refusal.inner_text()
    expect(daily).to_contain_text("0 of 1 left")  # the list follows the uploads
    _fits(page)
    _screenshot(page, f"team-quota-{width}")

    # The same figure on the team's history, the board and the submission page.
    mine = next(s for s in _api(demo, "GET", "/submissions", token).json() if s["status"] == "scored")
    score = percent(mine["results"]["v1.1"]["all"]["score"])
    history = page.locator("#history tbody tr", has_text=f"Quota {width}")
    expect(history.locator('td[data-label="PDMS v1.1"]')).to_have_text(score)
    page.goto(f"{demo.url}/?phase={PHASE}&version=v1.1")
    expect(page.locator("#leaderboard tbody tr", has_text=team).locator("td.score")).to_have_text(score)
    page.goto(f"{demo.url}/submissions/{mine['id']}?version=v1.1")
    expect(page.locator("#breakdown tbody tr").first.locator(".meter").first).to_have_text(score)


def _leaked_entry(demo: Demo, team: str) -> str:
    """Register a team as an organiser and upload, as it, the demo split's logged human future; return its token."""
    from scorer.baselines import baseline_submission
    from scorer.submission import dump_submission_json

    _, token = _new_team(demo, team)
    split_dir = demo.data_dir / "splits" / "demo"
    leaked = dump_submission_json(baseline_submission(split_dir, "human", f"Oracle {team}"))
    uploaded = _api(demo, "POST", "/submissions", token, files={"file": ("oracle.json", leaked)})
    assert uploaded.status_code == 202, uploaded.text
    return token


@pytest.mark.parametrize("width", [DESKTOP, PHONE])
def test_an_organiser_reads_an_integrity_flag_with_its_evidence_and_decides(
    demo: Demo, browser: Browser, width: int
) -> None:
    """Once the leaked entry is scored, the worker's check flags it by itself: the console's nav counts it as
    new, the integrity page marks it new with its evidence, and nothing changes until the organiser decides."""
    team = f"oracle-{width}"
    team_token = _leaked_entry(demo, team)
    page = _admin(browser, demo, width)
    link = page.locator("#integrity-link")
    expect(link.locator(".badge.alert")).to_have_text(re.compile(r"^\d+ new$"), timeout=SCORING_TIMEOUT_MS)
    assert "you have not opened yet" in (link.locator(".badge.alert").get_attribute("title") or "")
    _fits(page)
    page.locator("nav.tabs").scroll_into_view_if_needed()
    _screenshot(page, f"admin-integrity-count-{width}", full_page=False)
    link.click()
    page.wait_for_selector("#checks:not([hidden])")
    row = page.locator("table.flags tbody tr", has_text=team).filter(has_text="Leaked log")
    expect(row).to_contain_text("Leaked log", timeout=60_000)
    expect(row.locator(".badge.alert")).to_have_text("new")
    expect(row).to_contain_text("median displacement to the logged human future 0.0000 m")
    expect(row).to_contain_text("(seed 0)")
    row.locator("summary", has_text="evidence").click()
    expect(row.locator("details dl")).to_contain_text("closest tokens")
    expect(row.locator("details dl")).to_contain_text("ade m 0")
    submission_id = int(row.locator("td").nth(1).inner_text().split()[0])

    def admin_view() -> dict:
        return _api(demo, "GET", f"/admin/submissions/{submission_id}", demo.admin_token).json()

    dialog = page.locator("#confirm")
    row.get_by_role("button", name="disqualify").click()
    expect(dialog).to_contain_text(f"Disqualify submission {submission_id}?")
    dialog.get_by_role("button", name="Keep it as it is").click()
    assert admin_view()["disqualified"] is False  # the flag alone changes nothing
    _screenshot(page, f"integrity-{width}")
    row.get_by_role("button", name="disqualify").click()
    dialog.locator("textarea").fill("its trajectories are the logged future")
    dialog.get_by_role("button", name="Disqualify it").click()
    expect(row).to_contain_text("disqualified")
    assert admin_view()["disqualified"] is True
    _fits(page)
    _screenshot(page, f"integrity-decided-{width}")
    # Opened once, the flag is no longer new in this browser; an organiser may still check at once.
    seen = page.evaluate("JSON.parse(localStorage.getItem('navsim-lb-integrity-seen'))")
    assert f"leaked_log:{submission_id}:" in seen
    page.reload()
    page.wait_for_selector("#checks:not([hidden])")
    expect(row).to_contain_text("disqualified")
    expect(row.locator(".badge")).to_have_count(0)
    page.select_option("#split", "demo")
    page.get_by_role("button", name="Run the checks now").click()
    expect(page.locator("#message")).to_contain_text("Checking split demo")
    expect(row).to_contain_text("disqualified", timeout=60_000)
    page.get_by_role("link", name="← Admin console").click()
    expect(page.locator("#integrity-link")).to_contain_text("Integrity checks")
    # The team sees the organiser's decision, never the flag.
    seen = _api(demo, "GET", f"/submissions/{submission_id}", team_token).json()
    assert seen["disqualified"] is True and "leaked" not in json.dumps(seen).lower()
    assert _api(demo, "GET", "/admin/integrity", team_token).status_code in (401, 403)


def test_the_submission_page_spells_out_its_metrics_and_why_ec_is_undefined(
    demo: Demo, browser: Browser
) -> None:
    board = httpx.get(f"{demo.url}/api/v1/leaderboard", timeout=10).json()["rows"]
    entry = next(row for row in board if row["team"] == "demo-team")["submission_id"]
    page = _team_page(browser, demo, DESKTOP, demo.team_token)
    page.goto(f"{demo.url}/submissions/{entry}")
    page.get_by_role("link", name="EPDMS v2.2").click()
    expect(page.locator("#histograms figure")).to_have_count(1 + 9)
    rows = page.locator("#breakdown tbody tr")
    assert "no at-fault collisions" in (rows.nth(1).locator("th").get_attribute("title") or "")
    ec = rows.filter(has=page.locator("th", has_text="EC"))
    assert "two-frame extended comfort" in (ec.locator("th").get_attribute("title") or "")
    assert "no token has the frame of its log 0.5 s earlier" in (
        ec.locator(".meter").first.get_attribute("title") or ""
    )


@pytest.mark.parametrize("width", [DESKTOP, PHONE])
def test_a_board_row_with_a_page_opens_it_when_clicked_anywhere(
    demo: Demo, browser: Browser, width: int
) -> None:
    """The server marks the rows of published entries with their page (tests/test_api_drilldown.py); the
    demo's phase is open, so this row is marked here as the server marks it once the phase has closed."""
    page = _page(browser, width)
    page.goto(demo.url)
    row = page.locator("table.board tbody tr").first
    target = f"/submissions/{_latest_id(demo)}"
    row.evaluate("(row, target) => { row.dataset.href = target; }", target)
    assert row.evaluate("(row) => getComputedStyle(row).cursor") == "pointer"
    row.locator("td.score").click()  # a cell a phone shows too
    page.wait_for_url(f"**{target}")


@pytest.mark.parametrize("width", [DESKTOP, PHONE])
def test_the_two_stage_tab_and_a_submissions_groups_are_readable(
    demo: Demo, browser: Browser, width: int
) -> None:
    """The two-stage phase's tab: the combined EPDMS with each stage, the official code it reproduces; the
    demo entry's page: per group each frame's stage-one score, its weighted stage two and the weights."""
    page = _page(browser, width)
    page.goto(demo.url)
    page.get_by_role("link", name=TWO_STAGE_PHASE).click()
    expect(page.locator("#leaderboard caption")).to_contain_text(
        "run_pdm_score_from_submission.py: two-stage"
    )
    expect(page.locator("#leaderboard tbody tr")).to_have_count(3)
    expect(page.locator("#leaderboard thead")).to_contain_text("Stage 1")
    expect(page.locator("nav[aria-label='Metric version'] a")).to_have_text(["EPDMS v2.2-two-stage"])
    # Every header shown heads a cell shown: a phone hides the stage columns, headers and cells alike.
    shown = "elements => elements.filter((element) => element.offsetParent !== null).length"
    headers = page.locator("#leaderboard thead th").evaluate_all(shown)
    assert headers == page.locator("#leaderboard tbody tr").first.locator("td").evaluate_all(shown)
    _fits(page)
    _screenshot(page, f"two-stage-board-{width}")

    board = httpx.get(f"{demo.url}/api/v1/leaderboard", params={"phase": TWO_STAGE_PHASE}, timeout=10).json()
    entry = next(row for row in board["rows"] if row["team"] == "demo-team")
    team = _team_page(browser, demo, width, demo.team_token)
    team.goto(f"{demo.url}/submissions/{entry['submission_id']}")
    team.wait_for_selector("#group-table tbody tr")
    expect(team.locator("#group-table tbody tr")).to_have_count(6)  # 3 groups x their two frames
    expect(team.locator("#group-table .weight")).to_have_count(30)  # 5 synthetic successors per frame
    # The breakdown: the combined score, then each stage's rows under its name.
    sections = team.locator("#breakdown tbody tr.section")
    expect(sections).to_have_text(
        ["Stage 1: the logged frames", "Stage 2: their synthetic successors, weighted"]
    )
    _fits(team)
    _screenshot(team, f"two-stage-submission-{width}")

    # The team's history: a table per phase with that phase's versions only, and each stage's score.
    from server.numbers import percent

    mine = _api(demo, "GET", f"/submissions/{entry['submission_id']}", demo.team_token).json()
    combined = mine["results"]["v2.2-two-stage"]["all"]
    team.goto(f"{demo.url}/team")
    phase = team.locator("#history section.history-phase", has=team.locator("h3", has_text=TWO_STAGE_PHASE))
    row = phase.locator(
        "tbody tr", has=team.get_by_role("link", name=str(entry["submission_id"]), exact=True)
    )
    for name, key in (
        ("EPDMS v2.2-two-stage", "score"),
        ("Stage 1", "stage_one_score"),
        ("Stage 2", "stage_two_score"),
    ):
        expect(row.locator(f'td[data-label="{name}"]')).to_have_text(percent(combined[key]))
    expect(phase.locator('td[data-label="PDMS v1.1"]')).to_have_count(0)  # another phase's version
    one_stage = team.locator(
        "#history section.history-phase", has=team.locator("h3", has_text=re.compile(f"^Phase {PHASE} "))
    )
    expect(one_stage.locator('td[data-label="Stage 1"]')).to_have_count(0)
    _fits(team)
    phase.scroll_into_view_if_needed()
    _screenshot(team, f"two-stage-history-{width}")
