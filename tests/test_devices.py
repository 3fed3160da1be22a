"""The host's NumPy stand-ins for torch's irregular operations give torch's results."""

from __future__ import annotations

import torch

from torchslam.devices import flat_nonzero, index_select, is_host, numpy_viewable, repeat_counts
from torchslam.diagnostics.device_audit import DEVICE, device_audit

from ._helpers import seeded


def test_index_select_matches_torch_on_rows_and_columns():
    g = seeded(0)
    idx = torch.randint(0, 7, (50,), generator=g)
    for x in (torch.randn(7, 3, generator=g, dtype=torch.float64), torch.randint(-2**62, 2**62, (7, 4), generator=g),
              torch.randn(7, generator=g)):
        assert torch.equal(index_select(x, 0, idx), x.index_select(0, idx))
    x = torch.randn(6, 7, generator=g)
    assert torch.equal(index_select(x, 1, idx), x.index_select(1, idx))
    assert torch.equal(index_select(x.t(), 0, idx), x.t().index_select(0, idx))  # strided input
    assert index_select(x, 1, idx[:0]).shape == (6, 0)


def test_repeat_counts_and_flat_nonzero_match_torch():
    g = seeded(1)
    values = torch.randint(-5, 100, (40,), generator=g)
    counts = torch.randint(0, 4, (40,), generator=g)
    assert torch.equal(repeat_counts(values, counts), torch.repeat_interleave(values, counts))
    mask = torch.rand(100, generator=g) < 0.3
    assert torch.equal(flat_nonzero(mask), mask.nonzero().squeeze(-1))
    assert flat_nonzero(torch.zeros(5, dtype=torch.bool)).dtype == torch.int64


def test_numpy_paths_only_for_plain_host_tensors():
    x = torch.zeros(3)
    assert is_host(x) and numpy_viewable(x)
    assert not numpy_viewable(torch.zeros(3, requires_grad=True))
    with device_audit() as audit:
        y = torch.arange(4, device=DEVICE)
        assert not is_host(y) and not numpy_viewable(y)
        picked = index_select(y, 0, torch.tensor([3, 0], device=DEVICE))
        assert not audit.syncs and not audit.mixed  # torch's operation, queued on the device
    assert picked.tolist() == [3, 0]
