"""Run-folder outputs: the voxel grid of map.ply."""

import torch

from torchslam.slam.outputs import voxel_downsample


def _reference(points, colors, voxel):
    """Row-wise unique over integer voxel coordinates, then per-voxel means (float64)."""
    key = torch.floor(points.double() / voxel).to(torch.int64)
    _, inv = torch.unique(key, dim=0, return_inverse=True)
    n = int(inv.max()) + 1
    cnt = torch.zeros(n, dtype=torch.float64).index_add_(0, inv, torch.ones(len(points), dtype=torch.float64))
    P = torch.zeros(n, 3, dtype=torch.float64).index_add_(0, inv, points.double()) / cnt[:, None]
    C = torch.zeros(n, 3, dtype=torch.float64).index_add_(0, inv, colors.double()) / cnt[:, None]
    return P.float(), C.float()


def test_voxel_downsample_equals_rowwise_unique_reference():
    g = torch.Generator().manual_seed(0)
    # Negative and positive coordinates, many points per voxel, and a far outlier.
    pts = torch.cat([torch.randn(20000, 3, generator=g, dtype=torch.float64) * 0.3 - 0.1,
                     torch.tensor([[250.0, -300.0, 7.0]], dtype=torch.float64)])
    cols = torch.rand(len(pts), 3, generator=g)
    for voxel in (0.01, 0.05):
        P, C = voxel_downsample(pts, cols, voxel)
        Pr, Cr = _reference(pts, cols, voxel)
        assert torch.equal(P, Pr) and torch.equal(C, Cr)
    P, C = voxel_downsample(pts, cols, 0.0)  # no downsampling
    assert torch.equal(P, pts.float()) and torch.equal(C, cols)
    # Spans too wide for one int64 key fall back to the row-wise unique.
    wide = torch.tensor([[0.0, 0.0, 0.0], [1e7, 1e7, 1e7], [1e7, 1e7, 1e7]], dtype=torch.float64)
    P, _ = voxel_downsample(wide, torch.zeros(3, 3), 1e-4)
    assert P.shape == (2, 3)
