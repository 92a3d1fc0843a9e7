"""The rules page and the board's explanations: formulas written from the versions' data, every subscore in
words, the official code and the papers, and a link to the rules from every page."""

from __future__ import annotations

import html

from server_testing import World, submit_scored, uniform

from scorer.versions import METRIC_NAMES, VERSIONS, VersionName
from server.services.rules import SUBSCORES, all_version_rules, formula, header_title


def test_formulas_are_the_papers_and_follow_the_version_data() -> None:
    # PDMS as NAVSIM's paper writes it (v1.1: DDC logged with weight 0), EPDMS as NAVSIM v2's.
    assert formula(VERSIONS[VersionName.V1_1]) == "PDMS = NC × DAC × (5·EP + 5·TTC + 2·C + 0·DDC) / 12"
    assert formula(VERSIONS[VersionName.V2_2]) == (
        "EPDMS = NC × DAC × TLC × DDC × (5·EP + 5·TTC + 2·LK + 2·HC + 2·EC) / 16"
    )
    version = VERSIONS[VersionName.V1_0]
    weights = (("progress", 7.0), ("ttc", 1.0))
    heavier = version._replace(evaluation=version.evaluation._replace(weighted_rows=weights))
    assert formula(heavier) == "PDMS = NC × DAC × DDC × (7·EP + 1·TTC) / 8"


def test_every_version_names_its_script_at_its_tag_or_commit() -> None:
    rules = {rule.name: rule for rule in all_version_rules()}
    assert list(rules) == list(VERSIONS)
    assert rules["v2.2"].script_url.endswith("/blob/v2.2/navsim/planning/script/run_pdm_score_one_stage.py")
    assert "/blob/8021f918b907360ac5ae6fbc252b5f96f04db966/" in rules["v2.2-prefix"].script_url
    assert rules["v2.2-two-stage"].script_url.endswith("run_pdm_score_from_submission.py")
    assert any("Reactive traffic" in note for note in rules["v2.2-two-stage"].notes)
    assert not any("Reactive traffic" in note for note in rules["v2.2"].notes)
    assert any("unfiltered" in note for note in rules["v2.2-prefix"].notes)


def test_the_rules_page_explains_every_version_subscore_seeds_ties_and_papers(world: World) -> None:
    page = world.client.get("/rules")
    assert page.status_code == 200
    text = html.unescape(page.text)
    for rule in all_version_rules():
        assert f'id="{rule.anchor}"' in text and rule.formula in text and rule.script_url in text
    for item in SUBSCORES:
        assert f'id="{item.anchor}"' in text and item.name in text
    for section in ("seeds", "ranking", "ec-undefined", "papers"):
        assert f'id="{section}"' in text
    assert "arxiv.org/abs/2406.15349" in text and "arxiv.org/abs/2506.04218" in text
    assert "mean ± standard deviation (maximum)" in text and "earlier submission" in text


def test_every_page_links_the_rules(world: World) -> None:
    for path in ("/", "/team", "/admin", "/rules", "/no-such-page"):
        assert 'href="http://testserver/rules">Rules</a>' in world.client.get(path).text, path


def test_board_headers_spell_out_each_subscore_and_link_its_rule(world: World) -> None:
    submit_scored(world, world.team_id, b"a", [uniform(0.8)], "Explained")
    text = html.unescape(world.client.get("/", params={"version": "v2.2"}).text)
    for column in ("no_at_fault_collisions", "lane_keeping", "two_frame_extended_comfort"):
        assert f'title="{header_title(column)}"' in text
        assert METRIC_NAMES[column] in header_title(column)
    assert 'href="http://testserver/rules#metric-NC"' in text
    assert 'href="http://testserver/rules#version-v2.2"' in text
