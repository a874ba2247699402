"""The installed package's version, for every command's ``--version`` and the OpenAPI document."""

from __future__ import annotations

import argparse
from importlib import metadata

#: The distribution this code is installed as (pyproject.toml's ``[project] name``).
DISTRIBUTION = "fuzzyrisk"


def package_version() -> str:
    """``0.1.0``: the version pip installed (``unknown`` when the code runs from a checkout never installed)."""
    try:
        return metadata.version(DISTRIBUTION)
    except metadata.PackageNotFoundError:
        return "unknown (not installed: pip install -e .)"


def add_version_option(parser: argparse.ArgumentParser) -> None:
    """``--version``: print ``PROG (fuzzyrisk) 0.1.0`` and exit 0."""
    parser.add_argument("--version", action="version", version=f"%(prog)s ({DISTRIBUTION}) {package_version()}")
