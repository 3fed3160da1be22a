"""The CUDA path against the CPU, stage by stage (skipped without a GPU; ``scripts/gpu_check.py`` runs them).

The same inputs go through each stage on the CPU and on ``cuda``; results agree within float32
round-off (float64 for the back-end), and every result lives on the device of its inputs.
"""

from __future__ import annotations

import pytest
import torch

from torchslam.config import config_from_dict
from torchslam.data.synthetic import SyntheticConfig, generate_sequence

pytestmark = pytest.mark.cuda
CUDA = "cuda"


def _seq(seed: int = 0, frames: int = 6):
    return generate_sequence(SyntheticConfig(frames=frames, trajectory="orbit", seed=seed, height=120, width=160))


def _on(x, device):
    return x.to(device) if isinstance(x, torch.Tensor) else x


def _close(a, b, atol):
    assert b.device.type == CUDA
    torch.testing.assert_close(a, b.cpu(), atol=atol, rtol=0)


def _cloud(device):
    from torchslam.kcc import rgbd_to_points

    seq = _seq()
    f = seq[0]
    intr = seq.camera.as_tensor(torch.float32, device)[None]
    return rgbd_to_points(f.rgb.to(device)[None], f.depth.to(device)[None], intr)


def test_orthographic_projection():
    from torchslam.kcc import choose_resolution, orthographic_project

    out = {}
    for dev in ("cpu", CUDA):
        points, grey, valid = _cloud(dev)
        r = choose_resolution(points, valid, (90, 120))
        out[dev] = orthographic_project(points, grey, valid, None, r, (90, 120))
    _close(out["cpu"].depth, out[CUDA].depth, 1e-5)
    _close(out["cpu"].grey, out[CUDA].grey, 1e-5)
    assert torch.equal(out["cpu"].valid, out[CUDA].valid.cpu())


def test_kcc_train_predict_and_fusion():
    from torchslam.kcc import KCCConfig, choose_resolution, fuse_keyframe, keyframe_filter, keyframe_map, orthographic_project, track_step

    cfg = KCCConfig(ortho_height=90, ortho_width=120)
    out = {}
    for dev in ("cpu", CUDA):
        points, grey, valid = _cloud(dev)
        r = choose_resolution(points, valid, (90, 120))
        kf = keyframe_map(orthographic_project(points, grey, valid, None, r, (90, 120)))
        filt = keyframe_filter(kf, cfg)
        R = torch.eye(3, device=dev)[None]
        res = track_step(points, grey, valid, R, kf, filt, r, cfg)
        fused = fuse_keyframe(kf, res.frame, res.index, res.t_content[:, 2], res.matched, res.psr, 0.0)
        out[dev] = (filt.h_hat, res.t_content, res.psr, fused.depth)
    for a, b in zip(out["cpu"], out[CUDA]):
        assert b.device.type == CUDA
        torch.testing.assert_close(a, b.cpu(), atol=1e-3, rtol=1e-4)


def test_dense_registration():
    from torchslam.registration.dense import register_dense

    seq = _seq()
    f0, f1 = seq[0], seq[2]
    out = {}
    for dev in ("cpu", CUDA):
        out[dev] = register_dense(f0.rgb.to(dev)[None], f0.depth.to(dev)[None], f1.rgb.to(dev)[None], f1.depth.to(dev)[None], seq.camera)
    _close(out["cpu"].T_ij, out[CUDA].T_ij, 1e-5)


def test_fastgo_and_pose_graph_float64():
    from torchslam.backend import optimize_pose_graph
    from torchslam.fastgo import optimize
    from torchslam.fastgo.synthetic import loop_route_problem
    from torchslam.geometry import se3_inverse

    P = loop_route_problem(120, noise=0.01, seed=0)
    a = optimize(P.T_init, P.pairs, P.stats).T_wc
    b = optimize(P.T_init.to(CUDA), P.pairs.to(CUDA), P.stats.to(CUDA)).T_wc
    _close(a, b, 1e-8)
    i, j = P.pairs[:, 0], P.pairs[:, 1]
    T_ij = se3_inverse(P.T_gt[i]) @ P.T_gt[j]
    info = torch.eye(6, dtype=torch.float64).expand(len(i), 6, 6) * 1e4
    c = optimize_pose_graph(P.T_init, i, j, T_ij, info).T_wc
    d = optimize_pose_graph(*(t.to(CUDA) for t in (P.T_init, i, j, T_ij, info))).T_wc
    _close(c, d, 1e-8)


def test_lockstep_nislam_b8():
    from torchslam.systems import run_sequence
    from torchslam.systems.lockstep import run_lockstep
    from torchslam.systems.nislam import NISlam, NISlamConfig

    cfg = config_from_dict(NISlamConfig, {"attitude": "imu", "kcc": {"ortho_height": 90, "ortho_width": 120}})
    seqs = [_seq(seed, frames=8) for seed in range(8)]
    together = run_lockstep(cfg, seqs, device=CUDA, max_batch=8)
    for seq, r in zip(seqs, together):
        assert not isinstance(r, BaseException), r
        ref = run_sequence(NISlam(cfg, device="cpu"), seq).output
        torch.testing.assert_close(r.output.T_wc.cpu(), ref.T_wc, atol=1e-4, rtol=0)
