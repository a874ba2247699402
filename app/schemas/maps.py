"""A map as asked for (``MapCreate``: its name and settings) and as the service holds it (``MapInfo``: the same,
then read-only facts)."""

from __future__ import annotations

from collections.abc import Mapping
from datetime import datetime
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator
from pydantic_core import PydanticCustomError

from app.schemas import engine_choice
from app.schemas.common import (
    DEFAULT_FRAME_ID,
    FRAME_ID_MAX_CHARS,
    FRAME_ID_PATTERN,
    FRAME_ID_RULE,
    FrameId,
    MapName,
    NonNegativeFinite,
    PositiveFinite,
    Vector,
)
from app.schemas.engine_definition import EngineField, EnginePreset
from fuzzyocc.maps import MAX_PRIOR_SCANS

#: Scans a saved map's cell stands for when the import does not say (``MapImport.prior_scans``).
DEFAULT_PRIOR_SCANS = 2

EXAMPLE_MAP = {
    "name": "lab",
    "dimensions": 2,
    "resolution": 0.05,
    "origin": [-8.0, -5.0],
    "size": [16.0, 10.0],
    "model": "fuzzy",
    "sensor": {"range_sigma": 0.03, "registration_sigma": 0.0},
    "engine": "paper",
}
EXAMPLE_MAP_3D = {
    "name": "hall3d",
    "dimensions": 3,
    "resolution": 0.1,
    "origin": [-5.0, -5.0, 0.0],
    "size": [10.0, 10.0, 3.0],
    "model": "bayes",
    "sensor": {"range_sigma": 0.05, "registration_sigma": 0.01},
}


class SensorIn(BaseModel):
    """Range noise of the sensor and of the pose it is registered with (metres)."""

    model_config = ConfigDict(extra="forbid")

    range_sigma: NonNegativeFinite = 0.03
    registration_sigma: NonNegativeFinite = 0.0
    range_sigma_per_m: NonNegativeFinite = 0.0


class MapCreate(BaseModel):
    """A new map: a box of cells in its ROS frame (``frame_id``; origin = corner of cell 0, as in a Nav2 YAML).

    Every field but ``name`` is a setting: ``GET /maps/{name}`` shows each back (``MapInfo``) in a form
    this body takes, so ``{"name": new, **settings}`` copies a map's settings. A setting added here is
    taken, stored in the map's meta and shown without more code; a map stored before it existed shows
    its default. The facts ``MapInfo`` adds are refused by name.
    """

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [EXAMPLE_MAP, EXAMPLE_MAP_3D]})

    name: MapName
    dimensions: Literal[2, 3] | None = Field(None, description="2 or 3; taken from len(origin) when left out")
    resolution: PositiveFinite = Field(description="cell edge, metres")
    origin: Vector = Field(description="corner of cell 0 [x, y(, z)], metres")
    size: Annotated[list[PositiveFinite], Field(min_length=2, max_length=3)] = Field(
        description="extent [sx, sy(, sz)], metres, rounded up to whole cells; GET shows it as built (shape x "
        "resolution): the map covers origin .. origin + size"
    )
    model: Literal["fuzzy", "bayes"] = "fuzzy"
    sensor: SensorIn = Field(default_factory=SensorIn)
    engine: EngineField = Field(
        None, description="fuzzy maps: a preset name, an EngineDefinition, or an EngineInfo as GET shows it; left "
        "out: the default preset. GET: an EngineInfo, the preset the engine equals (or null) and its definition; "
        "null for a bayes map"
    )
    frame_id: FrameId = Field(
        DEFAULT_FRAME_ID, description="the ROS frame of the map (a fleet's namespaces: robot1/map): the frame_id of "
        "its OccupancyGrid and of its plans' paths; " + FRAME_ID_RULE,
        json_schema_extra={"pattern": FRAME_ID_PATTERN, "maxLength": FRAME_ID_MAX_CHARS},
    )

    @model_validator(mode="before")
    @classmethod
    def _no_facts(cls, data: Any) -> Any:
        """Refuse the read-only fields ``MapInfo`` adds, each named (a copied GET body that kept them)."""
        if not isinstance(data, Mapping):
            return data
        facts = [key for key in data if key in MapInfo.model_fields and key not in cls.model_fields]
        if facts:
            raise ValidationError.from_exception_data(cls.__name__, [
                {"type": PydanticCustomError("read_only", READ_ONLY_MESSAGE, {"field": key}), "loc": (key,),
                 "input": data[key]}
                for key in facts
            ])
        return data

    @model_validator(mode="after")
    def _dimensions_agree(self) -> MapCreate:
        dims = self.dimensions or len(self.origin)
        if len(self.origin) != dims:
            raise ValueError(f"origin has {len(self.origin)} values but dimensions is {dims}")
        if len(self.size) != dims:
            raise ValueError(f"size has {len(self.size)} values but origin has {dims}")
        self.dimensions = dims  # type: ignore[assignment]
        return self

    @model_validator(mode="after")
    def _engine_of_the_model(self) -> MapCreate:
        _check_engine_model(self.engine, self.model)
        if self.model == "fuzzy" and self.engine is None:
            self.engine = engine_choice.default()  # read when the map is made: DEFAULT_PRESET may move on
        return self


def _check_engine_model(engine: object, model: str) -> None:
    if engine is not None and model != "fuzzy":
        raise ValueError(f"engine applies to fuzzy maps only; a {model} map has none: leave engine out")


class MapImport(SensorIn):
    """The query of ``POST /maps/import``: the new map's name and settings, its sensor's as ``SensorIn``'s fields;
    its grid (resolution, origin, size) and cells come from the file."""

    name: MapName
    prior_scans: int = Field(
        DEFAULT_PRIOR_SCANS, ge=1, le=MAX_PRIOR_SCANS,
        description="the weight of the file's cells: each reads, and later scans change it, as if this many scans "
        "had agreed on it (hits on an occupied cell, pass-throughs on a free one)",
    )
    model: Literal["fuzzy", "bayes"] = "fuzzy"
    engine: EnginePreset | None = Field(None, description="fuzzy maps: a preset name; left out: the default preset")
    frame_id: FrameId | None = Field(
        None, description="the map's ROS frame; left out: an OccupancyGrid's header.frame_id, else map. "
        + FRAME_ID_RULE, json_schema_extra={"pattern": FRAME_ID_PATTERN, "maxLength": FRAME_ID_MAX_CHARS},
    )

    @model_validator(mode="after")
    def _engine_is_fuzzy(self) -> MapImport:
        _check_engine_model(self.engine, self.model)
        return self

    def sensor(self) -> SensorIn:
        """The sensor of the map, from the query's ``SensorIn`` fields."""
        return SensorIn(**{key: getattr(self, key) for key in SensorIn.model_fields})


READ_ONLY_MESSAGE = "{field} is read-only: GET /maps/{name} shows it, POST /maps does not take it; leave it out"


def _read_only(description: str) -> Any:
    return Field(description=description, json_schema_extra={"readOnly": True})


class MapInfo(MapCreate):
    """A map as the service holds it: its name and settings, as ``MapCreate`` takes them, then read-only facts."""

    # an answer has every field: required in the answer's schema (a generated client's fields are not optional)
    model_config = ConfigDict(json_schema_extra=None, json_schema_serialization_defaults_required=True)

    shape: list[int] = _read_only("cells along x, y(, z)")
    scans_fused: int = _read_only("scans fused so far")
    version: int = _read_only("grows with every accepted scan batch: by one, except after a batch that failed "
                              "inside the service after it was stored (its number is not reused)")
    created: datetime = _read_only("when the map was made, UTC")
    updated: datetime = _read_only("when its last batch was applied, UTC")
