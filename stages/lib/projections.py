"""Names of the map projections and the measured choice per location, without lanelet2 (``stages.lib.maps.projection``
makes the projectors): the dataset player names the projection it publishes without loading a map.

Formulas and the measurements behind the choice: ``stages.lib.maps.projection`` and docs/wire.md, "Frames".
"""

from __future__ import annotations

import enum


class Projection(enum.Enum):
    """How the map's latitude and longitude become metres from the origin."""

    UNKNOWN = 0
    LOCAL_CARTESIAN = 1
    SCALED_MERCATOR = 2
    UTM = 3
    AUTO = 4


PROJECTION_BY_LOCATION = {"k729": Projection.UTM, "k733": Projection.SCALED_MERCATOR}
_AUTO_CANDIDATES = (Projection.LOCAL_CARTESIAN, Projection.SCALED_MERCATOR, Projection.UTM)


def projection_for_location(location_id: str) -> Projection:
    """Measured best projection for a TAF-BW location id; LOCAL_CARTESIAN if unknown."""
    return PROJECTION_BY_LOCATION.get(location_id.strip().lower(), Projection.LOCAL_CARTESIAN)


def parse_projection(value: Projection | str) -> Projection:
    """A Projection from itself or its name, case-insensitive; UNKNOWN if unrecognised."""
    if isinstance(value, Projection):
        return value
    return Projection.__members__.get(str(value).strip().upper(), Projection.UNKNOWN)


def published_projection(configured: str, location_id: str) -> str:
    """The projection a source names in its ``SceneInfo``: the configured one, or for ``auto`` (or a name that is no
    projection) the measured one of the location, lower case (``utm``): a reader of the bus need not know the table."""
    chosen = parse_projection(configured)
    if chosen in (Projection.AUTO, Projection.UNKNOWN):
        chosen = projection_for_location(location_id)
    return chosen.name.lower()
