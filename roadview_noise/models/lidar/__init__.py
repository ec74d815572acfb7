"""LiDAR models. Shared parameter declarations of the weather models live here."""

from ...model import param
from ...physics.lidar_rays import EMPTY_RAYS


def empty_rays_param():
    """The ``empty_rays`` parameter of every LiDAR weather model (:mod:`physics.lidar_rays`)."""
    return param("fill", choices=EMPTY_RAYS,
                 doc="fill: rays that returned nothing in the input also get weather returns (a full grid's no-return"
                     " cells; a point list's empty cells of its firing grid, measured from the list) — raw sensor"
                     " output; sky_only: only those above the horizon — clouds whose ground or low returns were"
                     " removed; ignore: only the input's returns — crops, merged or motion-compensated clouds")
