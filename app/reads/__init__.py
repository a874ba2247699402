"""Reads of a map: its grid at one version (copied under the map's lock) and every answer made of it
(JSON, .npy, PNG, Nav2, OccupancyGrid, MCAP recording), big reads in turns, and the Foxglove live view."""

__all__ = ["foxglove", "lane", "recording", "service"]
