"""GC-SLAM on the simulated device (``diagnostics.device_audit``): no device tensor meets a host tensor, same trajectory."""

from __future__ import annotations

import pytest
import torch

from torchslam.config import config_from_dict
from torchslam.data.synthetic import SyntheticConfig, generate_sequence
from torchslam.diagnostics import DEVICE, device_audit
from torchslam.systems.gcslam import GCSlam, GCSlamConfig


def _run(seq, cfg, device):
    s = GCSlam(cfg, device=device)
    s.start(seq)
    for f in seq:
        s.track(f)
    return s.finish()


@pytest.mark.parametrize("frontend", ["sparse", "dense"])
def test_gcslam_keeps_device_and_host_apart(frontend):
    seq = generate_sequence(SyntheticConfig(frames=10, trajectory="orbit", seed=3, height=120, width=160))
    cfg = config_from_dict(GCSlamConfig, {"frontend": frontend})
    with device_audit() as audit:
        out = _run(seq, cfg, DEVICE)
    assert audit.mixed == [], audit.mixed[:5]
    ref = _run(seq, cfg, "cpu")
    torch.testing.assert_close(out.T_wc.as_subclass(torch.Tensor), ref.T_wc, atol=1e-5, rtol=0)


def test_prepared_frames_and_registrations_live_on_the_device():
    import dataclasses

    from torchslam.diagnostics import is_on_device

    seq = generate_sequence(SyntheticConfig(frames=3, trajectory="orbit", seed=4, height=120, width=160))
    f0, f1 = seq[0], seq[1]
    for frontend in ("sparse", "dense"):
        cfg = config_from_dict(GCSlamConfig, {"frontend": frontend})
        with device_audit() as audit:
            s = GCSlam(cfg, device=DEVICE)
            s.start(seq)
            fe = s.frontend
            a = fe.prepare(f0.rgb.to(DEVICE), f0.depth.to(DEVICE), True, lambda stage: None)
            b = fe.prepare(f1.rgb.to(DEVICE), f1.depth.to(DEVICE), True, lambda stage: None)
            target = type("Target", (), {"features": a.features, "dense": a.dense, "depth": a.depth})()
            reg = fe.register(target, b, torch.eye(4, dtype=torch.float64, device=DEVICE))
        assert audit.mixed == []
        assert is_on_device(a.features.points) and is_on_device(a.features.valid)
        if frontend == "dense":
            for level in a.dense.levels:
                tensors = [getattr(level, f.name) for f in dataclasses.fields(level) if isinstance(getattr(level, f.name), torch.Tensor)]
                assert tensors and all(is_on_device(t) for t in tensors)
        assert reg.ok and is_on_device(reg.T_kf)
