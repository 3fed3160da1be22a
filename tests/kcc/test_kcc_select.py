"""The speed helpers of the NI-SLAM front-end give the same bits as the plain forms they replace."""

import math

import pytest
import torch

from torchslam.geometry.camera import distort_normalized, distort_planes
from torchslam.kcc import rgbd_to_points
from torchslam.kcc._select import where
from torchslam.systems.batching import stack_rows as _stack_rows

from tests._helpers import seeded

_BITS = {torch.float32: torch.int32, torch.float64: torch.int64}


def _bits(t):
    return t.view(_BITS.get(t.dtype, t.dtype))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_where_matches_torch_where_bit_for_bit(dtype):
    g = seeded()
    a = torch.randn(3, 4, 5, dtype=dtype, generator=g)
    b = torch.randn(3, 4, 5, dtype=dtype, generator=g)
    a[0, 0, 0], a[0, 0, 1], a[0, 0, 2], b[1, 1, 1] = math.nan, math.inf, -0.0, -math.inf
    mask = torch.rand(3, 4, 5, generator=g) > 0.5
    for other in (b, b[0], torch.tensor(2.5, dtype=dtype), 0.0, -0.0, 1.0):
        assert torch.equal(_bits(where(mask, a, other)), _bits(torch.where(mask, a, other)))
    # broadcast mask, integer values
    assert torch.equal(_bits(where(mask[:, :1], a, 0.0)), _bits(torch.where(mask[:, :1], a, 0.0)))
    ints = torch.randint(-100, 100, (50,), generator=g, dtype=torch.int32)
    assert torch.equal(where(ints > 0, ints, 7), torch.where(ints > 0, ints, 7))


def test_where_keeps_gradients():
    a = torch.randn(6, generator=seeded(1), dtype=torch.float64, requires_grad=True)
    mask = torch.tensor([True, False, True, True, False, False])
    where(mask, a, 0.0).sum().backward()
    assert torch.equal(a.grad, mask.to(torch.float64))


def test_distort_planes_equals_distort_normalized():
    xy = torch.randn(2, 100, 2, generator=seeded(2)) * 0.4
    d = (0.262383, -0.953104, -0.005358, 0.002628, 1.163314)
    xd, yd = distort_planes(xy[..., 0].contiguous(), xy[..., 1].contiguous(), d)
    assert torch.equal(torch.stack([xd, yd], -1), distort_normalized(xy, d))


def test_rgbd_points_are_coordinate_planes_and_stack_without_copy():
    g = seeded(3)
    rgb = torch.rand(3, 3, 6, 8, generator=g)
    depth = torch.rand(3, 1, 6, 8, generator=g) + 0.5
    depth[0, 0, 0, 0], depth[1, 0, 1, 1], depth[2, 0, 2, 2] = 0.0, math.nan, math.inf
    points, _, valid = rgbd_to_points(rgb, depth, torch.tensor([5.0, 5.0, 4.0, 3.0]))
    assert points.shape == (3, 48, 3) and points.transpose(1, 2).is_contiguous()
    assert not bool(valid[0, 0]) and not bool(valid[1, 9]) and not bool(valid[2, 18])
    assert torch.equal(points[~valid], torch.zeros(3, 3))
    rows = [points[k : k + 1] for k in range(3)]
    stacked = _stack_rows(rows)
    assert torch.equal(stacked, points) and stacked.data_ptr() == points.data_ptr()
    assert torch.equal(_stack_rows([rows[0], rows[2]]), points[[0, 2]])
