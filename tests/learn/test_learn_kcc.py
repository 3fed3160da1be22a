"""NI-SLAM front-end objective: pairs with ground truth, soft arg-max loss, gradients, training."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from torchslam.errors import ConfigError, ShapeError
from torchslam.geometry import se3_exp
from torchslam.kcc import KCCConfig, Subpixel, frame_taper, kcc_features
from torchslam.learn import (
    KCCPairs,
    KCCTrainConfig,
    content_translation,
    kcc_pair_errors,
    kcc_shift_loss,
    resized_kcc_config,
    synthetic_kcc_pairs,
    train_kcc,
    tum_kcc_pairs,
)
from torchslam.systems.nislam import NISlamConfig

SMALL = KCCConfig(ortho_height=90, ortho_width=120)
DATA = dict(frames=30, keyframe_step=5, gaps=(2, 4), width=160, height=120)


@pytest.fixture(scope="module")
def pairs() -> KCCPairs:
    # Module fixtures run before the autouse one-thread fixture: set it here too.
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        return synthetic_kcc_pairs([0, 1], SMALL, **DATA)
    finally:
        torch.set_num_threads(threads)


def test_content_translation_is_what_nislam_inverts():
    g = torch.Generator().manual_seed(0)
    T_wk = se3_exp(torch.randn(5, 6, generator=g, dtype=torch.float64))
    T_wi = se3_exp(torch.randn(5, 6, generator=g, dtype=torch.float64))
    t = content_translation(T_wk, T_wi)
    # NISlam._pose: the frame's camera sits at -t in the keyframe attitude frame
    p_wi = T_wk[:, :3, 3] + (T_wk[:, :3, :3] @ (-t)[..., None])[..., 0]
    assert torch.allclose(p_wi, T_wi[:, :3, 3], atol=1e-12)
    # batched == per item (to float64 round-off: a batched and a single matmul may round
    # differently on some CPUs), and leading dims are kept
    for k in range(5):
        torch.testing.assert_close(content_translation(T_wk[k], T_wi[k]), t[k], rtol=1e-12, atol=1e-12)
    assert content_translation(T_wk.view(5, 1, 4, 4), T_wi.view(5, 1, 4, 4)).shape == (5, 1, 3)


def test_hard_peak_matches_ground_truth_before_training(pairs):
    # The frame conventions are right if the paper's defaults already find the true shift:
    # the translations are 0.7-5 px, the errors a small fraction of a pixel.
    assert len(pairs) == 12
    true_px = (pairs.t_xy / pairs.resolution[:, None]).norm(dim=1)
    assert float(true_px.max()) > 3.0
    err = kcc_pair_errors(pairs, SMALL)
    err_px = (err / pairs.resolution[:, None]).norm(dim=1)
    assert float(err_px.max()) < 0.5
    assert float(err_px.square().mean().sqrt()) < 0.3
    # the integer peak alone is within rounding of the truth
    err_int = kcc_pair_errors(pairs, dataclasses.replace(SMALL, subpixel=Subpixel.NONE))
    assert float((err_int / pairs.resolution[:, None]).abs().max()) < 1.0


def test_loss_is_batched_and_matches_per_pair(pairs):
    out = kcc_shift_loss(pairs, 0.3, 0.05, 0.01, SMALL)
    assert out.error_px.shape == (len(pairs), 2) and out.t_xy.shape == (len(pairs), 2)
    assert float(out.loss) == pytest.approx(float(out.error_px.square().sum(1).mean()), rel=1e-6)
    for k in (0, 5, 11):
        one = kcc_shift_loss(pairs.select(slice(k, k + 1)), 0.3, 0.05, 0.01, SMALL)
        assert torch.allclose(one.error_px[0], out.error_px[k], atol=1e-4)


def _tiny_pairs(dtype=torch.float64) -> KCCPairs:
    """Two pairs of 2-channel 12x16 images: smooth random content, frames shifted by known amounts."""
    g = torch.Generator().manual_seed(5)
    H, W = 12, 16
    base = torch.randn(2, 2, H, W, generator=g, dtype=dtype)
    # smooth a little so the correlation peak spans a few pixels (soft arg-max has a gradient)
    k = torch.tensor([0.25, 0.5, 0.25], dtype=dtype)
    base = base + torch.roll(base, 1, -1) * k[0] + torch.roll(base, -1, -1) * k[2]
    base = base + torch.roll(base, 1, -2) * k[0] + torch.roll(base, -1, -2) * k[2]
    shifts = [(1, 2), (-2, 1)]  # (s_x, s_y) content shift in pixels
    frame = torch.stack([torch.roll(base[b], (sy, sx), (-2, -1)) for b, (sx, sy) in enumerate(shifts)])
    frame = frame + 0.3 * torch.randn(frame.shape, generator=g, dtype=dtype)
    r = torch.tensor([0.01, 0.02], dtype=dtype)
    # ground truth deliberately off the integer shift so the loss has a slope
    t = torch.tensor([[1.3, 1.8], [-1.6, 1.2]], dtype=dtype) * r[:, None]
    return KCCPairs(base, frame, r, t)


def test_gradcheck_loss_wrt_sigma_lambda_temperature():
    p = _tiny_pairs()
    x = [torch.tensor(v, dtype=torch.float64, requires_grad=True) for v in (0.4, 0.1, 0.3)]
    assert torch.autograd.gradcheck(lambda s, l, t: kcc_shift_loss(p, s, l, t).loss, x, eps=1e-6, atol=1e-6, rtol=1e-4)


def test_finite_differences_of_loss_wrt_sigma():
    p = _tiny_pairs()
    sigma = torch.tensor(0.5, dtype=torch.float64, requires_grad=True)
    loss = kcc_shift_loss(p, sigma, 0.1, 0.2).loss
    (grad,) = torch.autograd.grad(loss, sigma)
    eps = 1e-5
    up = float(kcc_shift_loss(p, 0.5 + eps, 0.1, 0.2).loss)
    down = float(kcc_shift_loss(p, 0.5 - eps, 0.1, 0.2).loss)
    fd = (up - down) / (2 * eps)
    assert abs(fd) > 1e-4  # a real slope, not a flat loss
    assert float(grad) == pytest.approx(fd, rel=1e-5)


def test_a_few_training_steps_lower_the_loss_and_move_sigma_lambda():
    cfg = KCCTrainConfig(train_seeds=(0, 1), val_seeds=(100,), steps=8, eval_every=4, lr=0.1,
                         ortho_height=90, ortho_width=120, **DATA)
    res = train_kcc(cfg)
    m = res.metrics
    assert m["default"] == {"sigma": 0.2, "lam": 0.1, "temperature": 0.02}
    assert m["train_loss_learned"] < 0.7 * m["train_loss_default"]
    assert m["train_loss_last"] < m["train_loss_first"]
    learned = m["learned"]
    assert abs(math.log(learned["sigma"] / 0.2)) > 0.05 and abs(math.log(learned["lam"] / 0.1)) > 0.05
    assert {f"kcc.{k}": v for k, v in learned.items()} == pytest.approx(res.module.floats())
    # held-out seed: the objective falls there too
    assert m["val_learned"]["soft_loss_px2"] < m["val_default"]["soft_loss_px2"]
    assert [h["step"] for h in res.history] == [0, 4, 8]
    # seeded: a second run gives the same values
    again = train_kcc(dataclasses.replace(cfg, steps=2, eval_every=2))
    again2 = train_kcc(dataclasses.replace(cfg, steps=2, eval_every=2))
    assert again.metrics["learned"] == again2.metrics["learned"]


def test_tum_pairs_match_ground_truth(shared_data):
    pairs = tum_kcc_pairs(shared_data / "tum_fr1_xyz", SMALL, first=0, count=20, keyframe_step=5, gaps=(3,))
    # keyframes 0, 5, 10, 15; the first colour frames precede the ground truth's start
    assert 3 <= len(pairs) <= 4
    err = kcc_pair_errors(pairs, SMALL)
    err_px = (err / pairs.resolution[:, None]).norm(dim=1)
    # real data (depth noise, motion blur, ground-truth jitter): within a few pixels, mostly ~1
    assert float(err_px.median()) < 1.5
    assert float(err.norm(dim=1).max()) < 0.02  # metres


def test_bad_inputs_raise():
    p = _tiny_pairs()
    with pytest.raises(ShapeError, match="t_xy"):
        KCCPairs(p.keyframe, p.frame, p.resolution, p.t_xy[:, :1])
    with pytest.raises(ShapeError, match="frame"):
        KCCPairs(p.keyframe, p.frame[:1], p.resolution, p.t_xy)
    with pytest.raises(ShapeError, match="sigma: expected a float or a 0-d"):
        kcc_shift_loss(p, torch.ones(2, dtype=torch.float64), 0.1, 0.1)
    with pytest.raises(ConfigError, match="gaps"):
        synthetic_kcc_pairs([0], SMALL, gaps=(0,))
    with pytest.raises(ConfigError, match="seeds"):
        synthetic_kcc_pairs([], SMALL)
    with pytest.raises(ConfigError, match="val_seeds: must not overlap"):
        KCCTrainConfig(train_seeds=(0, 1), val_seeds=(1,))
    with pytest.raises(ConfigError, match="names: the KCC objective"):
        KCCTrainConfig(names=("kcc.T_c",))
    with pytest.raises(ConfigError, match="sigma, lam"):
        kcc_pair_errors(p, SMALL, sigma=-1.0)


def test_pairs_select_and_cat():
    p = _tiny_pairs()
    both = KCCPairs.cat([p.select(slice(0, 1)), p.select(torch.tensor([1]))])
    for f in ("keyframe", "frame", "resolution", "t_xy"):
        assert torch.equal(getattr(both, f), getattr(p, f))
    assert len(p.select(torch.tensor([True, False]))) == 1
    with pytest.raises(ShapeError, match="parts"):
        KCCPairs.cat([])
    # features of identical images give a frame that the hard peak places at shift 0
    z = kcc_features(torch.rand(1, 8, 8), torch.rand(1, 8, 8), torch.ones(1, 8, 8, dtype=torch.bool))
    same = KCCPairs(z, z.clone(), torch.ones(1), torch.zeros(1, 2))
    assert float(kcc_pair_errors(same, dataclasses.replace(SMALL, psr_window=3)).abs().max()) < 1e-3


def test_resized_config_keeps_the_frame_taper_share_of_the_window():
    run = NISlamConfig().kcc  # 360x480, frame_taper 24
    assert resized_kcc_config(run, 180, 240).frame_taper == 12
    assert resized_kcc_config(run, 90, 120).frame_taper == 6
    assert resized_kcc_config(run, 90, 240).frame_taper == 6  # the tighter side decides
    assert resized_kcc_config(run, 4, 5).frame_taper == 1  # a run that tapers keeps a taper
    small = resized_kcc_config(run, 90, 120, sigma=0.3)
    assert (small.ortho_height, small.ortho_width, small.sigma) == (90, 120, 0.3)
    assert resized_kcc_config(KCCConfig(), 90, 120).frame_taper == 0  # the paper's: none
    # train_kcc renders its pairs with the scaled taper of the NI-SLAM config it starts from
    assert resized_kcc_config(run, KCCTrainConfig().ortho_height, KCCTrainConfig().ortho_width).frame_taper == 12


def test_pairs_taper_the_frame_channels_only(pairs):
    tapered = synthetic_kcc_pairs([0, 1], dataclasses.replace(SMALL, frame_taper=6), **DATA)
    w = frame_taper(90, 120, 6, pairs.frame.dtype)
    torch.testing.assert_close(tapered.keyframe, pairs.keyframe, rtol=0, atol=0)
    torch.testing.assert_close(tapered.frame, pairs.frame * w, rtol=1e-6, atol=1e-6)
    assert not torch.allclose(tapered.frame, pairs.frame)
