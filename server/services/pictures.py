"""Drill-down pictures of a scored submission on one token: who may see them, and a cache on disk.

A picture shows a scene's map and objects, so teams see it only on splits whose scenes are public
(`Split.scenes_public`; a hidden test split's never are) and only on tokens of the subsets they may see;
organisers see every scene. Pictures are rendered once per (scene file, submission file, version, seed,
layout): the scene's hash is in the key, so a changed scene never shows a stale picture. The version decides
what is drawn: under a reactive one the vehicles as they reacted, under a two-stage one a stage-one token's
synthetic starts with their weights (the engine reads them from the split's stage mapping).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Literal

from scorer.files import write_atomically
from scorer.geometry import FloatArray
from server.models import Split, SplitKind, Status, Submission
from server.numbers import counted
from server.services.errors import Conflict, Forbidden, NotFound
from server.services.splits import ALL_SUBSET, visible_subsets
from server.settings import Settings
from server.storage import read_file, read_trajectories


def picture_scenes(split: Split, token: str) -> Path:
    """Return a local directory of the split holding what a picture of `token` reads: its scene and, for a
    stage-one token of a two-stage split, the scenes of the synthetic starts it weighs (a stored split's copy
    on this machine fetches only those)."""
    from scorer.two_stage.starts import successors
    from server.split_store import local_scenes, split_stages

    weighed: tuple[str, ...] = ()
    if split.kind == SplitKind.two_stage:  # its mapping, a stored split's kept in this machine's copy
        weighed = successors(split_stages(split.directory, split.content_hash).groups or (), token)
    return local_scenes(split.directory, split.content_hash, [token, *weighed])


def _checked(submission: Submission, token: str, seed: int, admin: bool) -> Path:
    """Return the token's scene file if the caller may see this picture; raise why not otherwise."""
    from scorer.scene import scene_paths

    split = submission.split
    if submission.status != Status.scored:
        raise Conflict(f"submission {submission.id} is {submission.status}: pictures exist once it is scored")
    if not 0 <= seed < submission.seed_count:
        raise NotFound(
            f"submission {submission.id} has {counted(submission.seed_count, 'seed')}; seed {seed} does not exist"
        )
    paths = scene_paths(picture_scenes(split, token))
    if token not in paths:
        raise NotFound(f"token {token} is not part of split {split.name!r}")
    if not admin:
        if not split.scenes_public:
            raise Forbidden(
                f"the scenes of split {split.name!r} are not public: only the organisers see them"
            )
        visible = visible_subsets(split, submission.phase, admin=False)
        # "all" holds every token of `paths`; the named subsets are stored with the split.
        revealed = ALL_SUBSET in visible or any(
            token in subset.tokens for subset in split.subsets if subset.name in visible
        )
        if not revealed:
            raise Forbidden(f"token {token} belongs to a subset of {split.name!r} that is not revealed yet")
    return paths[token]


def scene_picture(
    submission: Submission,
    token: str,
    version: str,
    seed: int,
    layout: Literal["wide", "narrow"],
    admin: bool,
    settings: Settings,
) -> bytes:
    """Return the PNG that explains the submission's score on `token` under `version`, in a layout for a
    desktop ("wide") or a phone ("narrow") (rendered once, then from disk)."""
    from scorer.evaluate import TokenError
    from scorer.explain import explain_split_token
    from scorer.picture import render
    from scorer.scene import scene_file_hash
    from scorer.submission import SubmissionError
    from scorer.two_stage.score import predictions_per_seed

    scene = _checked(submission, token, seed, admin)
    path = (
        settings.data_dir
        / "pictures"
        / f"{scene_file_hash(scene)}-{submission.sha256}-{version}-{seed}-{layout}-{token}.png"
    )
    if path.exists():
        return path.read_bytes()
    seeds: Sequence[Mapping[str, FloatArray]] | None = read_trajectories(
        settings.submission_store, submission.stored_name, submission.sha256
    )
    if seeds is None:  # an upload stored before the parsed copies, or a copy lost
        content = read_file(settings.submission_store, submission.stored_name)
        try:
            seeds = predictions_per_seed(content, submission.filename, version)
        except SubmissionError:
            raise Conflict(f"submission {submission.id} is not a submission {version} scores") from None
    if not 0 <= seed < len(seeds) or token not in seeds[seed]:
        raise NotFound(f"submission {submission.id} has no prediction for token {token} (seed {seed})")
    try:
        # The scene's directory: the split's, or this machine's copy of a stored split (`picture_scenes`).
        split_dir = scene.parent.parent
        explanation = explain_split_token(split_dir, settings.cache_dir, token, seeds[seed][token], version)
    except TokenError:  # its text may name server paths: the team is told what, not where
        raise Conflict(f"the scene of token {token} cannot be drawn under {version}") from None
    picture = render(explanation, "png", layout)
    write_atomically(path, picture, durable=False)  # rendered again when missing
    return picture
