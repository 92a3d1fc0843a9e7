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
- Near-identical entries of different teams: the same bytes (sha256), or some seed of one and some seed of
  the other (every seed is compared with every seed) with at least NEAR_COPY_FRACTION of their common tokens
  within SAME_POSE_M (1 cm) at every pose. Independent methods never agree to a centimetre on most tokens;
  re-uploading another team's file does, whichever seed it is put in.
- Probing the hidden set: a team's uploads that differ from another of its uploads in at most
  PROBE_MAX_TOKENS tokens (or PROBE_MAX_FRACTION of them, whichever is larger) in the two seeds that differ
  least (every seed of one compared with every seed of the other), at least PROBE_MIN_PAIRS such pairs. Changing a handful of tokens between uploads and reading the score is how one learns the
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
    """A submission as the checks see it: its team, its bytes' hash and each seed's positions."""

    submission_id: int
    team: str
    sha256: str
    seeds: tuple[FloatArray, ...]  # each (tokens, 8, 2), NaN where missing


@dataclass(frozen=True)
class SeedPair:
    """How one seed of an entry compares with one seed of another: the tokens both have, those that differ."""

    seeds: tuple[int, int]
    common: int
    differs: BoolArray

    @property
    def same_fraction(self) -> float:
        return float(1 - self.differs.sum() / self.common) if self.common else 0.0


def seed_pairs(first: Entry, second: Entry) -> list[SeedPair]:
    """Compare every seed of `first` with every seed of `second`: a copy or a probe may sit in any seed."""
    pairs = []
    for i, poses in enumerate(first.seeds):
        for j, other in enumerate(second.seeds):
            common, differs = differing_tokens(poses, other)
            pairs.append(SeedPair((i, j), int(common.sum()), differs))
    return pairs


def near_duplicates(entries: list[Entry], tokens: list[str]) -> list[Finding]:
    """Return a finding per pair of entries of different teams that are the same file, or of which some seed
    of one agrees within 1 cm with some seed of the other on at least NEAR_COPY_FRACTION of their common
    tokens (the later entry flagged, the earlier named, the seeds given).
    The tokens' last poses screen the seed pairs first: a pair that differs there on most tokens is no copy."""
    rows = [
        (index, entry.seeds[seed][:, -1])
        for index, entry in enumerate(entries)
        for seed in range(len(entry.seeds))
    ]
    owner = np.array([index for index, _ in rows], dtype=np.int64)
    ends = np.stack([end for _, end in rows]) if rows else np.zeros((0, len(tokens), 2))
    findings = []
    for later, second in enumerate(entries):
        # Every earlier seed against each seed of this entry: the fraction of tokens whose last poses are
        # within SAME_POSE_M, at best over this entry's seeds, then at best per earlier entry.
        earlier_rows = owner < later
        close_ends = np.zeros(int(earlier_rows.sum()))
        for end in ends[owner == later]:
            gaps = ends[earlier_rows] - end
            close_ends = np.maximum(
                close_ends, (np.einsum("etk,etk->et", gaps, gaps) <= SAME_POSE_M**2).mean(axis=1)
            )
        best_close = np.zeros(later)
        np.maximum.at(best_close, owner[earlier_rows], close_ends)
        for earlier in range(later):
            first = entries[earlier]
            if first.team == second.team:
                continue
            same_file = first.sha256 == second.sha256
            if not same_file and best_close[earlier] < NEAR_COPY_FRACTION:
                continue
            pairs = seed_pairs(first, second)
            best = max(pairs, key=lambda pair: pair.same_fraction)
            matching = [list(pair.seeds) for pair in pairs if pair.same_fraction >= NEAR_COPY_FRACTION]
            if not same_file and not matching:
                continue
            findings.append(
                Finding(
                    kind="near_duplicate",
                    submission_id=second.submission_id,
                    other_submission_id=first.submission_id,
                    summary=(
                        f"{'the same file as' if same_file else 'near-identical to'} submission "
                        f"{first.submission_id} of team {first.team}: its seed {best.seeds[1]} and their "
                        f"seed {best.seeds[0]} agree within {SAME_POSE_M * 100:g} cm on "
                        f"{best.same_fraction:.1%} of {best.common} common tokens"
                    ),
                    evidence={
                        "same_sha256": same_file,
                        "other_team": first.team,
                        "seeds": {"this": best.seeds[1], "other": best.seeds[0]},
                        "seeds_compared": len(pairs),
                        "matching_seed_pairs": [{"this": j, "other": i} for i, j in matching],
                        "common_tokens": best.common,
                        "fraction_within_1cm": round(best.same_fraction, 4),
                        "differing_tokens": [tokens[i] for i in np.flatnonzero(best.differs)[:PAIRS_LISTED]],
                    },
                )
            )
    return findings


def probing(entries: list[Entry], tokens: list[str]) -> Finding | None:
    """Return a finding where at least PROBE_MIN_PAIRS pairs of one team's uploads (oldest first) differ in a
    few tokens only (at least one) in the seeds that differ least, every seed compared with every seed: the
    pairs, those seeds, their differing-token counts and some of those tokens."""
    limit = max(PROBE_MAX_TOKENS, int(PROBE_MAX_FRACTION * len(tokens)))
    pairs: list[dict[str, Any]] = []
    for later in range(len(entries)):
        for earlier in range(later):
            close = [
                pair
                for pair in seed_pairs(entries[earlier], entries[later])
                if pair.common and 0 < int(pair.differs.sum()) <= limit
            ]
            if not close:
                continue
            pair = min(close, key=lambda pair: int(pair.differs.sum()))
            pairs.append(
                {
                    "submissions": [entries[earlier].submission_id, entries[later].submission_id],
                    "seeds": list(pair.seeds),
                    "differing_tokens": int(pair.differs.sum()),
                    "tokens": [tokens[i] for i in np.flatnonzero(pair.differs)[:PAIRS_LISTED]],
                }
            )
    if len(pairs) < PROBE_MIN_PAIRS:
        return None
    involved: list[int] = sorted({i for pair in pairs for i in pair["submissions"]})
    return Finding(
        kind="probing",
        submission_id=involved[-1],
        summary=(
            f"team {entries[0].team}: {len(pairs)} pairs of its {len(entries)} uploads (every seed compared) "
            f"differ in at most {limit} of {len(tokens)} tokens ({len(involved)} uploads involved)"
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
