"""What triangulated starting points buy: held-out PSNR after the same steps, triangulated vs random.

    python benchmarks/triangulate_init.py [--smoke] [--out DIR] [--iters N] [--size N] [--views N]

Two posed datasets without a point cloud, each reconstructed with the same trainer settings
from each start (``reconstruct --init``):

* ``scene``: the built-in ``face`` scene (``--views`` training + 8 held-out views of ``--size``
  px) saved without its points;
* ``capture``: the same scene rendered at twice the size as plain photos (every other of its
  training views, and its held-out views), posed by ``process-data`` (COLMAP, which needs the
  pixels, on one thread), its sparse cloud removed, trained at half size, normalised as
  nerfstudio does; its held-out views are its own every 8th photo.

Starts: ``auto`` (reconstruct's default for a dataset without points: the triangulated
points topped up to ``--random-points`` with points on the surfaces they mark,
:mod:`jaxedit.capture.dense`), ``triangulate`` (SIFT matches of
the training views triangulated at the known poses alone, :mod:`jaxedit.capture.triangulate`),
``random`` (``--random-points`` photo-consistent random points, the start before it) and
with ``--reference`` the cloud the dataset was saved with
(the scene's sampled surface points, or COLMAP's sparse cloud). Training: ``--iters`` steps
of reconstruct's defaults (density control from step 500 to half the steps). The triangulated points of ``scene`` are also
scored against the scene's ray-cast surface (distance to the nearest hit over the extent).

Writes ``DIR/triangulate_init.json`` with the goal of issue 74 checked: the start from
triangulated points (``auto``) reaches a higher held-out PSNR than the random start on both
(rewritten after each run).
``--seed`` seeds every start's points and training (other seeds give the spread).
``--smoke``: 16 views of 128 px, 20 steps, the scene only, starts ``auto`` and ``random``.
Each case and start can run in its own process (``--cases``, ``--starts``, one ``--out``
each): COLMAP runs on one thread, so every process poses the capture alike.
"""

from __future__ import annotations

import dataclasses
import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from common import write_json  # noqa: E402  (sets sys.path)

EXTRA_TEST = 8
#: What must agree for the cases of two runs to share one JSON file.
SETTINGS = ("smoke", "size", "train_views", "test_views", "iterations", "random_points",
            "seed")


def _surface_error(points, cameras) -> dict:
    """Distances of ``points`` to the face scene's surface seen by ``cameras``, over its extent."""
    from jaxedit import scenes

    hits = scenes.surface_points_and_ids(scenes.get_scene("face"), cameras)[0]
    hits = hits[:, ::2, ::2].reshape(-1, 3)
    hits = hits[np.isfinite(hits).all(axis=1)].astype(np.float64)
    extent = float(np.linalg.norm(hits.max(0) - hits.min(0)))
    dist = np.empty(len(points))
    for k in range(0, len(points), 64):
        dist[k:k + 64] = np.linalg.norm(points[k:k + 64, None] - hits[None], axis=-1).min(1)
    rel = dist / extent
    return {"median": float(np.median(rel)), "p90": float(np.percentile(rel, 90)),
            "within_1pct": float(np.mean(rel < 0.01))}


#: Each start: (reconstruct's init, the source its metrics must name).
STARTS = {"auto": ("auto", "triangulated+dense"), "random": ("random", "random"),
          "triangulate": ("triangulate", "triangulated")}


def _runs(data, root: Path, config, random_points: int, reference: str | None, starts,
          record, seed: int = 0) -> dict:
    """Held-out metrics of each of ``starts`` on ``data`` (which holds the ``reference``
    cloud, run too unless None); ``record(out)`` after each run."""
    from jaxedit.pipelines.reconstruct import reconstruct

    bare = dataclasses.replace(data, points=None, point_colors=None)
    out = {}
    runs = [(name, bare, *STARTS[name]) for name in starts]
    for name, d, init, source in runs + ([(reference, data, "auto", "dataset")]
                                         if reference else []):
        m = reconstruct(d, root / name, config, seed=seed, checkpoint_every=0, log_every=100,
                        random_points=random_points, init=init)
        assert m["initial_points"] == source, m["initial_points"]
        out[name] = {"initial_points": m["initial_point_count"],
                     "test_psnr": round(m["test_psnr"], 3), "test_ssim": round(m["test_ssim"], 4),
                     "num_gaussians": m["num_gaussians"], "train_seconds": m["train_time_s"]}
        print(name, out[name], flush=True)
        record(out)
    return out


def main(argv=None) -> int:
    import argparse

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--smoke", action="store_true", help="tiny sizes, for CI")
    p.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "results")
    p.add_argument("--iters", type=int, default=None)
    p.add_argument("--size", type=int, default=None)
    p.add_argument("--views", type=int, default=None)
    p.add_argument("--random-points", type=int, default=None,
                   help="points of the random start (reconstruct's default; smoke: 2000)")
    p.add_argument("--cases", default="scene,capture",
                   help="cases to run; the others are kept from DIR's JSON of the same settings")
    p.add_argument("--starts", default=None,
                   help="starts to run, in this order (comma-separated; default "
                        "auto,random,triangulate, smoke: auto,random)")
    p.add_argument("--seed", type=int, default=0,
                   help="seed of every start's points and training (another seed: the spread)")
    p.add_argument("--reference", action="store_true",
                   help="also reconstruct from the cloud each dataset was saved with")
    args = p.parse_args(argv)
    if args.starts is None:
        args.starts = "auto,random" if args.smoke else "auto,random,triangulate"

    import jaxedit
    from jaxedit.capture import quiet_colmap
    from jaxedit.pipelines.reconstruct import ReconstructConfig
    from jaxedit.train import TrainConfig

    jaxedit.enable_compilation()
    quiet_colmap(True)
    size = args.size or 128
    views = args.views or (16 if args.smoke else 32)
    iters = args.iters or (20 if args.smoke else 2000)
    config = TrainConfig(iterations=iters)
    if args.random_points is None:
        args.random_points = 2000 if args.smoke else ReconstructConfig.random_points
    results = {"smoke": args.smoke, "load_average_at_start": list(os.getloadavg()),
               "size": size, "train_views": views, "test_views": EXTRA_TEST,
               "iterations": iters, "random_points": args.random_points, "seed": args.seed,
               "cases": {}}
    cases = args.cases.split(",")
    t_start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="jaxedit-triangulate-") as tmp:
        root = Path(tmp)
        if "scene" in cases:
            _scene_case(args, root, size, views, config, results, t_start)
        if "capture" in cases and not args.smoke:
            _capture_case(args, root, size, views, config, results, t_start)
    _write(args.out, results, t_start)
    return 0


def _scene_case(args, root, size, views, config, results, t_start) -> None:
    """The built-in face scene saved without its points; the JSON is written after it."""
    from jaxedit import scenes
    from jaxedit.capture.triangulate import triangulate
    from jaxedit.io import load_nerfstudio

    scenes.make_scene("face", root / "scene", size=size, views=views, test_views=EXTRA_TEST)
    data = load_nerfstudio(root / "scene")
    images, cameras = data.train()
    t0 = time.perf_counter()
    points, _ = triangulate(images, cameras)
    scene = {"triangulate_seconds": round(time.perf_counter() - t0, 2),
             "triangulated_points": int(len(points)),
             "surface_error_over_extent": _surface_error(points.astype(np.float64), cameras)}
    results["cases"]["scene"] = scene

    def record(runs):
        scene["runs"] = runs
        _write(args.out, results, t_start)

    _runs(data, root / "runs_scene", config, args.random_points,
          "scene cloud" if args.reference else None, args.starts.split(","), record, args.seed)


def _capture_case(args, root, size, views, config, results, t_start) -> None:
    """A process-data capture of the face scene's renders, without COLMAP's cloud."""
    from jaxedit import scenes
    from jaxedit.capture import SfmOptions, process_capture
    from jaxedit.capture.triangulate import TriangulateOptions, feature_views, triangulate
    from jaxedit.io import load_nerfstudio
    from jaxedit.io.images import write_image

    # COLMAP needs more pixels than the scene case trains on: photos of twice the
    # size, trained at half (the same pixels as the scene case).
    scenes.make_scene("face", root / "photo_scene", size=2 * size, views=views,
                      test_views=EXTRA_TEST)
    shot = load_nerfstudio(root / "photo_scene")
    photos = root / "photos"
    sources = []
    for k in list(shot.train_indices[::2]) + list(shot.test_indices):
        sources.append(photos / f"view_{k:03d}.png")
        write_image(sources[-1], shot.images[k])
    t0 = time.perf_counter()
    summary = process_capture(root / "capture", sorted(sources),
                              options=SfmOptions(max_features=2048, num_threads=1))
    sfm_s = time.perf_counter() - t0
    capture = load_nerfstudio(root / "capture", downscale=2, normalize="nerfstudio")
    options = TriangulateOptions()
    t0 = time.perf_counter()
    views = feature_views(capture, options.feature_side)
    points, _ = triangulate(*views, options=options)
    case = results["cases"]["capture"] = {
        "photos": len(sources), "registered": summary["num_registered"],
        "sfm_seconds": round(sfm_s, 1), "sfm_points": summary["num_points"],
        "feature_views_px": list(views[0].shape[1:3]),
        "triangulate_seconds": round(time.perf_counter() - t0, 2),
        "triangulated_points": int(len(points))}

    def record(runs):
        case["runs"] = runs
        _write(args.out, results, t_start)

    _runs(capture, root / "runs_capture", config, args.random_points,
          "COLMAP cloud" if args.reference else None, args.starts.split(","), record, args.seed)


def _write(out: Path, results: dict, t_start: float) -> None:
    """Write the JSON of the cases run so far, with the gains and the goals they decide; the
    other cases of the file already there are kept when it has the same settings."""
    results["wall_time_s"] = round(time.perf_counter() - t_start, 1)
    kept = Path(out) / "triangulate_init.json"
    if kept.is_file():
        old = json.loads(kept.read_text())
        if all(old.get(k) == results[k] for k in SETTINGS):
            results["cases"] = {**{k: v for k, v in old["cases"].items()
                                   if k not in results["cases"]}, **results["cases"]}
    gains = {}  # over the random start, of each start run beside it
    for name, case in results["cases"].items():
        runs = case.get("runs", {})
        if "random" in runs:
            gains[name] = {start: round(runs[start]["test_psnr"] - runs["random"]["test_psnr"], 3)
                           for start in ("auto", "triangulate") if start in runs}
    results["psnr_gain_db"] = gains
    if not results["smoke"]:
        results["goals"] = {f"auto_start_beats_random_on_the_{name}": gain["auto"] > 0
                            for name, gain in gains.items() if "auto" in gain}
    write_json(out, "triangulate_init", results)


if __name__ == "__main__":
    raise SystemExit(main())
