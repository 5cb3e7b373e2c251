"""Map projections: how the map's latitude and longitude become metres from a recording's origin.

`Projection` names the choices, `projection_for_location` the measured best
one for a TAF-BW location, `parse_projection` reads a configured name, and
`projector` makes the lanelet2 projector that `io.read_osm` loads with.

Projection, measured on TAF-BW (share of all car rows inside a car lanelet)
    | recording         | LOCAL_CARTESIAN | SCALED_MERCATOR | UTM    |
    | k729, 25 seq.     | 0.9882          | 0.9891          | 0.9944 |
    | k733, 1 seq.      | 0.8333          | 0.8360          | 0.8203 |
    SCALED_MERCATOR is lanelet2's MercatorProjector (spherical Mercator on
    R = 6378137 m scaled by cos(origin latitude)) minus the origin's own x, y.
    In k733 the projection is not the cause: the moving cars fit the lane
    centrelines with 0.82 to 0.88 m rms and a residual offset of about 0.6 m
    under each of the three, and 91 % of the misses (1818 of 1981 rows) lie in a 3 m wide
    unmapped lane between lanelets -103632 and -103634, the missing fourth lane
    of Ostring's south-west approach, where two cars wait for about 75 s each.
    Counting that strip, the share is 0.986. `projection_for_location` picks
    UTM for K729 and SCALED_MERCATOR for K733 (the best measured, and the
    method the dataset names); `Projection.AUTO` tries all three against given
    car positions and keeps the best aligned. `offset_m` shifts the map: the
    least-squares offsets of the map towards the tracks are about
    (-0.4, -0.55) m for k729 and (+0.6, -0.1) m for k733; they raise the shares
    to 0.998 and 0.846 but are fitted on the same data, so none is applied.
"""

from __future__ import annotations

from lanelet2 import io as ll_io
from lanelet2 import projection as ll_projection

# the names (no lanelet2): stages.lib.projections, which the dataset player reads without loading a map
from stages.lib.projections import _AUTO_CANDIDATES, PROJECTION_BY_LOCATION, Projection, parse_projection, projection_for_location  # noqa: F401


def projector(projection: Projection, origin_lat_deg: float, origin_lon_deg: float):
    """The lanelet2 projector of a concrete projection at the origin; ValueError for UNKNOWN or AUTO."""
    origin = ll_io.Origin(origin_lat_deg, origin_lon_deg)
    if projection is Projection.LOCAL_CARTESIAN:
        return ll_projection.LocalCartesianProjector(origin)
    if projection is Projection.SCALED_MERCATOR:
        return ll_projection.MercatorProjector(origin)
    if projection is Projection.UTM:
        return ll_projection.UtmProjector(origin)
    raise ValueError(f"no projector for {projection}")
