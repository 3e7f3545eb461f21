"""Folders of inputs prepared once and reused (a dataset and its reconstruction)."""

from __future__ import annotations

import dataclasses
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


def prepared_scene(out: Path, scene: str, *, size: int, views: int, test_views: int,
                   seed: int, config=None, points: int | None = None, log=lambda msg: None):
    """(Dataset, Gaussians, metrics) of a built-in scene's dataset and reconstruction, made
    once under ``out`` and reused; ``config`` None: the dataset only (None, {}). A folder
    stamped with other settings is a DataError, never silently reused."""
    from ..io import load_ply
    from ..scenes import make_scene, size_arguments
    from . import reconstruct as recon

    out = Path(out)
    data_dir, recon_dir = out / "data", out / "reconstruct"
    stamp_prepared(out, {"scene": scene, "size": size, "views": views, "test_views": test_views,
                         "seed": seed, "reconstruct": None if config is None
                         else dataclasses.asdict(config),
                         # only when given, so older stamps stay valid
                         **({} if points is None else {"points": points})})
    if not (data_dir / "transforms.json").exists():
        log(f"making the {scene} scene ({views}+{test_views} views, {size} px)")
        make_scene(scene, data_dir, views=views, test_views=test_views, seed=seed,
                   num_points=points, **size_arguments(scene, size))
    dataset = recon.load_dataset(data_dir, config or recon.ReconstructConfig())
    if config is None:
        return dataset, None, {}
    if not (recon_dir / "scene.ply").exists():
        log(f"reconstructing {scene} ({config.train.iterations} steps)")
        recon.run_loaded(dataset, recon_dir, config, seed=seed)
    metrics = json.loads((recon_dir / "metrics.json").read_text())
    return dataset, load_ply(recon_dir / "scene.ply"), metrics
