"""The simulated device of ``diagnostics.device_audit``: what it counts, what it marks, what it leaves alone."""

from __future__ import annotations

import torch

from torchslam.diagnostics import DEVICE, device_audit, is_on_device, on_device


def test_counts_each_read_back():
    with device_audit() as audit:
        x = torch.arange(6.0, device=DEVICE)
        for k in range(4):
            _ = (x * k).sum().item()
    assert len(audit.syncs) == 4
    assert {e.op for e in audit.syncs} == {"TensorBase.item"}


def test_pure_device_work_counts_nothing():
    with device_audit() as audit:
        x = torch.randn(4, 5, device=DEVICE)
        y = torch.fft.irfft2(torch.fft.rfft2(x), s=(4, 5))
        z = torch.where(y > 0, y, torch.zeros_like(y)).cumsum(1)
    assert is_on_device(z)
    assert audit.syncs == [] and audit.mixed == []
    torch.testing.assert_close(z.as_subclass(torch.Tensor), torch.where(y > 0, y, 0.0).cumsum(1).as_subclass(torch.Tensor))


def test_data_dependent_shapes_and_branches_count():
    with device_audit() as audit:
        x = torch.tensor([1.0, -2.0, 3.0], device=DEVICE)
        _ = x[x > 0]  # boolean-mask indexing
        _ = x.nonzero()
        _ = torch.unique(x)
        if x.sum() > 0:  # an if on a tensor
            pass
        _ = x.cpu()
        _ = x.to("cpu")
        _ = x.tolist()
    ops = [e.op for e in audit.syncs]
    assert len(ops) == 7, ops
    assert not is_on_device(x.cpu()) and not is_on_device(x.to("cpu"))


def test_host_data_is_not_counted():
    with device_audit() as audit:
        h = torch.arange(5.0)  # no device: host data, as on a CUDA run
        _ = h.sum().item(), h.tolist(), bool(h[0] == 0)
        d = h.to(DEVICE)
        _ = d * 2
    assert audit.syncs == []
    assert is_on_device(d) and not is_on_device(h)


def test_following_the_inputs_device_keeps_data_there():
    with device_audit() as audit:
        x = on_device(torch.ones(3))
        assert x.device == DEVICE
        buf = torch.zeros(3, device=x.device)
        y = x.new_zeros(2)
    assert is_on_device(buf) and is_on_device(y)
    assert audit.mixed == []


def test_device_and_host_tensors_together_are_a_mix():
    with device_audit() as audit:
        x = torch.ones(3, device=DEVICE)
        host = torch.ones(3)
        _ = x + host  # raises on CUDA
        _ = x * torch.tensor(2.0)  # a 0-dim host scalar is fine on CUDA
        _ = x[torch.tensor([0, 2])]  # host indices are fine
        x[torch.tensor([1])] = host[:1]  # so is assigning host values
    assert [e.op for e in audit.mixed] == ["TensorBase.add"]
    assert audit.mixed[0].where == "?"  # not torchslam code: no torchslam line to name


def test_names_the_torchslam_line():
    from torchslam.kcc.peak import peak_to_sidelobe

    with device_audit() as audit:
        g = torch.rand(1, 16, 16, device=DEVICE)
        peak_to_sidelobe(g, window=3)
    assert audit.mixed == []
    for e in audit.syncs:
        assert e.where.startswith("torchslam/") and ":" in e.where


def test_outside_an_audit_nothing_is_recorded_and_marks_are_inert():
    x = on_device(torch.arange(3.0))
    with device_audit() as audit:
        pass
    _ = x.sum().item()
    assert audit.syncs == []
    assert float(x.sum()) == 3.0


def test_inner_audit_records_alone():
    with device_audit() as outer:
        x = torch.ones(2, device=DEVICE)
        with device_audit() as inner:
            _ = x.sum().item()
        _ = x.tolist()
    assert len(inner.syncs) == 1 and len(outer.syncs) == 1
