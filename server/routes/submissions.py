"""Team routes: upload (validated synchronously), dry-run validation, listing, status and metadata edits."""

from __future__ import annotations

import logging
from collections.abc import Iterator
from typing import Annotated, Any

import anyio
from fastapi import APIRouter, Depends, Header, HTTPException, Query, Request
from fastapi.responses import JSONResponse, Response
from sqlalchemy.orm import Session
from starlette.concurrency import run_in_threadpool

from scorer.versions import DEFAULT_VERSION, VersionName
from server.auth import ApprovedTeamDep, SessionDep, TeamDep, approved_team_of, counted_upload, current_token
from server.body_limit import upload_too_large
from server.models import Phase, Status, Team
from server.object_store import Staged
from server.params import PNG_RESPONSE, Offset, PictureLayout, RowId, SceneToken, SeedIndex
from server.schemas import (
    ComparableOut,
    StageGroupsOut,
    SubmissionAccepted,
    SubmissionOut,
    SubmissionPatch,
    TokenRow,
    ValidationReport,
)
from server.services.comparisons import comparable_entries, comparison_rows
from server.services.errors import Invalid
from server.services.pictures import scene_picture
from server.services.presenters import stage_group_views, submission_views, token_result_views
from server.services.splits import resolve_phase, split_tokens, upload_stages
from server.services.submissions import create_submission, edit_submission, get_submission, list_submissions
from server.services.validation import FORM_METADATA_FIELDS, Received, ValidUpload, validate_stream
from server.upload_form import UploadForm
from server.upload_gate import Check

log = logging.getLogger(__name__)
router = APIRouter(tags=["submissions"])
SUBMIT_PATH, VALIDATE_PATH = "/submissions", "/submissions:validate"
# What each upload route requires of its token, checked from the headers before the body is read
# (server.upload_gate); the routes' dependencies check the same again.
UPLOAD_CHECKS: dict[str, Check] = {SUBMIT_PATH: approved_team_of, VALIDATE_PATH: current_token}


def _body_chunks(request: Request) -> Iterator[bytes]:
    """Yield the request body's chunks as they arrive, to a route's code running in a worker thread."""
    stream = request.stream()

    async def next_chunk() -> bytes | None:
        return await anext(stream, None)

    while (chunk := anyio.from_thread.run(next_chunk)) is not None:
        yield chunk


def _checked_upload(request: Request, session: Session, staged: Staged | None) -> tuple[Phase, ValidUpload]:
    """Return the phase and the checked file, read in one pass as the body arrives (hashed, and written to
    `staged` on the way); raises Invalid (422) listing every problem, 413 past the upload limit."""
    form = UploadForm(_body_chunks(request), request.headers.get("content-type", ""))
    form.start_file()  # the fields before the file: its phase bounds what the file may inflate to
    phase = form.fields.get("phase")
    phase_row = resolve_phase(session, phase)
    limit = request.app.state.settings.max_upload_bytes
    received = Received(
        form,
        staged.write if staged is not None else None,
        limit,
        lambda: HTTPException(status_code=413, detail=upload_too_large(limit)),
    )
    tokens, stages = split_tokens(phase_row.split), upload_stages(phase_row.split)
    session.commit()  # no database connection is held while the file streams in, however slowly
    # The form's fields, the ones after the file included once it is read, give its metadata.
    upload = validate_stream(
        received, form.filename or "submission", tokens, form.fields, stages, staged=staged
    )
    if "phase" in form.after_file and resolve_phase(session, form.fields["phase"]).id != phase_row.id:
        message = (
            "the phase field must come before the file in the form (it says which split the file covers)"
        )
        raise Invalid(message, [{"token": None, "field": "phase", "message": message}])
    return phase_row, upload


# The routes read their body themselves (server.upload_form): the form they take, for the API's description.
def _form_body(*fields: str) -> dict[str, Any]:
    properties: dict[str, Any] = {"file": {"type": "string", "format": "binary"}}
    properties.update({name: {"type": "string"} for name in fields})
    schema = {"type": "object", "properties": properties, "required": ["file"]}
    return {"requestBody": {"required": True, "content": {"multipart/form-data": {"schema": schema}}}}


@router.post(
    SUBMIT_PATH,
    dependencies=[Depends(counted_upload)],
    status_code=202,
    response_model=SubmissionAccepted,
    openapi_extra=_form_body("phase", *FORM_METADATA_FIELDS),
    responses={
        409: {"description": "same file already submitted, or Idempotency-Key reused with another file"},
        422: {"description": "every problem of the file: token, field, message"},
        429: {"description": "a quota is exhausted, or too many uploads; says which and when to retry"},
    },
)
async def submit(
    request: Request,
    session: SessionDep,
    team: ApprovedTeamDep,
    idempotency_key: Annotated[str | None, Header(alias="Idempotency-Key", max_length=200)] = None,
) -> JSONResponse:
    """Upload a submission (a form with `file`: JSON (navsim-lb/submission) or NAVSIM submission pickle, and
    optionally phase, method, authors, institution, country, tech_report_url, code_url, before the file):
    checked as it streams to the store, before anything is queued; 202 with its id."""
    return await run_in_threadpool(_submit, request, session, team, idempotency_key)


def _submit(request: Request, session: Session, team: Team, idempotency_key: str | None) -> JSONResponse:
    settings = request.app.state.settings
    # Whatever stops the upload before its row is added, the object written so far is removed.
    with settings.submission_store.staging() as staged:
        phase_row, upload = _checked_upload(request, session, staged)
        submission, replayed = create_submission(
            session, team, phase_row, upload, settings.submission_store, idempotency_key
        )
        session.commit()
    if not replayed:
        try:
            request.app.state.enqueue(submission.id)
        except Exception:  # the row stays queued; the worker's reaper re-sends queued submissions
            log.exception("could not enqueue submission %s", submission.id)
    url = str(request.url_for("get_submission_route", submission_id=submission.id))
    body = SubmissionAccepted(id=submission.id, status=submission.status, replayed=replayed, url=url)
    return JSONResponse(body.model_dump(), status_code=202, headers={"Location": url})


@router.post(
    VALIDATE_PATH,
    dependencies=[Depends(counted_upload)],
    response_model=ValidationReport,
    openapi_extra=_form_body("phase"),
    responses={
        422: {"description": "every problem of the file: token, field, message"},
        429: {"description": "too many uploads from this token or address; Retry-After says when to retry"},
    },
)
async def validate(request: Request, session: SessionDep) -> ValidationReport:
    """Run the upload checks on a file (a form with `file`, and optionally `phase` before it) without storing
    anything."""
    _, upload = await run_in_threadpool(_checked_upload, request, session, None)
    return ValidationReport(
        valid=True, sha256=upload.sha256, seed_count=upload.seed_count, token_count=upload.token_count
    )


@router.get("/submissions")
def my_submissions(
    session: SessionDep,
    team: TeamDep,
    status: Status | None = None,
    limit: Annotated[int, Query(ge=1, le=500)] = 100,
    offset: Offset = 0,
) -> list[SubmissionOut]:
    """List the team's own submissions, newest first."""
    return submission_views(session, list_submissions(session, team.id, status, limit, offset), SubmissionOut)


@router.get("/submissions/{submission_id}", name="get_submission_route")
def submission_status(session: SessionDep, team: TeamDep, submission_id: RowId) -> SubmissionOut:
    """Status, progress, per-version results and error summary of one of the team's submissions."""
    return submission_views(session, [get_submission(session, submission_id, team.id)], SubmissionOut)[0]


@router.patch("/submissions/{submission_id}")
def edit(session: SessionDep, team: TeamDep, submission_id: RowId, patch: SubmissionPatch) -> SubmissionOut:
    """Edit metadata, hide or show, or select as the team's final entry."""
    submission = get_submission(session, submission_id, team.id)
    changes = {
        key: str(value) if key.endswith("_url") else value
        for key, value in patch.model_dump(exclude_unset=True).items()
    }
    edit_submission(session, submission, changes)
    session.commit()
    return submission_views(session, [submission], SubmissionOut)[0]


@router.get("/submissions/{submission_id}/groups")
def stage_groups(
    session: SessionDep,
    team: TeamDep,
    submission_id: RowId,
    version: VersionName = VersionName.V2_2_TWO_STAGE,
) -> StageGroupsOut:
    """A two-stage submission's groups per seed: each frame's stage-one score, its weighted stage two, the
    weights of its synthetic tokens, and the group's value with what it rests on."""
    return stage_group_views(session, get_submission(session, submission_id, team.id), version)


@router.get("/submissions/{submission_id}/tokens")
def token_rows(
    session: SessionDep,
    team: TeamDep,
    submission_id: RowId,
    version: VersionName = DEFAULT_VERSION,
    only_failed: bool = False,
) -> list[TokenRow]:
    """Per-token results of the current run on the tokens the team may see (failed tokens carry their error)."""
    submission = get_submission(session, submission_id, team.id)
    return token_result_views(session, submission, version, only_failed, admin=False)


@router.get("/submissions/{submission_id}/comparable")
def comparable(session: SessionDep, team: TeamDep, submission_id: RowId) -> list[ComparableOut]:
    """What one of the team's submissions may be compared with: its other scored submissions on the split,
    the entries published on it (their phase closed) and the split's baselines."""
    return comparable_entries(session, get_submission(session, submission_id, team.id), owner=True)


@router.get("/submissions/{submission_id}/comparable/{other_id}/tokens")
def comparable_token_rows(
    session: SessionDep,
    team: TeamDep,
    submission_id: RowId,
    other_id: RowId,
    version: VersionName = DEFAULT_VERSION,
) -> list[TokenRow]:
    """Per-token results of an entry the submission may be compared with, on the tokens the team may see."""
    submission = get_submission(session, submission_id, team.id)
    return comparison_rows(session, submission, other_id, version, owner=True, admin=False)


@router.get(
    "/submissions/{submission_id}/scenes/{token}.png", response_class=Response, responses=PNG_RESPONSE
)
def scene_picture_route(
    request: Request,
    session: SessionDep,
    team: TeamDep,
    submission_id: RowId,
    token: SceneToken,
    version: VersionName = DEFAULT_VERSION,
    seed: SeedIndex = 0,
    layout: PictureLayout = "wide",
) -> Response:
    """The picture that explains the score on one token: map, objects, trajectories, first infractions.
    Only for splits whose scenes are public, on tokens of the subsets the team may see."""
    submission = get_submission(session, submission_id, team.id)
    settings = request.app.state.settings
    picture = scene_picture(submission, token, version, seed, layout, admin=False, settings=settings)
    return Response(picture, media_type="image/png")
