"""Parity: jaxedit ``reconstruct`` against gsplat with simple_trainer's recipe, side by side.

    python benchmarks/parity.py --data DIR [--steps 2500 7000] [--lpips-weights FILE]
                                [--out DIR] [--smoke]

Both trainers start from the dataset's ``ply_file_path`` points (or the same
random cube when it has none), train on its training views for each step count
(one run per count: the means' learning-rate decay and density control depend
on it), composite on a white background, and are evaluated on its held-out
views with the same metrics: PSNR and SSIM (scikit-image), LPIPS-vgg where
``--lpips-weights`` gives the converted weights (``python -m experiments
convert-lpips``), steps/s and the final Gaussian count.

The gsplat side (gsplat 1.5.3 + torch, CUDA) runs where both import and a GPU is
present: a minimal trainer with simple_trainer's defaults (Adam learning rates,
``DefaultStrategy``, 0.8 L1 + 0.2 D-SSIM, random initial quaternions, SH degree
up by one every 1000 steps). Elsewhere the rows come from
``benchmarks/gsplat_baseline.json``, figures measured on an H100 and labelled
with their provenance (scene, date, what was not recorded); they compare only
when ``--data`` is that dataset.

Writes ``DIR/parity.json``. ``--smoke``: the built-in face at 32 px, 40 steps, CPU,
seconds (the gsplat rows are the committed ones).
"""

from __future__ import annotations

import json
import math
import tempfile
import time
from pathlib import Path

import numpy as np
from common import parse_args, write_json

BASELINE = Path(__file__).resolve().parent / "gsplat_baseline.json"


def extra(p):
    p.add_argument("--data", type=Path, default=None, help="nerfstudio dataset folder")
    p.add_argument("--steps", type=int, nargs="+", default=None, help="step counts (2500 7000)")
    p.add_argument("--lpips-weights", type=Path, default=None, help="LPIPS-vgg weights file")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--no-gsplat", action="store_true", help="skip the live gsplat runs")
    p.add_argument("--sides", default="jaxedit,gsplat",
                   help="which trainers to run here (a GPU session may split them)")
    p.add_argument("--renders", type=Path, default=None,
                   help="also save each run's held-out renders (uint8 .npz) in this folder, "
                        "e.g. to score LPIPS elsewhere")


def held_out_metrics(renders, targets, lpips_fn=None) -> dict:
    """PSNR / SSIM (scikit-image) and LPIPS (or None) averaged over the held-out views."""
    from jaxedit.metrics import psnr, ssim_skimage

    renders = np.clip(np.asarray(renders, np.float32), 0.0, 1.0)
    targets = np.asarray(targets, np.float32)
    out = {"psnr": float(np.mean([psnr(r, t) for r, t in zip(renders, targets)])),
           "ssim": float(np.mean([ssim_skimage(r, t) for r, t in zip(renders, targets)])),
           "lpips": None}
    if lpips_fn is not None:
        out["lpips"] = float(np.mean([float(lpips_fn(r, t)) for r, t in zip(renders, targets)]))
    return out


def save_renders(folder, name: str, renders) -> None:
    if folder is not None:
        folder.mkdir(parents=True, exist_ok=True)
        u8 = (np.clip(np.asarray(renders, np.float32), 0.0, 1.0) * 255 + 0.5).astype(np.uint8)
        np.savez_compressed(folder / f"{name}.npz", renders=u8)


def run_jaxedit(data, steps: int, seed: int, workdir: Path, lpips_fn, renders_dir=None) -> dict:
    """One ``reconstruct`` run with the CLI's defaults (white background)."""
    from jaxedit import train as T
    from jaxedit.io import load_ply
    from jaxedit.pipelines.reconstruct import reconstruct

    config = T.TrainConfig(iterations=steps)
    m = reconstruct(data, workdir, config, seed=seed, checkpoint_every=0, log_every=100)
    g = load_ply(workdir / "scene.ply")
    test_images, test_cams = data.test()
    renders = T.render_views(g, test_cams, sh_degree=config.sh_degree)
    save_renders(renders_dir, f"jaxedit_{steps}", renders)
    return dict(steps=steps, **held_out_metrics(renders, test_images, lpips_fn),
                steps_per_s=m["steps_per_s"], steady_steps_per_s=m["steady_steps_per_s"],
                train_time_s=m["train_time_s"], num_gaussians=m["num_gaussians"],
                initial_points=m["initial_points"])


def gsplat_available() -> bool:
    try:
        import gsplat  # noqa: F401
        import torch
    except ImportError:
        return False
    return bool(torch.cuda.is_available())


def torch_ssim(a, b):
    """Mean SSIM of [B, 3, H, W] images, Gaussian window 11 / sigma 1.5, 'valid' (as fused_ssim)."""
    import torch
    import torch.nn.functional as F

    x = torch.arange(11, dtype=a.dtype, device=a.device) - 5
    w = torch.exp(-x ** 2 / (2 * 1.5 ** 2))
    w = w / w.sum()
    win = (w[:, None] * w[None, :]).expand(3, 1, 11, 11).contiguous()

    def filt(z):
        return F.conv2d(z, win, groups=3)

    mu_a, mu_b = filt(a), filt(b)
    var_a = filt(a * a) - mu_a ** 2
    var_b = filt(b * b) - mu_b ** 2
    cov = filt(a * b) - mu_a * mu_b
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    s = ((2 * mu_a * mu_b + c1) * (2 * cov + c2)) / ((mu_a ** 2 + mu_b ** 2 + c1) * (var_a + var_b + c2))
    return s.mean()


def run_gsplat(data, points, colors, steps: int, seed: int, lpips_fn, renders_dir=None) -> dict:
    """A minimal gsplat trainer with simple_trainer's defaults (one view per step)."""
    import torch
    from gsplat import rasterization
    from gsplat.strategy import DefaultStrategy
    from scipy.spatial import cKDTree

    from jaxedit import sh as shlib
    from jaxedit.train import scene_extent

    torch.manual_seed(seed)
    dev = torch.device("cuda")
    images, cams = data.train()
    test_images, test_cams = data.test()
    scene_scale = scene_extent(cams)

    def camera_tensors(c):
        viewmats = torch.as_tensor(np.asarray(c.world_to_camera), dtype=torch.float32, device=dev)
        k = np.zeros((len(c), 3, 3), np.float32)
        k[:, 0, 0], k[:, 1, 1] = np.asarray(c.fx), np.asarray(c.fy)
        k[:, 0, 2], k[:, 1, 2], k[:, 2, 2] = np.asarray(c.cx), np.asarray(c.cy), 1.0
        return viewmats, torch.as_tensor(k, device=dev)

    viewmats, ks = camera_tensors(cams)
    gt = torch.as_tensor(np.asarray(images, np.float32), device=dev)
    n = len(points)
    dist, _ = cKDTree(points).query(points, k=4)
    scales = np.log(np.sqrt(np.mean(dist[:, 1:] ** 2, axis=-1)).clip(1e-7))
    sh = np.zeros((n, 16, 3), np.float32)
    sh[:, 0] = shlib.rgb_to_dc(np.clip(colors, 0.0, 1.0))
    params = torch.nn.ParameterDict({
        "means": torch.nn.Parameter(torch.as_tensor(points, dtype=torch.float32, device=dev)),
        "scales": torch.nn.Parameter(torch.as_tensor(scales[:, None].repeat(3, 1),
                                                     dtype=torch.float32, device=dev)),
        "quats": torch.nn.Parameter(torch.rand((n, 4), device=dev)),
        "opacities": torch.nn.Parameter(torch.full((n,), math.log(0.1 / 0.9), device=dev)),
        "sh0": torch.nn.Parameter(torch.as_tensor(sh[:, :1], device=dev)),
        "shN": torch.nn.Parameter(torch.as_tensor(sh[:, 1:], device=dev)),
    })
    lrs = dict(means=1.6e-4 * scene_scale, scales=5e-3, quats=1e-3, opacities=5e-2, sh0=2.5e-3,
               shN=2.5e-3 / 20)
    optimizers = {k: torch.optim.Adam([{"params": params[k], "lr": lr, "name": k}], eps=1e-15)
                  for k, lr in lrs.items()}
    decay = torch.optim.lr_scheduler.ExponentialLR(optimizers["means"], gamma=0.01 ** (1 / steps))
    strategy = DefaultStrategy()
    strategy.check_sanity(params, optimizers)
    state = strategy.initialize_state(scene_scale=scene_scale)
    white = torch.ones(3, device=dev)
    width, height = cams.width, cams.height

    def render(i_views, vm, kk, degree):
        colors_, alphas, info = rasterization(
            params["means"], params["quats"], torch.exp(params["scales"]),
            torch.sigmoid(params["opacities"]), torch.cat([params["sh0"], params["shN"]], 1),
            vm[i_views], kk[i_views], width, height, sh_degree=degree, packed=False)
        return colors_ + (1.0 - alphas) * white, info

    rng = np.random.default_rng(seed)
    order = []
    torch.cuda.synchronize()
    t0 = time.perf_counter()
    for step in range(steps):
        if not order:
            order = list(rng.permutation(len(images)))
        i = int(order.pop())
        rgb, info = render([i], viewmats, ks, min(step // 1000, 3))
        strategy.step_pre_backward(params, optimizers, state, step, info)
        target = gt[i:i + 1]
        l1 = torch.abs(rgb - target).mean()
        dssim = 1.0 - torch_ssim(rgb.permute(0, 3, 1, 2), target.permute(0, 3, 1, 2))
        loss = 0.8 * l1 + 0.2 * dssim
        loss.backward()
        for opt in optimizers.values():
            opt.step()
            opt.zero_grad(set_to_none=True)
        decay.step()
        strategy.step_post_backward(params, optimizers, state, step, info, packed=False)
    torch.cuda.synchronize()
    train_s = time.perf_counter() - t0
    tv, tk = camera_tensors(test_cams)
    with torch.no_grad():
        renders = [render([j], tv, tk, 3)[0][0].clamp(0, 1).cpu().numpy()
                   for j in range(len(test_images))]
    save_renders(renders_dir, f"gsplat_{steps}", renders)
    return dict(steps=steps, **held_out_metrics(renders, test_images, lpips_fn),
                steps_per_s=steps / train_s, train_time_s=train_s,
                num_gaussians=int(params["means"].shape[0]))


def committed_gsplat() -> dict:
    return json.loads(BASELINE.read_text())


def side_by_side(ours: list[dict], theirs: list[dict]) -> list[dict]:
    """Per step count: both rows and the differences (ours - gsplat) where both exist."""
    rows = []
    by_steps = {r["steps"]: r for r in theirs}
    for r in ours:
        g = by_steps.get(r["steps"])
        row = {"steps": r["steps"], "jaxedit": r, "gsplat": g}
        if g is not None:
            row["psnr_diff_db"] = (r["psnr"] - g["psnr"]) if g.get("psnr") is not None else None
            row["gaussians_ratio"] = (r["num_gaussians"] / g["num_gaussians"]
                                      if g.get("num_gaussians") else None)
            row["speed_ratio"] = (r["steps_per_s"] / g["steps_per_s"]
                                  if g.get("steps_per_s") else None)
        rows.append(row)
    return rows


def main(argv=None):
    args = parse_args(__doc__.splitlines()[0], argv, extra)
    from experiments.progress import configure
    from jaxedit import DataError, scenes
    from jaxedit.io import load_nerfstudio
    from jaxedit.pipelines.reconstruct import initial_points

    configure(mode="log", log_interval=60.0)
    steps = args.steps or ([40] if args.smoke else [2500, 7000])
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        data_dir = args.data
        if data_dir is None:
            if not args.smoke:
                raise SystemExit("parity: --data DIR is required (or --smoke)")
            data_dir = scenes.make_scene("face", tmp / "data", size=32, views=8, test_views=2,
                                         num_points=500)
        try:
            data = load_nerfstudio(data_dir, background=(1.0, 1.0, 1.0))
        except DataError as e:
            raise SystemExit(f"parity: {e}") from None
        if not len(data.test_indices):
            raise SystemExit(f"parity: {data_dir} has no held-out views")
        lpips_fn = None
        if args.lpips_weights is not None:
            from jaxedit.lpips import load_lpips
            lpips_fn = load_lpips(args.lpips_weights)
        sides = set(args.sides.split(","))
        ours = [run_jaxedit(data, s, args.seed, tmp / f"jaxedit_{s}", lpips_fn, args.renders)
                for s in steps] if "jaxedit" in sides else []
        live = (gsplat_available() and not args.no_gsplat and not args.smoke
                and "gsplat" in sides)
        if live:
            points, colors, _ = initial_points(data, 20_000, args.seed)
            theirs = [run_gsplat(data, points, colors, s, args.seed, lpips_fn, args.renders)
                      for s in steps]
            gsplat_source = {"source": "measured in this run"}
        else:
            baseline = committed_gsplat()
            theirs = baseline["runs"]
            gsplat_source = {k: v for k, v in baseline.items() if k != "runs"}
            gsplat_source["source"] = f"committed figures ({BASELINE.name}), not measured here"
    payload = {"data": str(args.data) if args.data else "built-in face (smoke)",
               "steps": steps, "smoke": bool(args.smoke), "gsplat_source": gsplat_source,
               "rows": side_by_side(ours, theirs) if ours else [
                   {"steps": g["steps"], "jaxedit": None, "gsplat": g} for g in theirs]}
    write_json(args.out, "parity", payload)
    for row in payload["rows"]:
        r, g = row["jaxedit"], row["gsplat"]
        line = f"{row['steps']} steps:"
        if r is not None:
            line += (f" jaxedit {r['psnr']:.2f} dB, {r['num_gaussians']} Gaussians, "
                     f"{r['steps_per_s']:.1f} steps/s")
        if g is not None:
            line += (f" | gsplat {g['psnr']:.2f} dB, {g['num_gaussians']} Gaussians, "
                     f"{g['steps_per_s']:.1f} steps/s")
        print(line)


if __name__ == "__main__":
    main()
