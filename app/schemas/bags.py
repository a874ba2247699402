"""What a bag import did to the map."""

from __future__ import annotations

from pydantic import BaseModel, Field

from app.errors import ErrorBody


class BagImportResult(BaseModel):
    """What an imported bag did to the map: every batch (``complete``), or the batches before the one that failed."""

    complete: bool = Field(description="true: every placed scan was fused. false: the import stopped at a batch that "
                           "failed (`stopped`); the batches before it are applied and durable, so do not send the "
                           "bag again (its first part would be fused twice)")
    stopped: ErrorBody | None = Field(None, description="why the import stopped part-way (the error body the failed "
                                      "batch would have answered alone: STORAGE_UNAVAILABLE, NOT_FOUND, CONFLICT, "
                                      "INVALID, ...); null when complete")
    messages: int = Field(description="scan messages read on the topics read")
    scans_fused: int = Field(description="scans fused into the map (all placed ones when complete)")
    skipped: dict[str, int] = Field(description="scan messages left out, by reason")
    rays: int
    cells_updated: int
    batches: int = Field(description="batches applied, each durable before the next")
    version: int = Field(description="the map's version after the last batch applied")
    topics: dict[str, str] = Field(description="the topics read, with their message types")
