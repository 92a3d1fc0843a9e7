"""Drill-down pictures of a scored submission on one token: who may see them, and a cache on disk.

A picture shows a scene's map and objects, so teams see it only on splits whose scenes are public
(`Split.scenes_public`; a hidden test split's never are) and only on tokens of the subsets they may see;
organisers see every scene. Pictures are rendered once per (scene file, submission file, version, seed):
the scene's hash is in the key, so a changed scene never shows a stale picture.
"""

from __future__ import annotations

from pathlib import Path

from scorer.files import write_atomically
from server.models import Status, Submission
from server.services.errors import Conflict, Forbidden, NotFound
from server.services.splits import ALL_SUBSET, visible_subsets
from server.settings import Settings
from server.storage import read_file, read_trajectories


def _checked(submission: Submission, token: str, seed: int, admin: bool) -> Path:
    """Return the token's scene file if the caller may see this picture; raise why not otherwise."""
    from scorer.scene import scene_paths
    from server.split_store import local_scenes

    split = submission.split
    if submission.status != Status.scored:
        raise Conflict(f"submission {submission.id} is {submission.status}: pictures exist once it is scored")
    if not 0 <= seed < submission.seed_count:
        raise NotFound(
            f"submission {submission.id} has {submission.seed_count} seed(s); seed {seed} does not exist"
        )
    paths = scene_paths(local_scenes(split.directory, split.content_hash, [token]))
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
    admin: bool,
    settings: Settings,
) -> bytes:
    """Return the PNG that explains the submission's score on `token` (rendered once, then from disk)."""
    from scorer.explain import explain_token
    from scorer.picture import render
    from scorer.scene import scene_file_hash
    from scorer.submission import load_submission

    scene = _checked(submission, token, seed, admin)
    path = (
        settings.data_dir
        / "pictures"
        / f"{scene_file_hash(scene)}-{submission.sha256}-{version}-{seed}-{token}.png"
    )
    if path.exists():
        return path.read_bytes()
    seeds = read_trajectories(settings.submission_store, submission.stored_name, submission.sha256)
    if seeds is None:  # an upload stored before the parsed copies, or a copy lost
        seeds = load_submission(
            read_file(settings.submission_store, submission.stored_name), submission.filename
        ).seeds
    explanation = explain_token(scene, settings.cache_dir, token, seeds[seed][token], version)
    picture = render(explanation, "png")
    write_atomically(path, picture, durable=False)  # rendered again when missing
    return picture
