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
