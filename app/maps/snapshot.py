"""A map's grid at one version as reads and plans get it: what an answer carries (``GridStamp``), and the
arrays copied under the map's apply lock (``GridSnapshot``)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from app.formats import etags, exports
from app.schemas import DEFAULT_FRAME_ID
from fuzzyocc import GridSpec


@dataclass(frozen=True)
class GridStamp:
    """What a read of one version of a map carries besides its cells: the version, its frame, time and ETag."""

    spec: GridSpec
    version: int
    frame_id: str = DEFAULT_FRAME_ID
    #: when the map reached this version (its last batch's ``updated``; its creation at version 0), ISO 8601
    updated: str = ""
    #: ``MapEntry.etag_seed``
    etag_seed: str = ""

    def etag(self, variant: Mapping[str, Any]) -> str:
        """The strong ETag of one representation of this version (``etags.entity_tag``)."""
        return etags.entity_tag(self.etag_seed, self.version, variant)


@dataclass(frozen=True)
class GridSnapshot:
    """Copies of a map's risk and observed arrays at one version, with what its outputs carry."""

    spec: GridSpec
    version: int
    risk: np.ndarray
    observed: np.ndarray
    frame_id: str = DEFAULT_FRAME_ID
    #: when the map reached this version (its last batch's ``updated``; its creation at version 0), ISO 8601
    updated: str = ""
    #: ``MapEntry.etag_seed``
    etag_seed: str = ""

    def etag(self, variant: Mapping[str, Any]) -> str:
        """``GridStamp.etag`` of this version."""
        return self.stamp().etag(variant)

    def stamp(self) -> GridStamp:
        """The ``GridStamp`` of the version these arrays are of."""
        return GridStamp(self.spec, self.version, self.frame_id, self.updated, self.etag_seed)

    def planar(self, z_min: float | None, z_max: float | None) -> tuple[np.ndarray, np.ndarray]:
        """2-D risk and observed: the map itself, or a 3-D map projected over ``[z_min, z_max]``."""
        if self.spec.ndim == 2:
            return self.risk, self.observed
        return exports.project_z(
            self.risk, self.observed, origin_z=self.spec.origin[2], resolution=self.spec.resolution,
            z_min=z_min, z_max=z_max,
        )
