"""``track_step``'s ``center``: the frame's orthographic image centred on a predicted translation."""

from __future__ import annotations

import pytest
import torch

from torchslam.data.synthetic import SyntheticConfig, generate_sequence
from torchslam.systems.batching import stack_dataclass
from torchslam.kcc import KCCConfig, choose_resolution, keyframe_filter, keyframe_map, orthographic_project, rgbd_to_points, track_step

SIZE = (240, 320)


@pytest.fixture(scope="module")
def scene():
    """A synthetic 320x240 frame's cloud, its keyframe map and filter (the cloud unmoved)."""
    seq = generate_sequence(SyntheticConfig(frames=1, trajectory="orbit", seed=3, width=320, height=240))
    f = seq[0]
    intr = seq.camera.as_tensor(torch.float32)[None]
    p, g, v = rgbd_to_points(f.rgb[None], f.depth[None], intr)
    cfg = KCCConfig(ortho_height=SIZE[0], ortho_width=SIZE[1], depth_median_center=True, depth_statistic="median")
    r = choose_resolution(p, v, SIZE, cfg.coverage, cfg.sample_step)
    km = keyframe_map(orthographic_project(p, g, v, None, r, SIZE))
    return p, g, v, r, km, keyframe_filter(km, cfg), cfg


def _step(scene, shift, center):
    p, g, v, r, km, filt, cfg = scene
    moved = p + torch.tensor([shift[0], shift[1], 0.0])  # the content moved, the camera's image window not
    c = None if center is None else torch.tensor([center], dtype=torch.float32)
    return track_step(moved, g, v, torch.eye(3)[None], km, filt, r, cfg, center=c)


def test_zero_center_is_the_optical_axis(scene):
    a, b = _step(scene, (0.03, -0.02), None), _step(scene, (0.03, -0.02), (0.0, 0.0))
    for name in ("t_content", "psr", "index", "response"):
        torch.testing.assert_close(getattr(a, name), getattr(b, name), rtol=0, atol=0)


def test_centre_on_a_whole_pixel_truth_leaves_no_shift_to_measure(scene):
    r = scene[3].item()
    truth = (12 * r, -5 * r)
    res = _step(scene, truth, truth)
    assert res.index.abs().max().item() == 0  # the centred image lies on the keyframe's
    torch.testing.assert_close(res.t_content[0, :2].double(), torch.tensor(truth, dtype=torch.float64), atol=1e-6, rtol=0)
    assert res.matched_fraction.item() > 0.8
    assert abs(res.t_content[0, 2].item()) < 1e-3


def test_centre_is_rounded_to_whole_pixels(scene):
    r = scene[3].item()
    truth = (6.3 * r, -4.2 * r)
    a, b = _step(scene, truth, (7.2 * r, -4.6 * r)), _step(scene, truth, (6.9 * r, -5.4 * r))  # both round to (7, -5)
    for name in ("t_content", "psr", "index", "response"):
        torch.testing.assert_close(getattr(a, name), getattr(b, name), rtol=0, atol=0)


def test_centre_removes_the_border_pull(scene):
    # The content moved (6.3, -4.2) and (24.3, 11.8) pixels: the same fraction of a pixel. On the
    # frame's own axis the image window stays while the content moves, the peak weakens with the
    # shift and the estimate differs; centred on a prediction 4 mm (half a pixel) off, the two
    # measure the same residual, equally well.
    r = scene[3].item()
    out = {}
    for px in ((6.3, -4.2), (24.3, 11.8)):
        truth = torch.tensor(px, dtype=torch.float64) * r
        for centred in (False, True):
            c = (truth + torch.tensor([0.004, -0.004], dtype=torch.float64)).tolist() if centred else None
            res = _step(scene, truth.tolist(), c)
            out[px, centred] = (res, (res.t_content[0, :2].double() - truth).norm().item())
    (near_c, e_near_c), (far_c, e_far_c) = out[(6.3, -4.2), True], out[(24.3, 11.8), True]
    (near_a, _), (far_a, _) = out[(6.3, -4.2), False], out[(24.3, 11.8), False]
    assert abs(e_near_c - e_far_c) < 1e-6 and e_far_c < 0.25 * r
    torch.testing.assert_close(near_c.psr, far_c.psr, rtol=1e-5, atol=0)
    assert near_a.psr.item() > 10 * far_a.psr.item()  # on its axis the far shift's peak fades
    assert far_c.psr.item() > 10 * far_a.psr.item()


def test_centre_is_per_item_of_a_batch(scene):
    p, g, v, r, km, filt, cfg = scene
    shifts = torch.tensor([[0.02, 0.01, 0.0], [-0.03, 0.02, 0.0]])
    moved = p.expand(2, -1, -1) + shifts[:, None]
    centers = shifts[:, :2] + torch.tensor([[0.002, 0.0], [0.0, -0.002]])
    two = lambda x: torch.cat([x, x])  # noqa: E731
    km2, f2 = stack_dataclass([km, km]), stack_dataclass([filt, filt])
    both = track_step(moved, g.expand(2, -1), v.expand(2, -1), torch.eye(3).expand(2, 3, 3), km2, f2, two(r), cfg, center=centers)
    for b in range(2):
        one = _step(scene, shifts[b, :2].tolist(), centers[b].tolist())
        torch.testing.assert_close(both.t_content[b], one.t_content[0], atol=1e-5, rtol=0)
