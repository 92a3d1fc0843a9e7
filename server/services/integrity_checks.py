"""The integrity checks' arithmetic, on trajectories alone: how close an entry sits to the logged human future,
how alike two entries are, and which of a team's uploads differ in only a few tokens.

Trajectories come aligned on the split's tokens: (tokens, 8, 2) arrays of x, y in the current ego frame, NaN
where an entry has no pose for a token. Only positions count: a copy with its headings changed is still a copy.

Thresholds, and why (figures: `benchmarks/integrity.py`, on the reference and synthetic scenes):

- Leaked log. An honest planner's per-token average displacement (ADE) to the human over 4 s has a median of
  decimetres to metres: on the 32 moving tokens of the reference scenes, 0.35 m for the demo's "noisy human"
  (the log plus 0.3 m of noise per coordinate, closer than any published planner) and 1.75 m for constant
  velocity; NAVSIM's best published planners reach an L2 of about 0.5-1 m. A copy of the log sits at 0 (1e-6 m
  after a float32 round trip), the log with 2 cm of noise at 0.025 m. An entry is flagged
  where its median ADE over the tokens on which the human moves is below LEAK_MEDIAN_ADE_M (5 cm, ten times
  under the best honest figure) over at least LEAK_MIN_TOKENS tokens. Tokens where the human stands still are
  left out: every sensible planner stands still there too.
- Near-identical entries of different teams: the same bytes (sha256), or at least NEAR_COPY_FRACTION of
  their common tokens within SAME_POSE_M (1 cm) at every pose. Independent methods never agree to a
  centimetre on most tokens; re-uploading another team's file does.
- Probing the hidden set: a team's uploads that differ from another of its uploads in at most
  PROBE_MAX_TOKENS tokens (or PROBE_MAX_FRACTION of them, whichever is larger), at least PROBE_MIN_PAIRS
  such pairs. Changing a handful of tokens between uploads and reading the score is how one learns the
  hidden answers token by token; improving a method changes most tokens.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from scorer.geometry import BoolArray, FloatArray

LEAK_MEDIAN_ADE_M = 0.05
LEAK_MIN_TOKENS = 5
MOVING_M = 1.0  # the human's path over 4 s, at least: shorter, the token says nothing about a leak
SAME_POSE_M = 0.01
NEAR_COPY_FRACTION = 0.9
PROBE_MAX_TOKENS = 20
PROBE_MAX_FRACTION = 0.01
PROBE_MIN_PAIRS = 3
CLOSEST_LISTED = 5  # tokens given as evidence
PAIRS_LISTED = 10


def integrity_thresholds() -> dict[str, str]:
    """Return the thresholds as the console states them (m, cm, %)."""
    figures = {
        "leak_m": LEAK_MEDIAN_ADE_M,
        "same_cm": SAME_POSE_M * 100,
        "copy_percent": NEAR_COPY_FRACTION * 100,
        "probe_pairs": PROBE_MIN_PAIRS,
        "probe_tokens": PROBE_MAX_TOKENS,
        "probe_percent": PROBE_MAX_FRACTION * 100,
    }
    return {name: f"{value:g}" for name, value in figures.items()}


@dataclass(frozen=True)
class Finding:
    """One suspicion with its evidence: what the organiser reads before deciding."""

    kind: str  # "leaked_log", "near_duplicate", "probing"
    submission_id: int
    summary: str
    evidence: dict[str, Any]
    other_submission_id: int | None = None


def displacements(poses: FloatArray, reference: FloatArray) -> FloatArray:
    """Return the distance of each pose to the reference's (tokens, 8), NaN where either is missing."""
    return np.asarray(np.hypot(*(poses - reference).transpose(2, 0, 1)), dtype=np.float64)


def _quantiles(values: FloatArray) -> dict[str, float]:
    return {
        f"q{int(q * 100):02d}": round(float(v), 4)
        for q, v in zip((0.05, 0.25, 0.5, 0.75), np.quantile(values, (0.05, 0.25, 0.5, 0.75)), strict=True)
    }


def leaked_log(
    submission_id: int, seeds: list[FloatArray], human: FloatArray, tokens: list[str]
) -> Finding | None:
    """Return a finding where a seed of the entry sits implausibly close to the logged human future on the
    tokens where the human moves: the seed with the smallest median ADE, its quantiles and closest tokens."""
    path = np.hypot(
        *np.diff(np.concatenate([np.zeros((len(human), 1, 2)), human], axis=1), axis=1).transpose(2, 0, 1)
    )
    moving = path.sum(axis=1) >= MOVING_M
    best: tuple[float, int, FloatArray, np.ndarray] | None = None
    for seed, poses in enumerate(seeds):
        ade = displacements(poses, human).mean(axis=1)
        usable = moving & np.isfinite(ade)
        if usable.sum() < LEAK_MIN_TOKENS:
            continue
        median = float(np.median(ade[usable]))
        if best is None or median < best[0]:
            best = (median, seed, ade, usable)
    if best is None or best[0] >= LEAK_MEDIAN_ADE_M:
        return None
    median, seed, ade, usable = best
    indices = np.flatnonzero(usable)
    closest = indices[np.argsort(ade[indices], kind="stable")[:CLOSEST_LISTED]]
    within = float((ade[usable] <= SAME_POSE_M).mean())
    return Finding(
        kind="leaked_log",
        submission_id=submission_id,
        summary=(
            f"median displacement to the logged human future {median:.4f} m over {usable.sum()} moving tokens "
            f"(seed {seed}); {within:.0%} of them within {SAME_POSE_M * 100:g} cm: the threshold is "
            f"{LEAK_MEDIAN_ADE_M:g} m"
        ),
        evidence={
            "seed": seed,
            "tokens": int(usable.sum()),
            "median_ade_m": round(median, 6),
            "quantiles_m": _quantiles(ade[usable]),
            "fraction_within_1cm": round(within, 4),
            "closest_tokens": [{"token": tokens[i], "ade_m": round(float(ade[i]), 6)} for i in closest],
            "threshold_m": LEAK_MEDIAN_ADE_M,
        },
    )


def differing_tokens(first: FloatArray, second: FloatArray) -> tuple[BoolArray, BoolArray]:
    """Return, per token, whether both entries have it and whether they differ there (some pose more than
    SAME_POSE_M apart)."""
    distance = displacements(first, second)
    common: BoolArray = np.asarray(np.isfinite(distance).all(axis=1), dtype=np.bool_)
    differs: BoolArray = common & (np.nan_to_num(distance, nan=0.0).max(axis=1) > SAME_POSE_M)
    return common, differs


@dataclass(frozen=True)
class Entry:
    """A submission as the checks see it: its team, when it came, its bytes' hash and its seed-0 positions."""

    submission_id: int
    team: str
    sha256: str
    poses: FloatArray  # (tokens, 8, 2), NaN where missing


def near_duplicates(entries: list[Entry], tokens: list[str]) -> list[Finding]:
    """Return a finding per pair of entries of different teams that are the same file or agree within 1 cm on
    at least NEAR_COPY_FRACTION of their common tokens (the later entry flagged, the earlier named).
    The tokens' last poses screen the pairs first: a pair that differs there on most tokens is no copy."""
    ends = np.stack([entry.poses[:, -1] for entry in entries]) if entries else np.zeros((0, len(tokens), 2))
    findings = []
    for later in range(len(entries)):
        # Per earlier entry at once: the fraction of tokens whose last poses are within SAME_POSE_M.
        gaps = ends[:later] - ends[later]
        close_ends = (np.einsum("etk,etk->et", gaps, gaps) <= SAME_POSE_M**2).mean(axis=1)
        for earlier in range(later):
            first, second = entries[earlier], entries[later]
            if first.team == second.team:
                continue
            same_file = first.sha256 == second.sha256
            if not same_file and close_ends[earlier] < NEAR_COPY_FRACTION:
                continue
            common, differs = differing_tokens(first.poses, second.poses)
            shared = int(common.sum())
            same = float(1 - differs.sum() / shared) if shared else 0.0
            if not same_file and same < NEAR_COPY_FRACTION:
                continue
            findings.append(
                Finding(
                    kind="near_duplicate",
                    submission_id=second.submission_id,
                    other_submission_id=first.submission_id,
                    summary=(
                        f"{'the same file as' if same_file else 'near-identical to'} submission "
                        f"{first.submission_id} of team {first.team}: {same:.1%} of {shared} common tokens "
                        f"within {SAME_POSE_M * 100:g} cm"
                    ),
                    evidence={
                        "same_sha256": same_file,
                        "other_team": first.team,
                        "common_tokens": shared,
                        "fraction_within_1cm": round(same, 4),
                        "differing_tokens": [tokens[i] for i in np.flatnonzero(differs)[:PAIRS_LISTED]],
                    },
                )
            )
    return findings


def probing(entries: list[Entry], tokens: list[str]) -> Finding | None:
    """Return a finding where at least PROBE_MIN_PAIRS pairs of one team's entries (oldest first) differ in
    a few tokens only (at least one): the pairs, their differing-token counts and some of those tokens."""
    limit = max(PROBE_MAX_TOKENS, int(PROBE_MAX_FRACTION * len(tokens)))
    pairs: list[dict[str, Any]] = []
    for later in range(len(entries)):
        for earlier in range(later):
            common, differs = differing_tokens(entries[earlier].poses, entries[later].poses)
            count = int(differs.sum())
            if 0 < count <= limit and common.any():
                pairs.append(
                    {
                        "submissions": [entries[earlier].submission_id, entries[later].submission_id],
                        "differing_tokens": count,
                        "tokens": [tokens[i] for i in np.flatnonzero(differs)[:PAIRS_LISTED]],
                    }
                )
    if len(pairs) < PROBE_MIN_PAIRS:
        return None
    involved: list[int] = sorted({i for pair in pairs for i in pair["submissions"]})
    return Finding(
        kind="probing",
        submission_id=involved[-1],
        summary=(
            f"team {entries[0].team}: {len(pairs)} pairs of its {len(entries)} uploads differ in at most "
            f"{limit} of {len(tokens)} tokens ({len(involved)} uploads involved)"
        ),
        evidence={
            "team": entries[0].team,
            "uploads": len(entries),
            "pairs": pairs[:PAIRS_LISTED],
            "pair_count": len(pairs),
            "max_differing_tokens": limit,
            "submissions": involved,
        },
    )
