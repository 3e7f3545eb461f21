"""Throw a broad set of bad inputs at every command; each must exit 2 with one line naming it.

    PYTHONPATH=$PWD JAX_PLATFORMS=cpu python scripts/probe_bad_inputs.py [--only WORD] [--list]

Builds its inputs in a temporary folder (a tiny dataset, a scene, photos, runs with
broken checkpoints, files with names that are not UTF-8), then runs every case through
:func:`experiments.cli.main` in-process with stderr captured at the descriptor level.
A case passes when the command exits 2, prints exactly one stderr line, no traceback,
and that line contains the case's needle (the flag or the path as the user gave it), at
most :data:`MAX_LINE` characters (a bad value is named, not echoed whole), and what the
case names as the user's (a file or a whole folder) is byte-identical afterwards.
Cases are generated per class: every float flag gets inf/-inf/nan, every int flag a
word, every input path a missing and a non-UTF-8 name, and so on. Prints the failures
and the counts; a case that runs longer than ``--timeout`` seconds counts as a failure
(a bad input must be refused before the work starts).

Besides the generated classes, the surfaces of issue 50 (:func:`surface_cases`):
``train-editor`` (its run folder, absurd settings, ``--resume`` of nothing, of a damaged
dataset or checkpoint, refused resumes that must leave the folder byte-identical), weights
folders (safetensors headers, configs, schedulers, tokenizers, editor sizes), masks that
decode to more than any memory, prompts (not UTF-8, pages long), damaged edit run
directories, and two processes of one run given different flags (run as a pair).
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import tempfile
import time
import traceback
from pathlib import Path

import numpy as np


PROMPT = "turn him into a bronze statue"  # one the simulated editor knows


def _inputs(root: Path) -> dict:
    """Every file the cases refer to, built once."""
    from jaxedit import camera as camlib, gaussians as G
    from jaxedit.io import save_nerfstudio, save_ply, write_image

    rng = np.random.default_rng(0)
    cams = camlib.hemisphere(4, radius=2.2, width=16, height=16, fov_deg=50.0)
    images = rng.uniform(0.2, 0.8, size=(4, 16, 16, 3)).astype(np.float32)
    pts = rng.normal(scale=0.3, size=(50, 3)).astype(np.float32)
    data = save_nerfstudio(root / "data", images, cams, test_indices=np.array([1]), points=pts,
                           point_colors=rng.uniform(size=(50, 3)).astype(np.float32)).parent
    scene = root / "scene.ply"
    save_ply(scene, G.from_points(pts, rng.uniform(size=(50, 3)), sh_degree=0))
    photos = root / "photos"
    for k in range(3):
        write_image(photos / f"p{k}.png", images[k])
    # A photo folder where one name is not UTF-8.
    badname = root / "photos_badname"
    for k in range(3):
        write_image(badname / f"p{k}.png", images[k])
    os.rename(badname / "p2.png", os.path.join(os.fsencode(badname), b"p\xff.png"))
    # A posed dataset without points whose noise images have nothing to triangulate.
    save_nerfstudio(root / "posed_noise", images, cams, test_indices=np.array([1]))
    # A dataset whose transforms.json names a file that is not UTF-8 (JSON's \udcff escape).
    badjson = save_nerfstudio(root / "data_badname", images, cams, test_indices=np.array([1])).parent
    meta = json.loads((badjson / "transforms.json").read_text())
    first = meta["frames"][0]["file_path"]
    renamed = first.replace(".png", "\udcff.png")
    os.rename(badjson / first, os.fsencode(badjson) + b"/" + os.fsencode(renamed))
    text = json.dumps(meta).replace(json.dumps(first), json.dumps(renamed))
    (badjson / "transforms.json").write_text(text)
    # Runs whose checkpoint is empty or garbage.
    runs = {}
    for kind, content in [("empty", b""), ("garbage", b"PK\x03\x04" + bytes(range(256)) * 4),
                          ("text", b"not a checkpoint\n")]:
        run = root / f"run_{kind}"
        (run / "checkpoints").mkdir(parents=True)
        (run / "checkpoints" / "ckpt_00000020.npz").write_bytes(content)
        (run / "checkpoint.npz").write_bytes(content)
        runs[kind] = run
    edit_run = root / "edit_run"
    (edit_run / "subtasks" / "00").mkdir(parents=True)
    (edit_run / "config.json").write_text('{"command": "edit", "mine": true}\n')
    (edit_run / "subtasks" / "00" / "scene.ply").write_bytes(scene.read_bytes())
    (edit_run / "schedule.json").write_text(json.dumps({"subtasks": [
        {"index": 0, "name": "r0", "ratio": 0.5, "snapshot": "subtasks/00/scene.ply"},
        {"index": 1, "name": "r1", "ratio": 1.0, "snapshot": "subtasks/01/scene.ply"}]}))
    (root / "afile").write_text("x\n")
    (root / "emptydir").mkdir()
    _bad_splat_files(root / "splats")
    _surface_inputs(root, scene)
    return _paths(root)


def _bad_splat_files(folder: Path) -> None:
    """Splat files whose data disagrees with what they declare (issue 73): a 1-splat .spz
    followed by 64 MiB of zeros (a gzip bomb), one with bytes after its gzip stream, and a
    .json that is not a SOG meta.json."""
    import gzip

    from jaxedit.io.formats import spz
    from jaxedit.io.formats.common import Splats

    folder.mkdir()
    one = Splats(np.zeros((1, 3), np.float32), np.full((1, 3), -3.0, np.float32),
                 np.array([[1.0, 0, 0, 0]], np.float32), np.zeros(1, np.float32),
                 np.zeros((1, 1, 3), np.float32))
    v3 = spz.encode(one, version=3)
    (folder / "bomb.spz").write_bytes(gzip.compress(gzip.decompress(v3) + bytes(64 << 20), 9,
                                                    mtime=0))
    (folder / "tail.spz").write_bytes(v3 + bytes(16))
    (folder / "notsog.json").write_text('{"subtasks": []}\n')


def _huge_png(path: Path, width: int, height: int) -> None:
    """A grey PNG whose header says ``width`` x ``height``, holding four rows: a few hundred
    bytes on disk, gigabytes once decoded."""
    import struct
    import zlib

    def chunk(kind: bytes, data: bytes) -> bytes:
        return (struct.pack(">I", len(data)) + kind + data
                + struct.pack(">I", zlib.crc32(kind + data)))

    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(b"\x89PNG\r\n\x1a\n"
                     + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0))
                     + chunk(b"IDAT", zlib.compress(b"\0" * (width + 1) * 4))
                     + chunk(b"IEND", b""))


def _npz(path: Path, meta: dict | None, kind: str | None = None, **arrays) -> None:
    """An npz as jaxedit's writers make them: ``kind`` None: a dataset (``meta``: its settings
    record), else a checkpoint of that kind (``meta``: its record)."""
    from jaxedit.io.checkpoint import FORMAT_VERSION

    path.parent.mkdir(parents=True, exist_ok=True)
    if kind is None:
        extra = {} if meta is None else {"meta": np.asarray(json.dumps(meta))}
    else:
        extra = {"__meta__": np.asarray(json.dumps(dict(
            version=FORMAT_VERSION, kind=kind, paths=list(arrays), keys=[], meta=meta)))}
    with open(path, "wb") as f:
        np.savez(f, **arrays, **extra)


def _surface_inputs(root: Path, scene: Path) -> None:
    """The inputs of :func:`surface_cases` (issue 50's surfaces)."""
    import shutil

    from jaxedit.edit.checkpoint import save_checkpoint, snapshot_fingerprint
    from jaxedit.edit.state import EditState, LossTracker
    from jaxedit.edit.trainer import SubtaskTrainer, EditTrainConfig
    from jaxedit.editors.bundled import bundled_editor
    from jaxedit_lab.train_editor.tiny_ip2p import EditorTrainConfig
    from jaxedit.io import load_ply
    from jaxedit.io.checkpoint import read_pytree
    from jaxedit_lab.train_editor import _stage_record

    # train-editor run folders.
    te = root / "te"
    (te / "file_checkpoints").mkdir(parents=True)
    (te / "file_checkpoints" / "checkpoints").write_text("a file\n")
    (te / "file_model").mkdir()
    (te / "file_model" / "model").write_text("a file\n")
    (te / "dir_dataset" / "dataset.npz").mkdir(parents=True)
    (te / "dir_config" / "config.json").mkdir(parents=True)
    (te / "nothing" / "checkpoints").mkdir(parents=True)
    smoke = EditorTrainConfig.smoke()
    good = _stage_record(smoke, "editor-vae")
    step = {".step": np.int32(0)}
    for name, record in [("other_settings", dict(good, size=64)),
                         ("record_missing", {"config": good}),
                         ("record_unknown", {"config": good, "step": 0, "losses": [], "x": 1}),
                         ("record_types", {"config": good, "step": "0", "losses": []}),
                         ("record_steps", {"config": good, "step": 7, "losses": []})]:
        run = te / name
        meta = record if name != "other_settings" else {"config": record, "step": 0,
                                                         "losses": []}
        _npz(run / "checkpoints" / "vae.npz", meta, "editor-vae", **step)
        (run / "dataset.npz").write_bytes(b"the user's dataset\n")
    record = {"size": smoke.size, "procedural_views": smoke.procedural_views,
              "scenes": list(smoke.scenes)}
    (te / "garbage_dataset").mkdir()
    (te / "garbage_dataset" / "dataset.npz").write_bytes(b"PK\x03\x04" + bytes(range(256)))
    _npz(te / "dataset_other" / "dataset.npz", dict(record, procedural_views=11),
         inputs=np.zeros((1, 32, 32, 3), np.uint8))
    _npz(te / "dataset_arrays" / "dataset.npz", record, inputs=np.zeros((1, 32, 32, 3), np.uint8))

    # Weights folders: copies of the bundled editor, one thing broken in each.
    def weights(name: str) -> Path:
        dst = root / "weights" / name
        shutil.copytree(bundled_editor(), dst)
        return dst

    def set_json(path: Path, **values) -> None:
        path.write_text(json.dumps({**json.loads(path.read_text()), **values}))

    for name, sub, values in [
            ("unet_layers", "unet/config.json", {"layers_per_block": 10 ** 6}),
            ("unet_channels", "unet/config.json", {"block_out_channels": "wide"}),
            ("unet_huge", "unet/config.json", {"block_out_channels": [16384] * 3,
                                               "layers_per_block": 16}),
            ("text_width", "text_encoder/config.json", {"hidden_size": "64"}),
            ("text_layers", "text_encoder/config.json", {"num_hidden_layers": 10 ** 7}),
            ("vae_latent", "vae/config.json", {"latent_channels": -4}),
            ("sched_steps", "scheduler/scheduler_config.json",
             {"num_train_timesteps": 10 ** 12}),
            ("sched_betas", "scheduler/scheduler_config.json", {"beta_start": "small"}),
            ("sched_trained", "scheduler/scheduler_config.json", {"trained_betas": [0.5]}),
            ("tok_length", "tokenizer/tokenizer_config.json", {"model_max_length": 5000})]:
        set_json(weights(name) / sub, **values)
    vocab = weights("tok_vocab") / "tokenizer" / "vocab.json"
    ids = json.loads(vocab.read_text())
    vocab.write_text(json.dumps(dict(ids, **{next(iter(ids)): "one"})))
    (vocab.parent / "tokenizer.json").unlink(missing_ok=True)
    unet_file = "unet/diffusion_pytorch_model.safetensors"
    for name, header in [
            ("st_types", {"w": {"dtype": "F32", "shape": ["4"], "data_offsets": [0, 16]}}),
            ("st_bytes", {"w": {"dtype": "F32", "shape": [4], "data_offsets": [0, 12]}}),
            ("st_bf16", {"w": {"dtype": "BF16", "shape": [3], "data_offsets": [0, 5]}}),
            ("st_meta", {"__metadata__": {"format": 1}}),
            ("st_length", None)]:
        path = weights(name) / unet_file
        raw = json.dumps(header).encode() if header is not None else b"{}"
        length = len(raw) if header is not None else 2 ** 62
        path.unlink()
        path.write_bytes(length.to_bytes(8, "little") + raw + bytes(16))

    # Masks that decode to gigabytes, one per frame of the dataset.
    frames = json.loads((root / "data" / "transforms.json").read_text())["frames"]
    for f in frames:
        _huge_png(root / "masks_huge" / (Path(f["file_path"]).stem + ".png"), 16 * 6000,
                  16 * 6000)

    # Edit run directories with a damaged checkpoint record, other data, bad snapshots.
    g = load_ply(scene)
    train = SubtaskTrainer(EditTrainConfig(scene_extent=1.0), int(g.num_alive())).init(g)
    plan = [{"index": 0, "name": "r1", "ratio": 1.0, "difficulty": None, "kind": "edit"}]

    def edit_run(name: str, size: int = 16, finished=(), **record) -> Path:
        run = root / "edit_runs" / name
        run.mkdir(parents=True)
        st = EditState.create(subtask=0, step=0, train=train,
                              images=np.zeros((3, size, size, 3), np.float32),
                              edited=np.zeros(3, bool), tracker=LossTracker.init(10),
                              records=tuple(finished))
        save_checkpoint(run / "checkpoint.npz", st, {"plan": plan, "header": {},
                                                     "wall_time_s": 1.0})
        arrays, info = read_pytree(run / "checkpoint.npz", kind="edit")
        info = {k: v for k, v in {**info, "max_intersections": 4096, **record}.items()
                if v is not None}
        _npz(run / "checkpoint.npz", info, "edit", **arrays)
        (run / "config.json").write_text('{"command": "edit", "mine": true}\n')
        return run

    edit_run("missing_keys", seconds=None)
    edit_run("unknown_keys", surprise=1)
    edit_run("wrong_types", step="3")
    edit_run("other_size", size=8)
    for name in ("snapshot_deleted", "snapshot_truncated"):
        staging = root / "edit_runs" / (name + "_snap")
        rel = "subtasks/00_r1.000/scene.ply"
        (staging / rel).parent.mkdir(parents=True)
        shutil.copy(scene, staging / rel)
        record = {"index": 0, "name": "r1", "snapshot": rel,
                  **snapshot_fingerprint(staging / rel)}
        run = edit_run(name, finished=[record])
        (run / "schedule.json").write_text(json.dumps({"subtasks": [record]}))
        if name == "snapshot_truncated":
            shutil.copytree(staging / "subtasks", run / "subtasks")
            (run / rel).write_bytes((run / rel).read_bytes()[:200])
        shutil.rmtree(staging)


def _paths(root: Path) -> dict:
    """Where :func:`_inputs` put everything."""
    return dict(data=root / "data", scene=root / "scene.ply", photos=root / "photos",
                posed_noise=root / "posed_noise",
                badname=root / "photos_badname", badjson=root / "data_badname",
                runs={k: root / f"run_{k}" for k in ("empty", "garbage", "text")},
                edit_run=root / "edit_run", afile=root / "afile", te=root / "te",
                weights=root / "weights", masks_huge=root / "masks_huge",
                edit_runs=root / "edit_runs")


def _base(command: str, inp: dict, out: str) -> list[str]:
    """A valid command line of ``command`` writing to ``out``."""
    return {
        "make-scene": ["make-scene", "ball", "--out", out],
        "reconstruct": ["reconstruct", "--data", str(inp["data"]), "--out", out],
        "render": ["render", "--scene", str(inp["scene"]), "--out", out],
        "edit": ["edit", "--data", str(inp["data"]), "--scene", str(inp["scene"]), "--prompt",
                 PROMPT, "--out", out],
        "demo": ["demo", "--out", out],
        "ablation": ["ablation", "--out", out],
        "bench": ["bench", "--out", out],
        "report": ["report", str(inp["data"]), "--output", out + ".html"],
        "convert-lpips": ["convert-lpips", "--out", out],
        "clip-metrics": ["clip-metrics", "--run", str(inp["edit_run"]), "--caption-orig", "a",
                         "--caption-edit", "b", "--out", out],
        "view": ["view", str(inp["edit_run"])],
        "process-data": ["process-data", "--images", str(inp["photos"]), "--out", out],
        "train-editor": ["train-editor", "--out", out],
        "export": ["export", str(inp["scene"]), "--out", out + ".spz"],
    }[command]


def cases(inp: dict, root: Path) -> list[tuple[str, list[str], str, Path | None]]:
    """(name, argv, needle (or a tuple of acceptable ones), file that must stay unchanged)."""
    from experiments import cli

    out_rel = os.path.relpath(root / "o", Path.cwd())
    subs = cli.build_parser().commands
    found = []
    for command, sub in subs.items():
        base = _base(command, inp, out_rel)
        for action in sub.arguments:
            if not action.option_strings or action.dest in ("help", "out", "output"):
                continue
            flag = action.option_strings[-1]
            nargs = action.nargs if isinstance(action.nargs, int) else 1
            if action.type is float:
                for bad in ("inf", "-inf", "nan", "1e999"):
                    found.append((f"{command} {flag} {bad}", base + [flag] + [bad] * nargs, flag,
                                  None))
            elif action.type is int:
                for bad in ("x", "1.5", "1e3"):
                    found.append((f"{command} {flag} {bad}", base + [flag] + [bad] * nargs, flag,
                                  None))
            elif action.type is Path and action.dest != "config":
                given = "no/such/path"
                args = [a for a in base]
                if flag in ("--video", "--triangulate"):  # instead of --images, not beside it
                    args[args.index("--images"):args.index("--images") + 2] = []
                if flag == "--triangulate":  # it writes into the dataset: no --out
                    args[args.index("--out"):args.index("--out") + 2] = []
                if flag in args:  # replace the valid value
                    i = args.index(flag)
                    args[i + 1] = given
                else:
                    args += [flag, given]
                found.append((f"{command} {flag} missing", args, given, None))
                # The wrong kind of thing: a one-line text file, an empty folder.
                for kind, wrong in (("a text file", "afile"), ("an empty folder", "emptydir")):
                    bad = [wrong if a == given else a for a in args]
                    found.append((f"{command} {flag} {kind}", bad, (wrong, flag), None))
        # Positional paths (report, view): a missing one.
        if command in ("report", "view"):
            args = [a if a not in (str(inp["data"]), str(inp["edit_run"])) else "no/such/run"
                    for a in base]
            found.append((f"{command} RUN_DIR missing", args, "no/such/run", None))
        # Output locations: read-only, under a file; as given (relative).
        if "--out" in base:
            i = base.index("--out")
            for kind, where in [("read-only", "/proc/jaxedit-probe"),
                                ("under-a-file", os.path.relpath(inp["afile"] / "o"))]:
                args = base[:i + 1] + [where] + base[i + 2:]
                found.append((f"{command} --out {kind}", args, where, None))
        # Config files: missing, non-finite values.
        cfg = root / f"cfg_{command}.json"
        float_flags = [a for a in sub.arguments if a.type is float and a.nargs is None]
        if float_flags:
            cfg.write_text('{"%s": Infinity}' % float_flags[0].dest)
            found.append((f"{command} --config Infinity", base + ["--config", str(cfg)],
                          (float_flags[0].dest, float_flags[0].option_strings[-1]), None))
        found.append((f"{command} --config missing", base + ["--config", "no/cfg.json"],
                      "no/cfg.json", None))
    # Splat files that declare one thing and hold another, through every reader's command.
    for name, needle in [("bomb.spz", "more than the 20 bytes"), ("tail.spz", "after the gzip"),
                         ("notsog.json", "not a SOG meta.json")]:
        bad = root / "splats" / name
        found.append((f"export {name}", ["export", str(bad), "--out", out_rel + ".ply"],
                      needle, bad.parent))
        found.append((f"render --scene {name}", ["render", "--scene", str(bad), "--out", out_rel],
                      needle, bad.parent))
    # Non-UTF-8 file names.
    found.append(("process-data non-UTF-8 photo name",
                  ["process-data", "--images", str(inp["badname"]), "--out", out_rel],
                  "\\xff", None))
    for command in ("reconstruct", "edit"):
        args = _base(command, inp, out_rel)
        args[args.index("--data") + 1] = str(inp["badjson"])
        found.append((f"{command} dataset naming a non-UTF-8 file", args, "\\xff", None))
    # A node of a run's tree whose branch name would leave the run.
    found.append(("clip-metrics --select of a branch outside the run",
                  _base("clip-metrics", inp, out_rel) + ["--select", "../x:0"], "--select",
                  inp["edit_run"]))
    # Points for a posed dataset: nothing to triangulate, or points already there.
    noise_json = inp["posed_noise"] / "transforms.json"
    found.append(("process-data --triangulate of noise images",
                  ["process-data", "--triangulate", str(inp["posed_noise"]), "--quiet"],
                  "--init random", noise_json))
    found.append(("process-data --triangulate of a dataset with points",
                  ["process-data", "--triangulate", str(inp["data"]), "--quiet"],
                  "ply_file_path", inp["data"] / "transforms.json"))
    found.append(("process-data --skip-missing-images without --triangulate",
                  ["process-data", "--images", str(inp["photos"]), "--out", out_rel,
                   "--skip-missing-images", "--quiet"], "--triangulate", None))
    found.append(("reconstruct --init triangulate of noise images",
                  ["reconstruct", "--data", str(inp["posed_noise"]), "--out", out_rel,
                   "--init", "triangulate", "--quiet"], "--init random", noise_json))
    # Broken checkpoints on --resume.
    for kind, run in inp["runs"].items():
        found.append((f"reconstruct --resume {kind} checkpoint",
                      ["reconstruct", "--data", str(inp["data"]), "--out", str(run), "--resume",
                       "--quiet"], "ckpt_00000020.npz", None))
        found.append((f"edit --resume {kind} checkpoint",
                      ["edit", "--data", str(inp["data"]), "--scene", str(inp["scene"]),
                       "--prompt", PROMPT, "--out", str(run), "--resume", "--quiet"],
                      "checkpoint.npz", None))
        found.append((f"edit --resume-from {kind}",
                      ["edit", "--data", str(inp["data"]), "--scene", str(inp["scene"]),
                       "--prompt", PROMPT, "--out", out_rel, "--resume-from", str(run), "--quiet"],
                      str(run), None))
    # A failed --select must leave the run's record alone.
    for bad in ("abc", "99", "nan", "-5", "inf", "1"):  # 1: its snapshot file is missing
        found.append((f"edit --select-only --select {bad}",
                      ["edit", "--data", str(inp["data"]), "--scene", str(inp["scene"]),
                       "--prompt", PROMPT, "--out", str(inp["edit_run"]), "--select-only",
                       "--select", bad], "--select" if bad != "1" else "scene.ply",
                      inp["edit_run"] / "config.json"))
    # A composition of larger views' targets that does not exist.
    found.append(("edit --edit-targets sharpest",
                  _base("edit", inp, out_rel) + ["--edit-targets", "sharpest"],
                  "--edit-targets", None))
    # Ablation flag combinations.
    for flags, needle in [(["--methods", "foo"], "--methods"),
                          (["--methods", "nd_equal_steps"], "--methods"),
                          (["--methods", ""], "--methods"),
                          (["--editor-modes", "0"], "--editor-modes"),
                          (["--editor-modes", "x"], "--editor-modes"),
                          (["--scenes", "nope"], "--scenes"), (["--scenes", ""], "--scenes"),
                          (["--prompts", "zzz"], "--prompts"), (["--seeds", "0"], "--seeds")]:
        found.append((f"ablation {' '.join(flags)}",
                      ["ablation", "--out", out_rel, *flags], needle, None))
    return found


def surface_cases(inp: dict, root: Path) -> list[tuple]:
    """The cases of issue 50's surfaces: (name, argv, needle(s), what must stay unchanged);
    an argv that is a tuple of two argvs is a pair of processes of one run, started at once."""
    out = os.path.relpath(root / "o", Path.cwd())
    te, w, runs = inp["te"], inp["weights"], inp["edit_runs"]
    train = ["train-editor", "--quiet"]
    smoke = [*train, "--smoke"]
    found = []
    # train-editor: its run folder, absurd settings, resume of nothing or of damage.
    for name, needle in [("file_checkpoints", "checkpoints"), ("file_model", "model"),
                         ("dir_dataset", "dataset.npz"), ("dir_config", "config.json")]:
        found.append((f"train-editor --out with {name}", [*smoke, "--out", str(te / name)],
                      needle, te / name))
    for flags, needle in [(["--lr", "0"], "--lr"), (["--lr", "-1"], "--lr"),
                          (["--vae-lr", "0"], "--vae-lr"), (["--lr", "1000"], "--lr"),
                          (["--seed", str(2 ** 70)], "--seed"),
                          (["--seed", str(-2 ** 64)], "--seed"),
                          (["--steps", str(10 ** 9)], "--steps"),
                          (["--vae-steps", str(10 ** 9)], "--vae-steps"),
                          (["--decoder-steps", "100"], "--decoder-steps"),
                          (["--decoder-steps", "-1"], "--decoder-steps"),
                          (["--steps", "0"], "--steps"),
                          (["--size", "100000"], "--size"), (["--size", "40"], "--size"),
                          (["--size", "48"], "--size"), (["--vae-crop", "4096"], "--vae-crop"),
                          (["--procedural-views", str(10 ** 8)], "--procedural-views"),
                          (["--batch", str(10 ** 6)], "--batch"),
                          (["--vae-batch", str(10 ** 6)], "--vae-batch"),
                          (["--text-width", "33"], "--text-width"),
                          (["--text-layers", "1000"], "--text-layers"),
                          (["--size", "1024", "--procedural-views", "10000", "--vae-batch",
                            "4096", "--vae-crop", "1024", "--scenes", "face,ball"], "memory")]:
        found.append((f"train-editor {' '.join(flags)}"[:80], [*train, "--out", out, *flags],
                      needle, None))
    found.append(("train-editor --resume of nothing", [*smoke, "--out", str(te / "nothing"),
                                                       "--resume"], "nothing to resume",
                  te / "nothing"))
    for name, needle in [("other_settings", "other settings"), ("record_missing", "vae.npz"),
                         ("record_unknown", "vae.npz"), ("record_types", "vae.npz"),
                         ("record_steps", "vae.npz"), ("garbage_dataset", "dataset.npz"),
                         ("dataset_other", "dataset.npz"), ("dataset_arrays", "dataset.npz")]:
        found.append((f"train-editor --resume {name}",
                      [*smoke, "--out", str(te / name), "--resume"], needle, te / name))
    # Weights folders given to the InstructPix2Pix editor.
    ip2p = ["edit", "--data", str(inp["data"]), "--scene", str(inp["scene"]), "--prompt",
            PROMPT, "--editor", "ip2p", "--out", out, "--quiet"]
    for name, needle in [("unet_layers", "layers_per_block"),
                         ("unet_channels", "block_out_channels"), ("unet_huge", "memory"),
                         ("text_width", "hidden_size"), ("text_layers", "num_hidden_layers"),
                         ("vae_latent", "latent_channels"),
                         ("sched_steps", "num_train_timesteps"), ("sched_betas", "beta_start"),
                         ("sched_trained", "trained_betas"), ("tok_length", "model_max_length"),
                         ("tok_vocab", "vocab.json"), ("st_types", "safetensors"),
                         ("st_bytes", "safetensors"), ("st_bf16", "safetensors"),
                         ("st_meta", "__metadata__"), ("st_length", "header length")]:
        found.append((f"edit --ip2p-weights {name}", [*ip2p, "--ip2p-weights", str(w / name)],
                      needle, w / name))
    for flags, needle in [(["--ip2p-steps", "100000"], "--ip2p-steps"),
                          (["--ip2p-size", "65536"], "--ip2p-size")]:
        found.append((f"edit --editor ip2p {' '.join(flags)}", [*ip2p, *flags], needle, None))
    # Masks that decode to gigabytes.
    found.append(("edit --masks decoding to gigabytes",
                  ["edit", "--data", str(inp["data"]), "--scene", str(inp["scene"]), "--prompt",
                   PROMPT, "--masks", str(inp["masks_huge"]), "--out", out, "--quiet"],
                  "masks_huge", inp["masks_huge"]))
    # Prompts: stray bytes (as Python holds them); pages of text the editor does not know
    # (InstructPix2Pix takes any text: its tokenizer keeps the first 75 tokens).
    for editor in ("ip2p", "simulated"):
        base = ["edit", "--data", str(inp["data"]), "--scene", str(inp["scene"]), "--editor",
                editor, "--out", out, "--quiet"]
        found.append((f"edit --editor {editor} --prompt not UTF-8",
                      [*base, "--prompt", "make it \udcff blue"], "--prompt", None))
    found.append(("edit --editor simulated --prompt of 10000 characters",
                  ["edit", "--data", str(inp["data"]), "--scene", str(inp["scene"]), "--out",
                   out, "--quiet", "--prompt", "z" * 10_000], "--prompt", None))
    # Damaged edit run directories on --resume: refused, the folder byte-identical.
    for name, needle in [("missing_keys", "lacks seconds"), ("unknown_keys", "surprise"),
                         ("wrong_types", "step"), ("other_size", "8x8 px"),
                         ("snapshot_deleted", "is missing"),
                         ("snapshot_truncated", "truncated or replaced")]:
        found.append((f"edit --resume {name}",
                      ["edit", "--data", str(inp["data"]), "--scene", str(inp["scene"]),
                       "--prompt", PROMPT, "--out", str(runs / name), "--resume", "--quiet"],
                      needle, runs / name))
    # Two processes of one run that were given different flags.
    for name, differ, needle in [("--num-processes", ("2", "3"), "--num-processes"),
                                 ("--out", (out, out + "_other"), "--out")]:
        def argv(i: int, differ=differ, name=name) -> list[str]:
            port = "{port}"  # filled in when the pair starts (a free port then)
            count = differ[i] if name == "--num-processes" else "2"
            where = differ[i] if name == "--out" else out
            return ["edit", "--data", str(inp["data"]), "--scene", str(inp["scene"]),
                    "--prompt", PROMPT, "--out", where, "--quiet", "--coordinator",
                    f"127.0.0.1:{port}", "--num-processes", count, "--process-id", str(i),
                    "--init-timeout", "60", "--heartbeat-timeout", "5"]
        found.append((f"two processes disagree on {name}", (argv(0), argv(1)),
                      (needle, "stopped"), None))
    return found


def _free_port() -> int:
    import socket

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def run_pair(argvs: tuple, timeout: float) -> list[tuple[int | str, str]]:
    """[(exit status, stderr)] of the processes of one multi-process run, started at once as
    real processes (``python -m experiments``): each runs under its own supervisor."""
    import subprocess

    port = str(_free_port())
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "TF_CPP_MIN_LOG_LEVEL": "3",
           "PYTHONPATH": os.pathsep.join([str(Path(__file__).resolve().parents[1]),
                                          os.environ.get("PYTHONPATH", "")])}
    procs = [subprocess.Popen([sys.executable, "-m", "experiments",
                               *[a.replace("{port}", port) for a in argv]],
                              stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env)
             for argv in argvs]
    results = []
    for p in procs:
        try:
            _, err = p.communicate(timeout=timeout)
            results.append((p.returncode, err.decode("utf-8", "replace")))
        except subprocess.TimeoutExpired:
            p.kill()
            _, err = p.communicate()
            results.append(("timeout", err.decode("utf-8", "replace")))
    return results


#: The longest error line a case may print: a bad value is named, not echoed whole.
MAX_LINE = 1000


def _folder_bytes(path: Path | None) -> dict | None:
    """{relative name: bytes} of every file of ``path`` (a file: itself); None: nothing kept."""
    if path is None:
        return None
    if path.is_file():
        return {"": path.read_bytes()}
    return {str(p.relative_to(path)): p.read_bytes() for p in sorted(path.rglob("*"))
            if p.is_file()}


def judge(code, err: str, needle, keep: Path | None, before: dict | None) -> str | None:
    """Why a case failed (None: it passed): exit 2, one line holding a needle, at most
    :data:`MAX_LINE` characters, no traceback, ``keep`` as it was."""
    lines = err.strip().splitlines()
    if code != 2:
        return f"exit {code}"
    if len(lines) != 1 or "Traceback" in err:
        return f"{len(lines)} lines"
    if not any(n in lines[0] for n in ((needle,) if isinstance(needle, str) else needle)):
        return f"does not name {needle!r}"
    if len(lines[0]) > MAX_LINE:
        return f"a line of {len(lines[0])} characters"
    if keep is not None and _folder_bytes(keep) != before:
        return f"changed {keep.name}"
    return None


def run_case(argv: list[str], timeout: float) -> tuple[int | str, str]:
    """(exit status, "traceback" or "timeout"; stderr) of ``cli.main(argv)`` in a forked child.

    A fork starts at once (everything is imported) and can be killed when a bad input is
    not refused and the command starts its real work.
    """
    with tempfile.TemporaryFile() as err:
        pid = os.fork()
        if pid == 0:  # the child: stderr to the file, stdout to nowhere
            os.dup2(err.fileno(), 2)
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, 1)
            sys.stderr = os.fdopen(2, "w", buffering=1)
            sys.stdout = os.fdopen(1, "w")
            from experiments import cli

            try:
                code = cli.main(argv)
            except SystemExit as e:
                code = e.code if isinstance(e.code, int) else 1
            except BaseException:  # noqa: BLE001 - a traceback is what we are looking for
                traceback.print_exc()
                code = 99
            sys.stderr.flush()
            os._exit(code if isinstance(code, int) else 1)
        deadline = time.monotonic() + timeout
        status = None
        while time.monotonic() < deadline:
            done, status = os.waitpid(pid, os.WNOHANG)
            if done:
                break
            time.sleep(0.05)
        else:
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
            status = None
        err.seek(0)
        text = err.read().decode("utf-8", "replace")
    if status is None:
        return "timeout", text
    if os.WIFSIGNALED(status):
        return f"signal {os.WTERMSIG(status)}", text
    code = os.WEXITSTATUS(status)
    return ("traceback" if code == 99 else code), text


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--only", default=None,
                   help="run only cases whose name contains this (or one of these, "
                        "comma-separated)")
    p.add_argument("--list", action="store_true", help="list the cases and stop")
    p.add_argument("--timeout", type=float, default=30.0, help="seconds per case")
    args = p.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        os.chdir(root)  # relative paths in the cases are relative to here
        pid = os.fork()  # the inputs use JAX: build them in a child, keep this one fork-safe
        if pid == 0:
            _inputs(root)
            os._exit(0)
        assert os.waitpid(pid, 0)[1] == 0, "building the inputs failed"
        inp = _paths(root)
        todo = [c for c in cases(inp, root) + surface_cases(inp, root)
                if args.only is None or any(w in c[0] for w in args.only.split(","))]
        if args.list:
            print("\n".join(name for name, *_ in todo))
            return 0
        failures = []
        for name, case_argv, needle, keep in todo:
            before = _folder_bytes(keep)
            if isinstance(case_argv, tuple):  # the processes of one run: each must refuse
                results = run_pair(case_argv, 4 * args.timeout)
            else:
                results = [run_case(case_argv, args.timeout)]
            problem, err = None, ""
            for code, err in results:
                problem = judge(code, err, needle, keep, before)
                if problem:
                    break
            lines = err.strip().splitlines()
            if keep is not None and keep.is_file() and before is not None:
                keep.write_bytes(before[""])
            out = root / "o"
            if out.exists():  # a case that got as far as writing: start the next one clean
                import shutil
                shutil.rmtree(out, ignore_errors=True)
            if problem:
                failures.append(name)
                print(f"FAIL {name}: {problem}: {(lines[-1] if lines else '')[:200]}")
        print(f"{len(todo) - len(failures)}/{len(todo)} cases exit 2 with one line naming the "
              f"bad input; {len(failures)} do not")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
