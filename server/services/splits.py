"""Splits (scene directories with a content hash and token subsets) and the phases that run on them."""

from __future__ import annotations

from collections.abc import Sequence
from datetime import datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

from sqlalchemy import select
from sqlalchemy.orm import Session

from scorer.scene import SceneFormatError, scene_paths
from scorer.two_stage.split import MAPPING_FILE, TwoStageSplitError, load_two_stage_split
from server import split_store
from server.models import Phase, Split, SplitKind, SplitSubset, utc_now
from server.object_store import StoreUnavailable
from server.services.errors import Conflict, Invalid, NotFound

if TYPE_CHECKING:
    from scorer.two_stage.split import TwoStageSplit

ALL_SUBSET = "all"
PUBLIC_SUBSET = "public"
PRIVATE_SUBSET = "private"


def split_tokens(split: Split) -> tuple[str, ...]:
    """Return the tokens a submission of the split covers: a log-replay split's scenes in token order, a
    two-stage split's stage-one then stage-two tokens (`stage_mapping`); a stored split's from its manifest."""
    if split.kind == SplitKind.two_stage:
        stages = stage_mapping(split)
        return stages.stage_one_tokens + stages.stage_two_tokens
    return split_store.split_tokens(split.directory, split.content_hash)


def stage_mapping(split: Split) -> TwoStageSplit:
    """Return a two-stage split's stage mapping and stage tokens (`scorer.two_stage.split`), a stored split's
    from this machine's copy of its `two_stage.json` (`server.split_store.split_stages`)."""
    return split_store.split_stages(split.directory, split.content_hash)


def upload_stages(split: Split) -> TwoStageSplit | None:
    """Return what an upload's stages must cover: a two-stage split's mapping, None for a one-stage split."""
    return stage_mapping(split) if split.kind == SplitKind.two_stage else None


def scene_starts(session: Session, split: Split) -> dict[str, tuple[str, int]]:
    """Return token -> (log name, t0 in us) of a split's readable scenes, read from its files the first time.

    Scoring pairs adjacent frames of a log for v2.2's EC, across the chunks of a run; a scene that cannot be
    read pairs with nothing (scoring reports it).
    """
    if split.scene_starts is None:
        from scorer.scene import scene_start  # the engine is heavy: imported only when the index is built

        starts: dict[str, list[Any]] = {}
        directory = split_store.local_scenes(split.directory, split.content_hash, split_tokens(split))
        for token, path in scene_paths(directory).items():
            try:
                starts[token] = list(scene_start(path))
            except (SceneFormatError, OSError):
                continue
        split.scene_starts = starts
        session.flush()
    return {token: (log_name, t0_us) for token, (log_name, t0_us) in split.scene_starts.items()}


def register_split(
    session: Session,
    name: str,
    directory: Path | str,
    public_tokens: list[str] | None = None,
    scenes_public: bool = False,
) -> Split:
    """Register a split directory, or an object store's prefix (s3://bucket/prefix, holding scenes/), under
    `name`; with `public_tokens`, the rest of the split is the private subset. `scenes_public` lets teams see
    its scenes in drill-down pictures (never for a hidden test split)."""
    from scorer.evaluate import split_content_hash  # the engine is heavy: imported only when a split is added

    if session.scalar(select(Split.id).where(Split.name == name)) is not None:
        raise Conflict(f"split {name!r} is already registered")
    source, stored = str(directory), split_store.is_stored_split(str(directory))
    local = Path(directory)
    try:
        if stored:
            local = split_store.fetch_whole_split(source)  # read once, to hash; its manifest published
        else:
            local = local.resolve()
            source = str(local)
        tokens = list(scene_paths(local))
    except SceneFormatError as error:
        raise Conflict(f"split {name!r}: {error}") from None
    except StoreUnavailable as error:
        raise Conflict(f"split {name!r}: {error}") from None
    except OSError as error:  # e.g. a name too long for the file system
        raise Conflict(
            f"split {name!r}: directory {source[:200]!r} cannot be read ({error.strerror})"
        ) from None
    if not tokens:
        raise Conflict(f"split {name!r}: no scene in {source}/scenes")
    kind = SplitKind.two_stage if (local / MAPPING_FILE).is_file() else SplitKind.log_replay
    if kind == SplitKind.two_stage:
        try:
            stages = load_two_stage_split(local)
        except TwoStageSplitError as error:
            raise Conflict(f"split {name!r}: {str(error).replace(str(local), '<split>')}") from None
        tokens = [*stages.stage_one_tokens, *stages.stage_two_tokens]
        if public_tokens is not None:
            raise Conflict(
                f"split {name!r} is a two-stage split: its groups are scored whole, so it has no public and "
                "private subsets (register the public and private parts as two splits)"
            )
    split = Split(
        name=name,
        directory=source,
        content_hash=split_content_hash(local),
        token_count=len(tokens),
        scenes_public=scenes_public,
        kind=kind,
    )
    if public_tokens is not None:
        unknown = sorted(set(public_tokens) - set(tokens))
        if unknown:
            problems: list[dict[str, str | None]] = [
                {"token": t, "field": "public_tokens", "message": "not a token of the split"} for t in unknown
            ]
            raise Invalid(f"{len(unknown)} public tokens are not in split {name!r}", problems)
        public = set(public_tokens)
        split.subsets = [
            SplitSubset(name=PUBLIC_SUBSET, tokens=[t for t in tokens if t in public]),
            SplitSubset(name=PRIVATE_SUBSET, tokens=[t for t in tokens if t not in public]),
        ]
    session.add(split)
    session.flush()
    if stored:
        scene_starts(session, split)  # from the copy read now: the machines that plan runs need no scene
    return split


def subset_tokens(split: Split) -> dict[str, list[str]]:
    """Return subset name -> tokens of a split, "all" included."""
    subsets = {ALL_SUBSET: list(split_tokens(split))}
    subsets.update({subset.name: list(subset.tokens) for subset in split.subsets})
    return subsets


def subset_names(split: Split) -> list[str]:
    """Return the subset names of a split, "all" last."""
    return [subset.name for subset in split.subsets] + [ALL_SUBSET]


def visible_subsets(split: Split, phase: Phase | None, admin: bool, now: datetime | None = None) -> list[str]:
    """Return the subsets a caller may see: the private part only to admins or once the phase has closed."""
    names = subset_names(split)
    closed = phase is not None and has_closed(phase, now)
    if admin or closed or names == [ALL_SUBSET]:
        return names
    # Before the phase closes, "all" would leak the private tokens' scores into the public numbers.
    return [PUBLIC_SUBSET] if PUBLIC_SUBSET in names else []


def split_by_name(session: Session, name: str) -> Split:
    """Return the registered split `name` or raise NotFound."""
    split = session.scalar(select(Split).where(Split.name == name))
    if split is None:
        raise NotFound(f"split {name!r} is not registered")
    return split


def create_phase(
    session: Session,
    name: str,
    split: Split,
    opens_at: datetime | None = None,
    closes_at: datetime | None = None,
    per_day: int | None = None,
    total: int | None = None,
    in_flight: int | None = None,
) -> Phase:
    """Create a phase on `split` (opening now by default) with its default quotas (None: unlimited)."""
    if session.scalar(select(Phase.id).where(Phase.name == name)) is not None:
        raise Conflict(f"phase {name!r} already exists")
    opens_at = opens_at or utc_now()
    if closes_at is not None and closes_at <= opens_at:
        raise Conflict(
            f"phase {name!r} would close ({closes_at.isoformat()}) before it opens ({opens_at.isoformat()})"
        )
    phase = Phase(
        name=name,
        split=split,
        opens_at=opens_at,
        closes_at=closes_at,
        per_day=per_day,
        total=total,
        in_flight=in_flight,
    )
    session.add(phase)
    session.flush()
    return phase


def is_open(phase: Phase, now: datetime | None = None) -> bool:
    """Return whether the phase accepts submissions at `now`."""
    now = now or utc_now()
    return phase.opens_at <= now and (phase.closes_at is None or now < phase.closes_at)


def has_closed(phase: Phase, now: datetime | None = None) -> bool:
    """Return whether the phase has closed at `now`: its private subset and its entries are then public."""
    return phase.closes_at is not None and phase.closes_at <= (now or utc_now())


def resolve_phase(session: Session, name: str | None, now: datetime | None = None) -> Phase:
    """Return the phase called `name`, or by default the open phase that opened last, else the newest phase."""
    if name:
        phase = session.scalar(select(Phase).where(Phase.name == name))
        if phase is None:
            raise NotFound(f"phase {name!r} does not exist")
        return phase
    phases = session.scalars(select(Phase).order_by(Phase.opens_at.desc(), Phase.id.desc())).all()
    if not phases:
        raise NotFound("no phase exists yet: an admin must create one (`navsim-lb admin create-phase`)")
    open_phases = [phase for phase in phases if is_open(phase, now)]
    return (open_phases or phases)[0]


def list_phases(session: Session, newest_first: bool = False) -> Sequence[Phase]:
    """Return every phase by opening time (the newest first when asked)."""
    order = Phase.opens_at.desc() if newest_first else Phase.opens_at
    return session.scalars(select(Phase).order_by(order)).all()


def list_splits(session: Session) -> Sequence[Split]:
    """Return every registered split by name."""
    return session.scalars(select(Split).order_by(Split.name)).all()
