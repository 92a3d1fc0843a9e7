"""Scoring calls only the tests make: one token's proposals scored alone, and agent trajectories scored against
their caches without the split's steps. The product scores tokens in batches (`pdm_scorer.score_batch`) and
splits through `evaluate.score_tokens`; these wrap the same calls for a test's smaller inputs."""

from __future__ import annotations

from collections.abc import Collection, Sequence

import numpy as np

from scorer.cache import MetricCache
from scorer.drivable_map import DrivableMap
from scorer.evaluate import TokenResult, score_against_references, token_results
from scorer.geometry import FloatArray
from scorer.observation import Observation
from scorer.pdm_scorer import ProposalScores, score_batch
from scorer.versions import MetricVersion, ScorerConfig


def score_proposals(
    states: FloatArray,
    observation: Observation,
    drivable_map: DrivableMap,
    centerline_xy: FloatArray,
    route_lane_ids: Collection[str],
    config: ScorerConfig,
) -> ProposalScores:
    """Return the scores of one token's simulated proposals (P, 41, 11) against its observation and map: a
    batch of one, as the devkit's `PDMScorer.score_proposals` scores them."""
    states = np.asarray(states, dtype=np.float64)
    return score_batch(
        states[None], [observation], [drivable_map], [centerline_xy], [route_lane_ids], config
    ).token(0)


def score_caches(
    caches: Sequence[MetricCache],
    poses: Sequence[FloatArray],
    version: MetricVersion,
    seed: int | None = None,
) -> list[TokenResult]:
    """Return the rows of one agent trajectory per cache, all tokens in one batch against their cached
    PDM-Closed measures, each token scored alone (v2.2's EC, which pairs tokens, undefined).

    The states are named by token, so a token may appear once; a diverging simulation raises ValueError (the
    product's rows say which trajectory diverged instead).
    """
    if len({cache.token for cache in caches}) < len(caches):
        raise ValueError("one trajectory per token: score another trajectory of a token in another call")
    _, scores = score_against_references(caches, poses, version)
    return token_results(caches, seed, scores, version)
