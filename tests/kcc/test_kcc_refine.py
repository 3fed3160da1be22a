"""``refine_against_map``: a cloud's full pose against a keyframe's orthographic map."""

from __future__ import annotations

import math

import pytest
import torch

from torchslam.data.synthetic import SyntheticConfig, generate_sequence
from torchslam.errors import ConfigError, ShapeError
from torchslam.geometry import se3_exp, se3_inverse, so3_exp, so3_log
from torchslam.kcc import KeyframeMap, MapRefineConfig, choose_resolution, keyframe_map, orthographic_project, refine_against_map, rgbd_to_points
from torchslam.kcc.refine import _Level, _pool

SIZE = (240, 320)


def _cloud(seq, i):
    f = seq[i]
    intr = seq.camera.as_tensor(torch.float32)[None]
    p, g, v = rgbd_to_points(f.rgb[None], f.depth[None], intr)
    return f, p, g, v


@pytest.fixture(scope="module")
def pair():
    """Two 320x240 frames of a synthetic hand-held pan 0.5 s apart: the second's cloud, the first's map, the true transform."""
    seq = generate_sequence(SyntheticConfig(frames=16, trajectory="handheld", seed=1, width=320, height=240, depth_noise=False))
    fa, pa, ga, va = _cloud(seq, 0)
    fb, pb, gb, vb = _cloud(seq, 15)
    r = choose_resolution(pa, va, SIZE)
    km = keyframe_map(orthographic_project(pa, ga, va, None, r, SIZE))
    T_ab = se3_inverse(fa.T_wc) @ fb.T_wc
    return pb, gb, vb, km, r, T_ab, (pa, ga, va)


def _perturbed(T: torch.Tensor, deg: float, cm: float, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    w = torch.randn(3, generator=g, dtype=torch.float64)
    t = torch.randn(3, generator=g, dtype=torch.float64)
    out = T.clone()
    out[:3, :3] = so3_exp(w / w.norm() * math.radians(deg)) @ T[:3, :3]
    out[:3, 3] += t / t.norm() * cm / 100
    return out


def _errors(T: torch.Tensor, T_true: torch.Tensor) -> tuple[float, float]:
    E = se3_inverse(T_true) @ T
    return math.degrees(float(so3_log(E[:3, :3]).norm())), 100 * float(E[:3, 3].norm())


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_planted_rotation_is_recovered(pair, seed):
    # The attitude's heading error at a loop is of this order (0.7 deg on the long synthetic run).
    pb, gb, vb, km, r, T_true, _ = pair
    T0 = _perturbed(T_true, 0.8, 1.0, seed)
    res = refine_against_map(pb, gb, vb, km, r, T0[None])
    rot, trans = _errors(res.T[0], T_true)
    assert bool(res.converged[0]) and int(res.count[0]) > 2000
    assert rot < 0.1 and trans < 0.3, (rot, trans)
    # The covariance is finite and positive, rotation standard deviations well under a degree.
    sd = res.covariance[0].diagonal().sqrt()
    assert bool((sd > 0).all()) and math.degrees(float(sd[3:].max())) < 0.2


def test_the_cloud_against_its_own_map_stays_put(pair):
    _, _, _, km, r, _, (pa, ga, va) = pair
    eye = torch.eye(4, dtype=torch.float64)[None]
    res = refine_against_map(pa, ga, va, km, r, eye)
    rot, trans = _errors(res.T[0], eye[0])
    # The map holds each point at its pixel's centre: a fraction of a pixel (r ~ 5 mm) remains.
    assert bool(res.converged[0]) and rot < 0.02 and trans < 0.1, (rot, trans)


def test_batch_rows_match_single_calls(pair):
    pb, gb, vb, km, r, T_true, _ = pair
    T0 = torch.stack([_perturbed(T_true, 0.8, 1.0, s) for s in (3, 4)])
    two = KeyframeMap(*(x.expand(2, *x.shape[1:]) for x in (km.grey, km.depth, km.weight)))
    both = refine_against_map(pb.expand(2, -1, -1), gb.expand(2, -1), vb.expand(2, -1), two, r.expand(2), T0)
    for b in range(2):
        one = refine_against_map(pb, gb, vb, km, r, T0[b : b + 1])
        torch.testing.assert_close(both.T[b], one.T[0], atol=1e-6, rtol=0)
        assert int(both.count[b]) == int(one.count[0])


def test_jacobian_matches_autograd(pair):
    # The analytic rows [a, q x a] against float64 autograd through the same bilinear map.
    pb, gb, vb, km, r, T_true, _ = pair
    cfg = MapRefineConfig()
    f64 = torch.float64
    fields, ok = _pool(torch.stack([km.depth, km.grey], dim=1).to(f64), km.valid, 1)
    p = pb[:, ::50].to(f64)
    lv = _Level(fields, ok, r.to(f64)[:, None], p, gb[:, ::50].to(f64), vb[:, ::50], cfg)
    T = _perturbed(T_true, 0.3, 0.5, 5)[None]
    r_d, r_g, n, m, q, use = lv.residuals(T)

    def residuals(delta):
        rd, rg, *_ = lv.residuals(se3_exp(delta)[None] @ T)
        return torch.cat([rd[0], rg[0]])

    J = torch.autograd.functional.jacobian(residuals, torch.zeros(6, dtype=f64))
    rows = torch.cat([torch.cat([a, torch.cross(q, a, dim=-1)], dim=-1)[0] for a in (n, m)])
    keep = torch.cat([use[0], use[0]])
    # Only the grey/depth gradients the sampler reports where it is smooth (use), and in the
    # interior of a bilinear cell (at a cell border the two sides' derivatives differ).
    assert int(keep.sum()) > 100
    torch.testing.assert_close(J[keep], rows[keep], atol=1e-6, rtol=1e-6)


def test_an_empty_map_does_not_converge(pair):
    pb, gb, vb, km, r, T_true, _ = pair
    empty = KeyframeMap(torch.zeros_like(km.grey), torch.zeros_like(km.depth), torch.zeros_like(km.weight))
    res = refine_against_map(pb, gb, vb, empty, r, T_true[None])
    assert not bool(res.converged[0]) and int(res.count[0]) == 0
    torch.testing.assert_close(res.T[0], T_true)


def test_bad_arguments_name_themselves(pair):
    pb, gb, vb, km, r, T_true, _ = pair
    with pytest.raises(ShapeError, match="T_init"):
        refine_against_map(pb, gb, vb, km, r, T_true)
    with pytest.raises(ConfigError, match="levels"):
        MapRefineConfig(levels=0)
    with pytest.raises(ConfigError, match="divisible"):
        refine_against_map(pb, gb, vb, km, r, T_true[None], MapRefineConfig(levels=8))
