"""The command-line tools: a map from a CARMEN log (``import_log``) or a ROS bag (``import_bag``), in-process
or through the HTTP API, on their shared base (``common``); a copy of the database while the service runs
(``backup``); the progress all three show (``progress``). Each is ``python -m app.<name>`` and a console
script of pyproject.toml."""

__all__ = ["backup", "common", "import_bag", "import_log", "progress"]
