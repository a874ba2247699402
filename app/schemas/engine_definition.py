"""A fuzzy map's engine in its settings: taken as a preset name, an ``EngineDefinition`` or an ``EngineInfo``,
shown as an ``EngineInfo`` (``EngineField``)."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    FiniteFloat,
    PlainSerializer,
    PlainValidator,
    SerializeAsAny,
)

from app.schemas import engine_choice
from fuzzyocc.presets import PRESETS

#: The smallest useful engine: empty, unknown, occupied (Table 1 cut down to three labels).
EXAMPLE_ENGINE = {
    "labels": ["EMP", "UNK", "OCC"],
    "unknown": "UNK",
    "input_mfs": {
        "EMP": {"type": "left_shoulder", "top_end": -2.0, "zero_at": 0.0},
        "OCC": {"type": "triangle", "left": -2.0, "peak": 0.0, "right": 1.5},
        "UNK": {"type": "right_shoulder", "zero_at": 0.0, "top_start": 1.5},
    },
    "output_mfs": {
        "EMP": {"type": "left_shoulder", "top_end": 0.0, "zero_at": 0.5},
        "UNK": {"type": "triangle", "left": 0.0, "peak": 0.5, "right": 1.0},
        "OCC": {"type": "right_shoulder", "zero_at": 0.5, "top_start": 1.0},
    },
    "rules": {
        "EMP": {"EMP": "EMP", "UNK": "EMP", "OCC": "UNK"},
        "UNK": {"EMP": "EMP", "UNK": "UNK", "OCC": "OCC"},
        "OCC": {"EMP": "UNK", "UNK": "OCC", "OCC": "OCC"},
    },
    "and_op": "min",
    "or_op": "max",
    "normalize": False,
}


# These models document the object forms of ``MapCreate.engine`` in the OpenAPI document;
# the request is checked by ``engine_choice.parse`` (``fuzzyocc.engine_spec``), whose messages name
# the bad field by its path (``engine.input_mfs.PO.peak must be a finite number``).

LabelName = Annotated[str, Field(min_length=1, max_length=engine_choice.MAX_NAME_CHARS)]


class TriangleIn(BaseModel):
    """0 at ``left``, 1 at ``peak``, 0 at ``right``; ``left < peak < right``."""

    model_config = ConfigDict(extra="forbid")

    type: Literal["triangle"]
    left: FiniteFloat
    peak: FiniteFloat
    right: FiniteFloat


class TrapezoidIn(BaseModel):
    """0 at ``a``, 1 from ``b`` to ``c``, 0 at ``d``; ``a < b <= c < d``."""

    model_config = ConfigDict(extra="forbid")

    type: Literal["trapezoid"]
    a: FiniteFloat
    b: FiniteFloat
    c: FiniteFloat
    d: FiniteFloat


class LeftShoulderIn(BaseModel):
    """1 up to ``top_end``, 0 from ``zero_at``; ``top_end < zero_at``."""

    model_config = ConfigDict(extra="forbid")

    type: Literal["left_shoulder"]
    top_end: FiniteFloat
    zero_at: FiniteFloat


class RightShoulderIn(BaseModel):
    """0 up to ``zero_at``, 1 from ``top_start``; ``zero_at < top_start``."""

    model_config = ConfigDict(extra="forbid")

    type: Literal["right_shoulder"]
    zero_at: FiniteFloat
    top_start: FiniteFloat


MembershipIn = Annotated[TriangleIn | TrapezoidIn | LeftShoulderIn | RightShoulderIn, Field(discriminator="type")]
LabelMap = Annotated[dict[LabelName, MembershipIn], Field(min_length=2, max_length=engine_choice.MAX_LABELS)]


class EngineDefinition(BaseModel):
    """A fuzzy engine (``fuzzyocc.FuzzyEngine``): labels, membership functions, rule table, operators."""

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [EXAMPLE_ENGINE]})

    labels: Annotated[list[LabelName], Field(min_length=2, max_length=engine_choice.MAX_LABELS)] = Field(
        description="state and output labels in increasing order of risk"
    )
    unknown: LabelName = Field(description="the label of unknown space (a new cell); alone it defuzzifies to 0.5")
    input_mfs: LabelMap = Field(
        description="per label, on the distance from the measured surface in sigmas (negative: in front); together "
        "they cover the whole axis, and far behind the surface only the unknown label is active, at 1"
    )
    output_mfs: LabelMap = Field(
        description="per label, on the risk axis [0, 1], which they cover; each label alone defuzzifies above "
        "the one before it; at most two positive at any risk"
    )
    rules: dict[LabelName, dict[LabelName, LabelName]] = Field(
        description="rules[current][new]: the label concluded from the cell's current label and the new "
        "measurement's; rules[x][unknown] must be x"
    )
    and_op: Literal["min", "product"] = "min"
    or_op: Literal["max", "probsum"] = "max"
    normalize: bool | None = Field(None, description="rescale each fused state to a largest activation of 1; "
                                   "null: when and_op is product")
    incidence_floor: float = Field(1.0, gt=0.0, le=1.0, description="sigma along a LaserScan beam is divided by "
                                   "max(sin(incidence on the surface), incidence_floor); 1: incidence ignored")
    no_return_neighbours: int = Field(0, ge=0, le=8, description="a LaserScan no-return with a hit among this "
                                      "many neighbours on each side clears only up to 0.1 m before the nearest "
                                      "of them; 0: every no-return clears to range_max")


EnginePreset = Literal[tuple(PRESETS)]  # type: ignore[valid-type]


class EngineInfo(BaseModel):
    """A fuzzy map's engine as ``GET /maps/{name}`` shows it, and one form ``POST /maps`` takes.

    Taken: the preset alone, the definition alone, or both when the definition is the preset's
    engine (else a 422 naming ``engine.preset``).
    """

    model_config = ConfigDict(extra="forbid")

    preset: EnginePreset | None = Field(None, description="shown: the preset the engine equals, or null")
    # the definition is shown as engine_spec's dict, checked when the engine was built; SerializeAsAny lets that
    # dict through while the schema documents it as an EngineDefinition
    definition: SerializeAsAny[EngineDefinition] | None = Field(None, description="shown: the engine in full")


def show(choice: engine_choice.EngineChoice | None) -> EngineInfo | None:
    """``choice`` as an ``EngineInfo`` (not validated again: its engine was built and checked)."""
    return None if choice is None else EngineInfo.model_construct(**choice.as_object())


#: A map's ``engine``: validated (and built) by ``engine_choice.parse`` from a preset name, an EngineDefinition
#: or an EngineInfo; shown and stored as an EngineInfo.
EngineField = Annotated[
    engine_choice.EngineChoice | None,
    PlainValidator(engine_choice.parse, json_schema_input_type=EnginePreset | EngineDefinition | EngineInfo | None),
    PlainSerializer(show, return_type=EngineInfo | None),
]
