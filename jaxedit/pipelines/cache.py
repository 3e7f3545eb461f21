"""Folders of inputs prepared once and reused (a dataset and its reconstruction)."""

from __future__ import annotations

import json
from pathlib import Path

from ..errors import DataError
from ..io.files import atomic_write_text

#: The stamp that says with which settings a folder was prepared.
STAMP = "prepared.json"


def stamp_prepared(out: Path, wanted: dict) -> None:
    """Claim ``out`` for the cached inputs described by ``wanted`` (``out/prepared.json``);
    a DataError when an earlier run prepared it with other settings."""
    stamp = Path(out) / STAMP
    if stamp.exists() and json.loads(stamp.read_text()) != wanted:
        raise DataError(stamp, f"prepared with other settings ({stamp.read_text().strip()}); "
                               "use another output folder")
    Path(out).mkdir(parents=True, exist_ok=True)
    atomic_write_text(stamp, json.dumps(wanted) + "\n")
