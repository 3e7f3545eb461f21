"""Regenerate the built-in ``person`` dataset with Blender's Cycles (needs ``blender``).

    python scripts/render_person.py --out jaxedit/scenes/data/person [--samples 32 --views 72]

The model is Reallusion's "Male" character (``male02``: suit, long hair, beard) from the Debian
package ``sweethome3d-furniture`` (``apt-get install blender sweethome3d-furniture``), licensed
CC BY 3.0 US; its licence file is copied into the dataset. Steps:

1. extract the OBJ, its textures and LICENSE.TXT from ``Reallusion.sh3f`` (a zip);
2. drop the model's back faces (every triangle is stored twice, with both windings; coincident
   triangles make a path tracer shadow itself);
3. place it in the jaxedit world: +z up, metres, facing +x, the head centred over the origin;
4. frame head and shoulders like the Instruct-NeRF2NeRF face scene: cameras on a frontal arc
   (azimuth -90..90 degrees around the face, elevation waving between 0 and 20 degrees, a hand-held
   sweep), looking at the chin; test views interleaved along the arc;
5. render RGBA (transparent backdrop: loaders composite it over their background, white by
   default) and depth with ``scripts/blender_person.py`` under soft area lights;
6. sample the point cloud on the mesh surface, keep points that at least two training views see
   (rendered depth), colour them with the mean of the pixels they land on (shading baked in, as a
   COLMAP cloud would be);
7. write the nerfstudio dataset (``transforms.json``, ``images/``, ``sparse_pc.ply``), the scene
   info (with mesh vertices, for the convention tests) and the credits.

The repository's copy was made with the defaults. Cycles renders are reproducible for a given
Blender build; the point sampling is seeded.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
import zipfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # the checkout's jaxedit, not an installed copy

from jaxedit.camera import look_at, make_camera, opencv_w2c_to_opengl_c2w, stack  # noqa: E402
from jaxedit.io.files import atomic_write_text  # noqa: E402
from jaxedit.io.images import read_image_with_alpha  # noqa: E402
from jaxedit.io.nerfstudio import save_nerfstudio  # noqa: E402
from jaxedit.scenes.library import split_views  # noqa: E402

CATALOG = "/usr/share/sweethome3d/furniture/Reallusion.sh3f"
MODEL = "male02"
HAIR_MATERIALS = ("6",)  # male02.mtl: material 6 is male02_6.jpg, the hair texture
CREDIT = ("3D model: \"Male\" (male02) by Reallusion (http://www.reallusion.com/), from the "
          "Sweet Home 3D furniture library (Debian package sweethome3d-furniture), licensed "
          "under Creative Commons Attribution 3.0 United States "
          "(http://creativecommons.org/licenses/by/3.0/us/). Changes: duplicate back faces "
          "removed, posed and rendered with Blender Cycles by jaxedit's scripts/render_person.py.")


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, required=True, help="dataset folder to write")
    p.add_argument("--catalog", default=CATALOG, help="Reallusion.sh3f of sweethome3d-furniture")
    p.add_argument("--blender", default="blender", help="Blender executable")
    p.add_argument("--size", type=int, default=256, help="image width and height")
    p.add_argument("--views", type=int, default=72, help="training views")
    p.add_argument("--test-views", type=int, default=8, help="held-out views")
    p.add_argument("--samples", type=int, default=64, help="Cycles samples per pixel")
    p.add_argument("--points", type=int, default=5000, help="points in the initial cloud")
    p.add_argument("--vertices", type=int, default=256,
                   help="mesh vertices (not hair) kept in jaxedit_scene.json for the "
                        "convention tests")
    p.add_argument("--seed", type=int, default=0, help="point and vertex sampling")
    return p.parse_args(argv)


# ------------------------------------------------------------------ the model


def extract_model(catalog: str, dest: Path) -> tuple[Path, Path]:
    """Unzip the model folder and the licence; (obj path, licence path)."""
    with zipfile.ZipFile(catalog) as z:
        for name in z.namelist():
            if name.startswith(f"reallusion/{MODEL}/") or name == "LICENSE.TXT":
                z.extract(name, dest)
    return dest / "reallusion" / MODEL / f"{MODEL}.obj", dest / "LICENSE.TXT"


def drop_back_faces(obj: Path) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Rewrite ``obj`` without its duplicate (reversed) faces.

    Returns (vertices [V, 3], triangles [F, 3], the material of each triangle); faces are
    fanned into triangles for the returned arrays, the file keeps its polygons.
    """
    seen, kept, verts, tris, materials, material = set(), [], [], [], [], ""
    for line in obj.read_text(encoding="utf-8", errors="replace").splitlines():
        if line.startswith("v "):
            verts.append([float(x) for x in line.split()[1:4]])
        if line.startswith("usemtl "):
            material = line.split(maxsplit=1)[1].strip()
        if line.startswith("f "):
            idx = [int(c.split("/")[0]) - 1 for c in line.split()[1:]]
            key = frozenset(idx)
            if key in seen:
                continue
            seen.add(key)
            tris += [(idx[0], idx[k], idx[k + 1]) for k in range(1, len(idx) - 1)]
            materials += [material] * (len(idx) - 2)
        kept.append(line)
    obj.write_text("\n".join(kept) + "\n", encoding="utf-8")
    return np.asarray(verts, np.float64), np.asarray(tris, np.int64), materials


def solid_vertices(tris: np.ndarray, materials: list[str]) -> np.ndarray:
    """Indices of the vertices of solid parts: not of the hair cards, whose strands taper
    to points far thinner than a pixel (so a strand's tip vertex may cover no pixel)."""
    hair = np.array([m in HAIR_MATERIALS for m in materials])
    return np.setdiff1d(np.unique(tris[~hair]), np.unique(tris[hair]))


def model_to_world(verts: np.ndarray) -> np.ndarray:
    """4x4: OBJ (y up, centimetres, facing +z) -> world (+z up, metres, facing +x),
    the head's centre over the origin, the feet on z = 0."""
    rot = np.array([[0.0, 0.0, 1.0],   # obj +z (the face's direction) -> world +x
                    [1.0, 0.0, 0.0],   # obj +x -> world +y
                    [0.0, 1.0, 0.0]])  # obj +y (up) -> world +z
    m = np.eye(4)
    m[:3, :3] = 0.01 * rot
    w = verts @ m[:3, :3].T
    head = head_points(w)
    m[:3, 3] = [-head[:, 0].mean(), -head[:, 1].mean(), -w[:, 2].min()]
    return m


def head_points(world_verts: np.ndarray) -> np.ndarray:
    """The vertices in the top 13% of the body's height: the head (and hair)."""
    z = world_verts[:, 2]
    return world_verts[z > z.max() - 0.13 * (z.max() - z.min())]


# ------------------------------------------------------------------ cameras and lights


def arc_cameras(target: np.ndarray, n: int, size: int, *, radius: float = 1.2,
                fov_deg: float = 32.0, centre_deg: float = -20.0, half_arc_deg: float = 80.0):
    """``n`` cameras on a frontal arc, batched; elevation waves between 0 and 20 deg.

    The body faces +x (azimuth 0) and the head is turned to about -35 degrees: the arc is
    centred between the two, as a photographer would circle a sitter.
    """
    cams = []
    for i in range(n):
        t = i / max(n - 1, 1)
        az = np.radians(centre_deg - half_arc_deg + 2.0 * half_arc_deg * t)
        el = np.radians(10.0 - 10.0 * np.cos(2.0 * np.pi * 2.5 * t))
        eye = target + radius * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az),
                                          np.sin(el)])
        cams.append(make_camera(look_at(eye, target), width=size, height=size, fov_deg=fov_deg))
    return stack(cams), fov_deg


def studio_lights(head: np.ndarray) -> list[dict]:
    """Large soft key (front left, above), a dimmer fill (front right), a rim behind."""
    return [{"location": (head + [2.0, 1.4, 1.2]).tolist(), "size": 1.8, "power": 260.0},
            {"location": (head + [1.8, -2.0, 0.2]).tolist(), "size": 2.5, "power": 120.0},
            {"location": (head + [-1.6, 0.5, 1.4]).tolist(), "size": 1.2, "power": 120.0}]


# ------------------------------------------------------------------ points


def read_depth(path: Path) -> np.ndarray:
    """float [H, W] depth of Blender's Depth pass (large where nothing is hit)."""
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise RuntimeError(f"cannot read {path}: {oiio.geterror()}")
    try:
        pixels = np.asarray(inp.read_image(0, 0, 0, inp.spec().nchannels, "float"), np.float32)
    finally:
        inp.close()
    return pixels.reshape(pixels.shape[0], pixels.shape[1], -1)[..., 0]


def sample_surface(verts: np.ndarray, tris: np.ndarray, n: int, rng) -> np.ndarray:
    """float [n, 3] points uniform by area on the triangles."""
    a, b, c = (verts[tris[:, k]] for k in range(3))
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=-1)
    pick = rng.choice(len(tris), size=n, p=area / area.sum())
    u, v = rng.random(n), rng.random(n)
    flip = u + v > 1.0
    u, v = np.where(flip, 1.0 - u, u), np.where(flip, 1.0 - v, v)
    return a[pick] + u[:, None] * (b[pick] - a[pick]) + v[:, None] * (c[pick] - a[pick])


def visible_colours(points, cameras, rgba, depth, *, tol: float = 0.01):
    """(seen count [P], mean colour [P, 3]) of points over views whose depth agrees."""
    count = np.zeros(len(points))
    total = np.zeros((len(points), 3))
    for v in range(len(rgba)):
        w2c = np.asarray(cameras.world_to_camera[v], np.float64)
        pc = points @ w2c[:3, :3].T + w2c[:3, 3]
        z = pc[:, 2]
        u = float(cameras.fx[v]) * pc[:, 0] / z + float(cameras.cx[v])
        r = float(cameras.fy[v]) * pc[:, 1] / z + float(cameras.cy[v])
        col, row = np.floor(u).astype(int), np.floor(r).astype(int)
        h, w = depth[v].shape
        ok = (z > 0) & (col >= 0) & (col < w) & (row >= 0) & (row < h)
        col, row = np.clip(col, 0, w - 1), np.clip(row, 0, h - 1)
        ok &= np.abs(depth[v][row, col] - z) < tol
        ok &= rgba[v][row, col, 3] > 0.99  # interior pixels: no backdrop mixed into the colour
        count += ok
        total += np.where(ok[:, None], rgba[v][row, col, :3], 0.0)
    return count, total / np.maximum(count, 1)[:, None]


# ------------------------------------------------------------------ main


def main(argv=None) -> int:
    args = parse_args(argv)
    if shutil.which(args.blender) is None:
        raise SystemExit(f"render_person: {args.blender!r} not found (apt-get install blender)")
    if not Path(args.catalog).is_file():
        raise SystemExit(f"render_person: {args.catalog} not found "
                         f"(apt-get install sweethome3d-furniture)")
    rng = np.random.default_rng(args.seed)
    with tempfile.TemporaryDirectory(prefix="render_person.") as tmp:
        tmp = Path(tmp)
        obj, licence = extract_model(args.catalog, tmp / "model")
        verts, tris, materials = drop_back_faces(obj)
        m = model_to_world(verts)
        world = verts @ m[:3, :3].T + m[:3, 3]
        head = head_points(world).mean(0)
        target = head + np.array([0.0, 0.0, -0.06])  # about the chin: head and shoulders
        total = args.views + args.test_views
        cameras, fov = arc_cameras(target, total, args.size)
        job = {"obj": str(obj), "model_to_world": m.tolist(),
               "cameras": opencv_w2c_to_opengl_c2w(np.asarray(cameras.world_to_camera)).tolist(),
               "fov_deg": fov, "size": args.size, "samples": args.samples,
               "lights": studio_lights(head), "target": head.tolist(), "world": 0.35,
               "out": str(tmp / "render")}
        (tmp / "job.json").write_text(json.dumps(job), encoding="utf-8")
        start = time.perf_counter()
        subprocess.run([args.blender, "-b", "--factory-startup", "-noaudio", "-P",
                        str(ROOT / "scripts" / "blender_person.py"), "--", str(tmp / "job.json")],
                       check=True)
        seconds = time.perf_counter() - start
        rgba, depth = [], []
        for i in range(total):
            colour, alpha = read_image_with_alpha(tmp / "render" / "rgba" / f"frame_{i:05d}.png")
            rgba.append(np.concatenate([colour, alpha[..., None]], -1))
            depth.append(read_depth(tmp / "render" / "depth" / f"frame_{i:05d}.exr"))
        rgba, depth = np.stack(rgba), np.stack(depth)
        train, test = split_views(args.views, args.test_views)
        # Candidates on the framed part of the surface (head and shoulders, not the legs);
        # keep those two training views see, as SfM would.
        upper = tris[(world[tris][:, :, 2] > target[2] - 0.5).any(axis=1)]
        cand = sample_surface(world, upper, 4 * args.points, rng)
        seen, colours = visible_colours(cand, cameras[train], rgba[train], depth[train])
        keep = np.flatnonzero(seen >= 2)[:args.points]
        save_nerfstudio(args.out, rgba, cameras, train_indices=train, test_indices=test,
                        points=cand[keep], point_colors=colours[keep])
        solid = solid_vertices(tris, materials)
        vertex_ids = rng.choice(solid, size=min(args.vertices, len(solid)), replace=False)
        info = {"scene": "person", "size": args.size, "views": args.views,
                "test_views": args.test_views, "background": "transparent (RGBA PNG)",
                "description": "head and shoulders of a photo-textured man (Reallusion male02), "
                               "Cycles renders on a frontal arc",
                "render": json.loads((tmp / "render" / "render_info.json").read_text()),
                "render_seconds": round(seconds, 1), "fov_deg": fov,
                "credit": CREDIT,
                "mesh_vertices": np.round(world[np.sort(vertex_ids)], 5).tolist()}
        atomic_write_text(args.out / "jaxedit_scene.json", json.dumps(info, indent=1) + "\n")
        atomic_write_text(args.out / "CREDITS.txt", CREDIT + "\n")
        shutil.copyfile(licence, args.out / "LICENSE-Reallusion.txt")
    print(f"render_person: {total} views in {seconds:.0f} s, {len(keep)} points -> {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
