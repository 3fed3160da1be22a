"""The host-device synchronisation counter: planted synchronisations are counted once each."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchslam.diagnostics import SyncKind, count_syncs


@pytest.fixture
def x() -> torch.Tensor:
    return torch.randn(7, generator=torch.Generator().manual_seed(0), dtype=torch.float64)


@pytest.mark.parametrize("k", [0, 1, 3, 10])
def test_k_item_calls_count_k(x, k):
    with count_syncs() as syncs:
        for i in range(k):
            x[i % 7].item()
    assert syncs.count == k
    assert all(e.op == "Tensor.item" and e.kind == SyncKind.SCALAR for e in syncs.events)
    # the location is this test's line, not torch's internals
    assert all(e.where.startswith("tests/diagnostics/test_syncs.py:") for e in syncs.events)


def test_pure_tensor_region_counts_zero(x):
    m = x > 0
    with count_syncs() as syncs:
        y = torch.where(m, x, 0.0).cumsum(0)
        y = y[torch.arange(3)] + x.new_zeros(3) + torch.full((3,), 2.0, dtype=x.dtype)
        L, info = torch.linalg.cholesky_ex(torch.eye(3, dtype=x.dtype) * y.abs().max())
        z = x.to(x.device).to(torch.float32).repeat_interleave(2)
        x.clone()[m] = 0.0  # masked_fill on CUDA: no synchronisation
        w = torch.tensor([1.0, 2.0])  # host data kept on the host
        a = (L.sum() + z.sum() + w.sum()).requires_grad_()
        (a * 2).backward()
    assert syncs.count == 0, syncs.summary()


@pytest.mark.parametrize(
    "name, fn, op",
    [
        ("bool", lambda x: bool((x > 0).any()), "Tensor.__bool__"),
        ("if", lambda x: 1 if (x > 0).any() else 0, "Tensor.__bool__"),
        ("int", lambda x: int(x.argmax()), "Tensor.__int__"),
        ("float", lambda x: float(x.sum()), "Tensor.__float__"),
        ("index", lambda x: list(range(x.argmax())), "Tensor.__index__"),
        ("tolist", lambda x: x.tolist(), "Tensor.tolist"),
        ("cpu", lambda x: x.cpu(), "Tensor.cpu"),
        ("to cpu", lambda x: x.to("cpu"), "Tensor.to"),
        ("numpy", lambda x: x.numpy(), "Tensor.numpy"),
        ("array", lambda x: np.asarray(x), "Tensor.__array__"),
        ("format", lambda x: f"{x.sum():.3f}", "Tensor.__format__"),
        ("new_tensor", lambda x: x.new_tensor([1.0, 2.0]), "Tensor.new_tensor"),
        ("as_tensor", lambda x: torch.as_tensor(np.zeros(2), device=x.device), "torch.as_tensor"),
        ("tensor", lambda x: torch.tensor([1, 2], device=x.device), "torch.tensor"),
        ("nonzero", lambda x: (x > 0).nonzero(), "aten.nonzero.default"),
        ("where1", lambda x: torch.where(x > 0), "aten.nonzero.default (in torch.where)"),
        ("argwhere", lambda x: torch.argwhere(x > 0), "aten.nonzero.default"),
        ("unique", lambda x: torch.unique(x), "aten._unique2.default"),
        ("masked_select", lambda x: torch.masked_select(x, x > 0), "aten.masked_select.default"),
        ("bool index", lambda x: x[x > 0], "aten.index.Tensor"),
        ("bool index put", lambda x: x.clone().__setitem__(x == x, 2 * x), "aten.index_put_.default"),
        ("repeat_interleave", lambda x: torch.repeat_interleave(torch.ones(3, dtype=torch.int64)), "aten.repeat_interleave.Tensor"),
        ("bincount", lambda x: torch.bincount(torch.ones(3, dtype=torch.int64)), "aten.bincount.default"),
        ("cholesky check", lambda x: torch.linalg.cholesky(torch.eye(2, dtype=x.dtype)), "aten._linalg_check_errors.default"),
        ("0-dim as int", lambda x: torch.arange(torch.ones((), dtype=torch.int64) * 3), "aten._local_scalar_dense.default"),
    ],
)
def test_each_synchronising_op_counts_once(x, name, fn, op):
    with count_syncs() as syncs:
        fn(x)
    assert syncs.count == 1 and syncs.events[0].op.startswith(op), syncs.summary()


def test_boolean_mask_indexing_counts_and_integer_indexing_does_not(x):
    m = x > 0
    idx = torch.arange(3)
    with count_syncs() as syncs:
        x[idx]
        x[:, None][idx, 0]
    assert syncs.count == 0
    with count_syncs() as syncs:
        x[m]
        x[:, None][m, 0]
    assert syncs.count == 2 and {e.kind for e in syncs.events} == {SyncKind.SHAPE}


def test_nested_regions_count_their_own(x):
    with count_syncs() as outer:
        x.sum().item()
        with count_syncs() as inner:
            x.max().item()
            x[x > 0]
        bool(x.any())
    assert inner.count == 2
    assert outer.count == 4
    assert [e.op for e in outer.events][1:3] == [e.op for e in inner.events]
    # the modes are gone afterwards: nothing is recorded outside the region
    x.sum().item()
    assert outer.count == 4


def test_report_summary_names_call_sites(x):
    with count_syncs() as syncs:
        for _ in range(3):
            x.sum().item()
        x.tolist()
    assert len(syncs) == 4
    (op, where), n = syncs.by_location().most_common(1)[0]
    assert (op, n) == ("Tensor.item", 3) and "test_syncs.py" in where
    text = syncs.summary()
    assert text.startswith("4 synchronisation(s)") and "3 x Tensor.item" in text


def test_counter_leaves_results_unchanged(x):
    with count_syncs():
        y = (x[x > 0] ** 2).sum()
    assert torch.equal(y, (x[x > 0] ** 2).sum())


def test_exception_inside_region_restores_modes(x):
    with pytest.raises(RuntimeError):
        with count_syncs() as syncs:
            x.item()  # not a one-element tensor
    assert syncs.count == 1
    with count_syncs() as after:
        x.sum()
    assert after.count == 0


def test_host_copy_and_its_read_count_once(x):
    with count_syncs() as syncs:
        x.cpu().numpy()
        np.asarray(x.detach().cpu())
        x.to("cpu").tolist()
    assert [e.op for e in syncs.events] == ["Tensor.cpu", "Tensor.cpu", "Tensor.to"]
    with count_syncs() as syncs:
        y = x.cpu()
        x.sum()
        y.numpy()  # not right after the copy: the counter pairs a read only with the call before
    assert syncs.count == 2
