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
    Time,
    Vector,
)
from app.schemas.engine_definition import EngineField, EnginePreset
from fuzzyocc.config import GROWING_MIN_RESOLUTION
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


EXAMPLE_MAP_GROWING = {
    "name": "explore",
    "dimensions": 2,
    "resolution": 0.05,
    "forget_beyond": 50.0,
}


class MapCreate(BaseModel):
    """A new map in its ROS frame (``frame_id``): a box of cells (``origin`` = corner of cell 0, as in a Nav2 YAML,
    and ``size``), or, with neither, a growing map whose cells are allocated where scans reach.

    Every field but ``name`` is a setting: ``GET /maps/{name}`` shows each back (``MapInfo``) in a form
    this body takes, so ``{"name": new, **settings}`` copies a map's settings. A setting added here is
    taken, stored in the map's meta and shown without more code; a map stored before it existed shows
    its default. The facts ``MapInfo`` adds are refused by name.
    """

    model_config = ConfigDict(extra="forbid",
                              json_schema_extra={"examples": [EXAMPLE_MAP, EXAMPLE_MAP_3D, EXAMPLE_MAP_GROWING]})

    name: MapName
    dimensions: Literal[2, 3] | None = Field(None, description="2 or 3; taken from len(origin) when left out, 2 for a "
                                             "growing map")
    resolution: PositiveFinite = Field(description=f"cell edge, metres (a growing map: at least "
                                       f"{GROWING_MIN_RESOLUTION} m)")
    extent: Literal["fixed", "growing"] | None = Field(
        None, description="fixed: the box of origin and size; growing: no box, the cells of the lattice anchored at "
        "the frame's origin (cell i covers [i * resolution, (i + 1) * resolution) along each axis, as OctoMap's keys) "
        "held where scans reach. Left out: fixed when origin and size are given, growing when neither is"
    )
    origin: Vector | None = Field(None, description="a fixed map: corner of cell 0 [x, y(, z)], metres. GET of a "
                                  "growing map: the corner of its bounds (null while it has none), read-only")
    size: Annotated[list[PositiveFinite], Field(min_length=2, max_length=3)] | None = Field(
        None, description="a fixed map: extent [sx, sy(, sz)], metres, rounded up to whole cells; GET shows it as built "
        "(shape x resolution): the map covers origin .. origin + size. GET of a growing map: the size of its "
        "bounds (null while it has none), read-only"
    )
    forget_beyond: PositiveFinite | None = Field(
        None, description="metres: after each scan, every cell whose centre lies farther than this from the scan's "
        "sensor (in the plane on a 2-D map) goes back to never observed, and blocks left empty are freed; null keeps "
        "everything. Changed with PATCH /maps/{name}"
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
        boxed = (self.origin is not None, self.size is not None)
        extent = self.extent or ("growing" if boxed == (False, False) else "fixed")
        if extent == "growing":
            given = [name for name, value in (("origin", self.origin), ("size", self.size)) if value is not None]
            if given:
                raise ValueError(f"{' and '.join(given)} of a growing map are its bounds, read-only: leave them out "
                                 "(or give extent fixed for a box)")
            if self.resolution < GROWING_MIN_RESOLUTION:
                raise ValueError(f"resolution of a growing map must be at least {GROWING_MIN_RESOLUTION} m (its cells' "
                                 "indices within 1e7 m of the frame's origin then fit 32 bits)")
            if self.model != "fuzzy":
                raise ValueError(f"a growing map is a fuzzy map: a {self.model} map needs a box (origin and size)")
            self.dimensions = self.dimensions or 2  # type: ignore[assignment]
        else:
            if self.origin is None or self.size is None:
                raise ValueError("a fixed map needs both origin and size (leave both out for a growing map)")
            dims = self.dimensions or len(self.origin)
            if len(self.origin) != dims:
                raise ValueError(f"origin has {len(self.origin)} values but dimensions is {dims}")
            if len(self.size) != dims:
                raise ValueError(f"size has {len(self.size)} values but origin has {dims}")
            self.dimensions = dims  # type: ignore[assignment]
        self.extent = extent  # type: ignore[assignment]
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


class MapChange(BaseModel):
    """``PATCH /maps/{name}``: the settings a map may change after it is made (each applied in its place among the
    map's batches: durable, replayed). A field left out is left as it is."""

    model_config = ConfigDict(extra="forbid")

    forget_beyond: PositiveFinite | None = Field(
        description="metres, as MapCreate's; null keeps everything from now on (cells forgotten stay forgotten)"
    )


class ClearRegion(BaseModel):
    """``POST /maps/{name}/clear``: a box, metres; the cells from the one containing ``min`` to the one containing
    ``max`` go back to never observed (as octomap_server's ``clear_bbx``)."""

    model_config = ConfigDict(extra="forbid")

    min: Vector = Field(description="lower corner [x, y(, z)], metres")
    max: Vector = Field(description="upper corner [x, y(, z)], metres")


class Cleared(BaseModel):
    """What a clear did, once durable."""

    cells_cleared: int = Field(description="cells that were observed and are not any more")
    version: int = Field(description="the map's version after the clear")


class Bounds(BaseModel):
    """A cell-aligned box, metres: the cells from ``min`` to ``max``."""

    min: list[float] = Field(description="corner of the first cell [x, y(, z)]")
    max: list[float] = Field(description="far corner of the last cell [x, y(, z)]")


READ_ONLY_MESSAGE = "{field} is read-only: GET /maps/{name} shows it, POST /maps does not take it; leave it out"


def _read_only(description: str) -> Any:
    return Field(description=description, json_schema_extra={"readOnly": True})


class MapHistory(BaseModel):
    """Where a map's history starts and what it takes: the stored batches a rebuild re-fuses from its base."""

    from_version: int = Field(description="the version the history starts after: its base snapshot's (0 while no "
                              "batch has left the history: a rebuild starts from the map's creation)")
    from_stamp: Time | None = Field(description="the stamp of the history's first stamped scan (ROS time: a corrected "
                                    "trajectory re-poses the scans from there on); null while it holds none "
                                    "(scans stored before stamps were kept have none)")
    bytes: int = Field(description="bytes of the history's stored batches (FUZZYRISK_MAX_HISTORY_BYTES bounds them)")
    scans: int = Field(description="scans in the history's batches")


class MapInfo(MapCreate):
    """A map as the service holds it: its name and settings, as ``MapCreate`` takes them, then read-only facts."""

    # an answer has every field: required in the answer's schema (a generated client's fields are not optional)
    model_config = ConfigDict(json_schema_extra=None, json_schema_serialization_defaults_required=True)

    shape: list[int] | None = _read_only("cells along x, y(, z); a growing map: of its bounds (null while it has none)")
    bounds: Bounds | None = _read_only("the cell-aligned box of every observed cell, metres; null while none is (and "
                                       "in a list answered by a replica that does not hold the map)")
    held_cells: int | None = _read_only("cells the map holds in memory (what FUZZYRISK_MAX_MAP_CELLS and "
                                 "FUZZYRISK_MAX_TOTAL_CELLS count): a cell of a mixed block each, one a uniform block, "
                                 "none for space no scan reached (a bayes map: its whole box); null in a list answered by a replica that does "
                                        "not hold the map")
    scans_fused: int = _read_only("scans fused so far")
    version: int = _read_only("grows with every accepted scan batch: by one, except after a batch that failed "
                              "inside the service after it was stored (its number is not reused)")
    created: datetime = _read_only("when the map was made, UTC")
    updated: datetime = _read_only("when its last batch was applied, UTC")
    history: MapHistory = _read_only("the batches kept for a rebuild: from which version, their bytes and scans")

    @model_validator(mode="after")
    def _dimensions_agree(self) -> MapInfo:
        # overrides MapCreate's: a growing map's origin and size are facts here (its bounds), not settings
        return self
