"""How grids and answers are written: file formats (PNG, .npy, Nav2 map_server, OccupancyGrid data),
media types, and the entity tags of conditional reads. Pure functions, no service state."""

__all__ = ["etags", "exports", "mediatypes"]
