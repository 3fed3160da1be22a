"""Micro-benchmark of the NI-SLAM per-frame front-end core: orthographic projection + KCC predict + PSR.

Frames are a smooth random textured surface 1-2 m away, rotated slightly against the keyframe;
B frames are matched at once. Prints median and best milliseconds per frame for each batch size
and, with ``--out``, writes them as JSON. Usage::

    python scripts/bench_kcc.py [--batch 1 4 16] [--size 480 640] [--repeats 10] [--device cpu] [--quick]
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor

from _bench import sync
from torchslam.environment import environment_info
from torchslam.errors import ShapeError
from torchslam.geometry import so3_exp
from torchslam.kcc import KCCConfig, choose_resolution, correlator_for, kcc_features, keyframe_filter, orthographic_project, rgbd_to_points


def _synthetic_rgbd(batch: int, size: tuple[int, int], gen: torch.Generator, dtype, device) -> tuple[Tensor, Tensor]:
    """A smooth random textured surface 1–2 m away: (B, 3, H, W) colour and (B, 1, H, W) depth."""
    H, W = size
    tex = torch.rand(batch, 3, H // 8, W // 8, generator=gen, dtype=dtype)
    rgb = F.interpolate(tex, size=(H, W), mode="bilinear", align_corners=False)
    rough = torch.rand(batch, 1, 6, 8, generator=gen, dtype=dtype)
    depth = 1.0 + F.interpolate(rough, size=(H, W), mode="bicubic", align_corners=False).clamp(0, 1)
    return rgb.to(device), depth.to(device)


def benchmark_frontend(
    batch_size: int = 1,
    image_size: tuple[int, int] = (480, 640),
    cfg: KCCConfig | None = None,
    repeats: int = 10,
    warmup: int = 2,
    device: str | torch.device = "cpu",
    dtype: torch.dtype = torch.float32,
    seed: int = 0,
    rgb: Tensor | None = None,
    depth: Tensor | None = None,
    intrinsics: Tensor | None = None,
) -> dict[str, float]:
    """Time the per-frame front-end core on ``batch_size`` frames at once.

    Per repeat: back-projection of the RGB-D frames, rotation and orthographic projection
    (z-buffer), KCC features, prediction and PSR against a filter trained once beforehand.
    Training and the resolution search (once per keyframe) are timed separately.

    Args:
        batch_size: frames matched at once (B).
        image_size: ``(H, W)`` of the synthetic input images (ignored when ``rgb`` is given).
        cfg: KCC settings (orthographic size, σ, λ, sub-pixel mode, ...); default ``KCCConfig()``.
        repeats: timed repetitions.
        warmup: untimed repetitions first.
        device: where to run.
        dtype: float32 or float64.
        seed: seed of the synthetic scene and rotations.
        rgb: optional (B, 3, H, W) colour in [0, 1] to use instead of the synthetic scene.
        depth: optional (B, 1, H, W) depth in metres (with ``rgb``).
        intrinsics: optional (4,) or (B, 4) ``(fx, fy, cx, cy)``; default Kinect-like.

    Returns:
        Median milliseconds per batch and per frame for ``ortho`` (back-projection +
        projection), ``kcc`` (features + predict + PSR) and ``total``, ``frames_per_s``, the
        fastest repeat (``best_total_ms_per_frame``, ``best_frames_per_s``) and the
        once-per-keyframe ``train_ms`` (resolution + projection + training).
    """
    cfg = cfg if cfg is not None else KCCConfig()
    device = torch.device(device)
    gen = torch.Generator().manual_seed(seed)
    if rgb is None:
        rgb, depth = _synthetic_rgbd(batch_size, image_size, gen, dtype, device)
    elif depth is None:
        raise ShapeError("depth: required when rgb is given")
    B, _, H, W = rgb.shape
    if intrinsics is None:
        f = 525.0 * W / 640.0
        intrinsics = torch.tensor([f, f, (W - 1) / 2, (H - 1) / 2], dtype=dtype, device=device)
    size = (cfg.ortho_height, cfg.ortho_width)
    correlator = correlator_for(cfg).to(device)
    rot = so3_exp(0.02 * torch.randn(B, 3, generator=gen, dtype=dtype).to(device))

    def project(rotation, r_k):
        points, grey, valid = rgbd_to_points(rgb, depth, intrinsics)
        return orthographic_project(points, grey, valid, rotation, r_k, size)

    with torch.no_grad():
        sync(device)
        t0 = time.perf_counter()
        points, grey, valid = rgbd_to_points(rgb, depth, intrinsics)
        r_k = choose_resolution(points, valid, size, cfg.coverage, cfg.sample_step)
        kf = orthographic_project(points, grey, valid, None, r_k, size)
        filt = keyframe_filter(kf, correlator)
        sync(device)
        train_ms = (time.perf_counter() - t0) * 1e3

        t_ortho: list[float] = []
        t_kcc: list[float] = []
        for i in range(warmup + repeats):
            sync(device)
            t0 = time.perf_counter()
            ortho = project(rot, r_k)
            sync(device)
            t1 = time.perf_counter()
            x = kcc_features(ortho.grey, ortho.depth, ortho.valid, cfg.channel_norm, cfg.fill_holes)
            pred = correlator(x, filt, r_k)
            pred.psr.sum().item()  # forces completion on lazy backends
            sync(device)
            t2 = time.perf_counter()
            if i >= warmup:
                t_ortho.append((t1 - t0) * 1e3)
                t_kcc.append((t2 - t1) * 1e3)
    # Medians, and minima: on a shared machine the minimum is the least disturbed repeat.
    ortho_ms = statistics.median(t_ortho)
    kcc_ms = statistics.median(t_kcc)
    total = statistics.median([a + b for a, b in zip(t_ortho, t_kcc)])
    best = min(a + b for a, b in zip(t_ortho, t_kcc))
    return {
        "batch_size": float(B),
        "ortho_ms_per_batch": ortho_ms,
        "kcc_ms_per_batch": kcc_ms,
        "total_ms_per_batch": total,
        "ortho_ms_per_frame": ortho_ms / B,
        "kcc_ms_per_frame": kcc_ms / B,
        "total_ms_per_frame": total / B,
        "frames_per_s": 1e3 * B / total,
        "best_total_ms_per_frame": best / B,
        "best_frames_per_s": 1e3 * B / best,
        "train_ms": train_ms,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--batch", type=int, nargs="+", default=[1, 4, 16], help="frames matched at once (B)")
    ap.add_argument("--size", type=int, nargs=2, default=[480, 640], metavar=("H", "W"), help="input image size")
    ap.add_argument("--repeats", type=int, default=10)
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--dtype", choices=["float32", "float64"], default="float32")
    ap.add_argument("--quick", action="store_true", help="tiny images and orthographic size, two repeats (smoke run)")
    ap.add_argument("--out", type=Path, default=None, help="write the figures to this JSON file")
    args = ap.parse_args(argv)
    cfg = KCCConfig()
    size, repeats, warmup = tuple(args.size), args.repeats, args.warmup
    if args.quick:
        cfg, size, repeats, warmup = KCCConfig(ortho_height=36, ortho_width=48), (48, 64), 2, 1
    rows = []
    for B in args.batch:
        out = benchmark_frontend(B, size, cfg, repeats, warmup, args.device, getattr(torch, args.dtype))
        rows.append(out)
        print(f"  B={B:3d}: {out['total_ms_per_frame']:8.3f} ms/frame median ({out['ortho_ms_per_frame']:.3f} ortho + "
              f"{out['kcc_ms_per_frame']:.3f} KCC), {out['best_total_ms_per_frame']:.3f} best, "
              f"train {out['train_ms']:.1f} ms", flush=True)
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        result = {"machine": environment_info(), "image_size": list(size), "device": args.device, "dtype": args.dtype,
                  "ortho": [cfg.ortho_height, cfg.ortho_width], "repeats": repeats, "rows": rows}
        args.out.write_text(json.dumps(result, indent=2) + "\n")
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
