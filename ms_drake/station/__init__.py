"""Stations: MakeStation(scenario) for simulation and hardware (the LCM twin and its emulator),
robots and grippers in the plant, drivers, environments, the label-from-depth sensor."""

from ms_drake.station.station import (  # noqa: F401
    MakeStation,
    StationObject,
    add_environment,
    add_objects,
    get_plant,
    get_scene_graph,
    resolve_object_names,
    station_objects,
)
