"""The service: ``mapservice.MapService`` wires the maps, their write path, reads and plans, and starts and
stops them together; ``bag_upload`` fuses an uploaded bag into a map batch by batch."""

__all__ = ["bag_upload", "mapservice"]
