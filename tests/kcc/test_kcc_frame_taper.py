"""``KCCConfig.frame_taper``: the frame's KCC channels tapered at its window's border, the keyframe's not."""

from __future__ import annotations

import math

import pytest
import torch

from torchslam.data.synthetic import SyntheticConfig, generate_sequence
from torchslam.errors import ConfigError
from torchslam.kcc import (
    KCCConfig, choose_resolution, frame_taper, keyframe_filter, keyframe_map, orthographic_project, rgbd_to_points, track_step,
)
from torchslam.systems.nislam import NISlamConfig

SIZE = (240, 320)


def test_taper_values():
    assert frame_taper(6, 8, 0) is None
    w = frame_taper(60, 80, 10, torch.float64)
    assert w.shape == (60, 80)
    # Inside the border band every weight is 1; the band rises as a raised cosine of the distance
    # from the border measured at pixel centres.
    assert torch.equal(w[10:50, 10:70], torch.ones(40, 60, dtype=torch.float64))
    for i in range(10):
        expect = 0.5 - 0.5 * math.cos(math.pi * (i + 0.5) / 10)
        assert w[i, 40].item() == pytest.approx(expect, abs=1e-12)
        assert w[59 - i, 40].item() == pytest.approx(expect, abs=1e-12)  # symmetric
        assert w[30, i].item() == pytest.approx(expect, abs=1e-12)
    assert w[0, 0].item() == pytest.approx(w[0, 40].item() * w[30, 0].item(), abs=1e-12)  # separable
    assert (w > 0).all()  # no pixel is dropped altogether
    assert frame_taper(60, 80, 10, torch.float32).dtype == torch.float32


def test_config():
    assert KCCConfig().frame_taper == 0  # the paper's correlator
    assert NISlamConfig().kcc.frame_taper == 24  # NI-SLAM's default
    with pytest.raises(ConfigError, match="frame_taper"):
        KCCConfig(frame_taper=-1)


def _scene(kind: str, seed: int):
    seq = generate_sequence(SyntheticConfig(frames=1, trajectory=kind, seed=seed, width=320, height=240))
    f = seq[0]
    return rgbd_to_points(f.rgb[None], f.depth[None], seq.camera.as_tensor(torch.float32)[None])


def _pull(points, grey, valid, taper: int) -> float:
    """Mean fraction of a prediction's error the match follows (negative: towards the window's centre).

    The content moved by a fixed translation; the frame's window is centred on a prediction
    8 px off in four directions, and each error is compared with the opposite prediction's, so a
    constant offset of the estimate cancels.
    """
    cfg = KCCConfig(ortho_height=SIZE[0], ortho_width=SIZE[1], depth_median_center=True, depth_statistic="median",
                    frame_taper=taper)
    r = choose_resolution(points, valid, SIZE, cfg.coverage, cfg.sample_step)
    km = keyframe_map(orthographic_project(points, grey, valid, None, r, SIZE))
    filt = keyframe_filter(km, cfg)
    truth = torch.tensor([0.05, -0.03])
    moved = points + torch.tensor([truth[0], truth[1], 0.0])

    def error(e: torch.Tensor) -> torch.Tensor:
        center = (truth - e.float() * r)[None]
        res = track_step(moved, grey, valid, torch.eye(3)[None], km, filt, r, cfg, center=center)
        return ((res.t_content[0, :2] - truth) / r).double()

    pulls = []
    for e in ((8.0, 0.0), (0.0, 8.0), (6.0, 6.0), (6.0, -6.0)):
        e = torch.tensor(e, dtype=torch.float64)
        pulls.append(float(((error(e) - error(-e)) / 2) @ e / e.square().sum()))
    return sum(pulls) / len(pulls)


@pytest.mark.parametrize("kind,seed", [("handheld", 0), ("translate", 1)])
def test_taper_weakens_the_pull_towards_the_prediction(kind, seed):
    # Both windows cut their content off at the same border; a prediction that errs puts the
    # frame's border where the keyframe's is only at the wrong shift, and the match leans
    # towards it. Tapering one side leaves no common border to line up.
    points, grey, valid = _scene(kind, seed)
    without, with_taper = _pull(points, grey, valid, 0), _pull(points, grey, valid, 24)
    assert without < -0.003  # the pull is there to remove
    assert abs(with_taper) < 0.6 * abs(without)


def test_taper_leaves_an_exact_prediction_exact():
    points, grey, valid = _scene("orbit", 3)
    cfg = KCCConfig(ortho_height=SIZE[0], ortho_width=SIZE[1], depth_median_center=True, depth_statistic="median",
                    frame_taper=24)
    r = choose_resolution(points, valid, SIZE, cfg.coverage, cfg.sample_step)
    km = keyframe_map(orthographic_project(points, grey, valid, None, r, SIZE))
    truth = torch.tensor([12.0, -5.0]) * r  # whole pixels
    moved = points + torch.tensor([truth[0], truth[1], 0.0])
    res = track_step(moved, grey, valid, torch.eye(3)[None], km, keyframe_filter(km, cfg), r, cfg, center=truth[None])
    assert res.index.abs().max().item() == 0
    torch.testing.assert_close(res.t_content[0, :2], truth, atol=0.05 * r.item(), rtol=0)


def test_frame_channels_are_tapered_and_keyframe_channels_not():
    # The one place that decides it: ``channels(..., frame=True)``, which the tracking step uses.
    from torchslam.kcc import correlator_for, kcc_channels

    points, grey, valid = _scene("orbit", 3)
    cfg = KCCConfig(ortho_height=SIZE[0], ortho_width=SIZE[1], frame_taper=24)
    r = choose_resolution(points, valid, SIZE, cfg.coverage, cfg.sample_step)
    images = orthographic_project(points, grey, valid, None, r, SIZE)
    plain = kcc_channels(images, KCCConfig(ortho_height=SIZE[0], ortho_width=SIZE[1]))
    w = frame_taper(SIZE[0], SIZE[1], 24, plain.dtype)
    assert torch.equal(kcc_channels(images, cfg), plain)
    torch.testing.assert_close(kcc_channels(images, cfg, frame=True), plain * w, rtol=0, atol=0)
    torch.testing.assert_close(correlator_for(cfg).channels(images, frame=True), plain * w, rtol=0, atol=0)
