"""``humimic fetch``: public data sets, downloaded at run time."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Literal

import tyro


@dataclass(frozen=True, kw_only=True)
class FetchCommand:
    """Download public data sets for humimic at run time."""

    what: Annotated[Literal["climb"], tyro.conf.Positional] = "climb"
    """climb: the holosoma climbing clips with box meshes."""


def run_fetch(cmd: FetchCommand) -> None:
    """Run ``humimic fetch``."""
    from humimic.datasets import fetch_holosoma_climb

    del cmd  # There is one data set: nothing to choose.
    print(fetch_holosoma_climb())
