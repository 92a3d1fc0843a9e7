"""Load a NAVSIM synthetic scene pickle (`Scene.save_to_disk`) into inert records, executing nothing.

The pickle is a dict of plain data (frames of numpy arrays, lists and strings) plus, in its extended future,
nuPlan objects: `DetectionsTracks` of `Agent` / `StaticObject` and `TrafficLightStatuses`. Pickle rebuilds
those as NEWOBJ + BUILD (a state dict, or `(None, slots)` for the `__slots__` classes `TimePoint`, `StateSE2`,
`StateVector2D`) and their enums as a call `Enum(value)`. Each allowed nuPlan class is replaced by a `Record`
that keeps its class name and state; each enum by `EnumValue`; every other global is refused. The numpy
globals are the log pickles' (`log_pickle.NUMPY_GLOBALS`).
"""

from __future__ import annotations

import pickle
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType
from typing import Any

from scorer.openscene.log_pickle import NUMPY_GLOBALS, RestrictedUnpickler
from scorer.submission import UNPICKLING_ERRORS

# The nuPlan classes an extended future holds (nuplan-devkit v1.2 module paths).
RECORD_CLASSES = {
    ("nuplan.planning.simulation.observation.observation_type", "DetectionsTracks"),
    ("nuplan.common.actor_state.tracked_objects", "TrackedObjects"),
    ("nuplan.common.actor_state.agent", "Agent"),
    ("nuplan.common.actor_state.static_object", "StaticObject"),
    ("nuplan.common.actor_state.scene_object", "SceneObject"),
    ("nuplan.common.actor_state.scene_object", "SceneObjectMetadata"),
    ("nuplan.common.actor_state.oriented_box", "OrientedBox"),
    ("nuplan.common.actor_state.state_representation", "StateSE2"),
    ("nuplan.common.actor_state.state_representation", "StateVector2D"),
    ("nuplan.common.actor_state.state_representation", "TimePoint"),
    ("nuplan.common.maps.maps_datatypes", "TrafficLightStatuses"),
    ("nuplan.common.maps.maps_datatypes", "TrafficLightStatusData"),
}
ENUM_CLASSES = {
    ("nuplan.common.actor_state.tracked_objects_types", "TrackedObjectType"),
    ("nuplan.common.maps.maps_datatypes", "TrafficLightStatusType"),
}


class ScenePickleError(ValueError):
    """A synthetic scene pickle that cannot be read; the message names the file."""


class Record:
    """A nuPlan object as data: its class name and its pickled state (instance dict and slots merged).

    Unpickling makes it with `__new__` alone (NEWOBJ), then hands it its state (BUILD)."""

    kind: str = "Record"
    state: Mapping[str, Any] = MappingProxyType({})

    def __setstate__(self, state: Any) -> None:
        if isinstance(state, tuple) and len(state) == 2:  # (instance dict or None, slots dict)
            parts = [part for part in state if part is not None]
        else:
            parts = [state]
        merged = dict(self.state)
        for part in parts:
            if not isinstance(part, dict) or not all(isinstance(key, str) for key in part):
                raise pickle.UnpicklingError(f"malformed {self.kind} state")
            merged.update(part)
        self.state = merged


@dataclass(frozen=True)
class EnumValue:
    """A nuPlan enum member as data: the enum's name and the member's value."""

    kind: str
    value: int


def _record_class(name: str) -> type[Record]:
    return type(name, (Record,), {"kind": name})


def _enum_class(name: str) -> Callable[[Any], EnumValue]:
    def member(value: Any) -> EnumValue:
        if isinstance(value, bool) or not isinstance(value, int):
            raise pickle.UnpicklingError(f"{name} member must be an integer, got {value!r}")
        return EnumValue(name, value)

    return member


_ALLOWED_GLOBALS: dict[tuple[str, str], Any] = {
    **NUMPY_GLOBALS,
    **{key: _record_class(key[1]) for key in RECORD_CLASSES},
    **{key: _enum_class(key[1]) for key in ENUM_CLASSES},
}


def load_scene_pickle(path: Path | str) -> Any:
    """Return the content of a synthetic scene pickle, nuPlan objects as `Record`s and `EnumValue`s."""
    path = Path(path)
    try:
        return RestrictedUnpickler(path.read_bytes(), _ALLOWED_GLOBALS, "a synthetic scene pickle").load()
    except UNPICKLING_ERRORS as error:
        raise ScenePickleError(f"{path}: not a readable synthetic scene pickle ({error})") from None
