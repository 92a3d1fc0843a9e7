"""Path and query parameters the routes share: row ids and counts within the SQL integer columns (a larger
number cannot name a row, and the database would refuse it with a server error instead of a 422)."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from fastapi import Path, Query

from server.schemas import SQL_INT_MAX

RowId = Annotated[int, Path(ge=1, le=SQL_INT_MAX, description="row id")]
OptionalRowId = Annotated[int | None, Query(ge=1, le=SQL_INT_MAX, description="row id")]
Offset = Annotated[int, Query(ge=0, le=SQL_INT_MAX)]
SceneToken = Annotated[str, Path(pattern=r"^[0-9A-Za-z_-]{1,64}$", description="scene token of the split")]
SeedIndex = Annotated[int, Query(ge=0, le=1000, description="seed of a multi-seed submission")]
PictureLayout = Annotated[
    Literal["wide", "narrow"],
    Query(description="wide: the legend beside the map (a desktop); narrow: under it, for a phone"),
]
PNG_RESPONSE: dict[int | str, dict[str, Any]] = {
    200: {"content": {"image/png": {}}, "description": "a PNG picture"}
}
