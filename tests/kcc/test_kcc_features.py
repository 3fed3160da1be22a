"""Learned KCC channels (``kcc.features=learned``): the network, its loading, and the correlator with it."""

from __future__ import annotations

import dataclasses

import pytest
import torch
from torch.func import functional_call

from torchslam.errors import ConfigError, DataFormatError
from torchslam.kcc import (
    PACKAGED_WEIGHTS,
    FeatureKind,
    KCCConfig,
    KCCFeatureNet,
    KernelCorrelator,
    OrthoImages,
    correlator_for,
    kcc_channels,
    kcc_features,
    kcc_features_masked,
    kcc_predict,
    kcc_response,
    kcc_train,
    keyframe_filter,
    load_feature_net,
    peak_to_sidelobe,
    soft_argmax,
)
from torchslam.learn import PairWeightNet, learnable, save_checkpoint
from torchslam.systems.nislam import NISlamConfig

from tests._helpers import seeded


def _images(B=2, H=24, W=32, seed=0, dtype=torch.float32, holes=0.3):
    gen = seeded(seed)
    grey = torch.rand(B, H, W, generator=gen, dtype=torch.float64)
    depth = 1.0 + torch.rand(B, H, W, generator=gen, dtype=torch.float64)
    valid = torch.rand(B, H, W, generator=gen, dtype=torch.float64) > holes
    valid[:, :, :3] = False  # a band no window reaches across: it stays a hole
    return grey.to(dtype), depth.to(dtype), valid


def _random_net(seed=0, learned=2, hidden=8, weight=1.0):
    torch.manual_seed(seed)
    net = KCCFeatureNet(learned, hidden, initial_weight=weight)
    return net


def test_channels_pass_through_handcrafted_and_keep_the_energy_per_element():
    grey, depth, valid = _images()
    net = _random_net(weight=0.7)
    with torch.no_grad():
        x = net(grey, depth, valid)
        w = net.channel_weights()
    h, m = kcc_features_masked(grey, depth, valid)
    assert x.shape == (2, net.channels, 24, 32) and net.channels == 4
    assert float(w.sum()) == pytest.approx(net.channels, rel=1e-6)
    torch.testing.assert_close(x[:, :2], h * w[:2].sqrt()[:, None, None], rtol=1e-6, atol=1e-6)
    torch.testing.assert_close(h, kcc_features(grey, depth, valid), rtol=0, atol=0)
    # every channel standardised over the mask: mean energy per element = the mask's fraction,
    # the same as the hand-crafted channels' (the kernel's sigma keeps its meaning)
    frac = m.flatten(1).mean(1)
    energy = x.square().flatten(1).sum(1) / x[0].numel()
    torch.testing.assert_close(energy, frac, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(h.square().flatten(1).sum(1) / h[0].numel(), frac, rtol=1e-5, atol=1e-6)
    # holes that stay holes are 0 in every channel
    assert torch.all(x[:, :, :, :2] == 0) and torch.all(m[:, :, :, :2] == 0)


def test_initial_weights_start_near_the_handcrafted_channels():
    net = KCCFeatureNet(learned=2, hidden=8, initial_weight=0.1)
    torch.testing.assert_close(net.channel_weights(), torch.tensor([1.9, 1.9, 0.1, 0.1]), rtol=1e-5, atol=1e-6)
    assert sum(p.numel() for p in net.parameters()) < 50_000


def test_batched_channels_equal_per_item_and_float64_matches_float32():
    grey, depth, valid = _images(B=3, seed=1)
    net = _random_net(seed=1)
    with torch.no_grad():
        x = net(grey, depth, valid)
        for i in range(3):
            one = net(grey[i : i + 1], depth[i : i + 1], valid[i : i + 1])
            torch.testing.assert_close(x[i : i + 1], one, rtol=1e-4, atol=1e-5)
        x64 = net(grey.double(), depth.double(), valid)
    assert x64.dtype == torch.float64
    torch.testing.assert_close(x64.float(), x, rtol=1e-4, atol=1e-4)


def test_planted_circular_shift_is_recovered_with_learned_channels():
    """Convolutions commute with shifts away from the border: a rolled keyframe is found at its shift."""
    gen = seeded(3)
    H, W = 48, 64
    # smooth random content (a few low frequencies), valid everywhere but a margin
    base = torch.nn.functional.avg_pool2d(torch.rand(1, 1, H, W, generator=gen, dtype=torch.float64), 5, 1, 2)[0]
    depth = 1.0 + torch.nn.functional.avg_pool2d(torch.rand(1, 1, H, W, generator=gen, dtype=torch.float64), 7, 1, 3)[0]
    valid = torch.zeros(1, H, W, dtype=torch.bool)
    valid[:, 8:-8, 8:-8] = True
    grey, depth = base * valid, depth * valid
    net = _random_net(seed=4, weight=1.0).double()
    s = (3, -2)  # content moves by (s_x, s_y)
    fr = (torch.roll(grey, (s[1], s[0]), (-2, -1)), torch.roll(depth, (s[1], s[0]), (-2, -1)),
          torch.roll(valid, (s[1], s[0]), (-2, -1)))
    with torch.no_grad():
        z = net(grey, depth, valid)
        x = net(*fr)
        pred = kcc_predict(x, kcc_train(z, 0.2, 0.1), 0.2, torch.tensor([0.01], dtype=torch.float64))
    torch.testing.assert_close(pred.shift[0], torch.tensor([3.0, -2.0], dtype=torch.float64), atol=0.05, rtol=0)


def test_gradcheck_through_network_and_correlator_float64():
    grey, depth, valid = _images(B=1, H=6, W=7, seed=5, dtype=torch.float64, holes=0.2)
    net = _random_net(seed=5, learned=1, hidden=2, weight=0.8).double()
    names = [n for n, _ in net.named_parameters()]
    params = tuple(p.detach().clone().requires_grad_() for _, p in net.named_parameters())
    fr = (torch.roll(grey, 1, -1), torch.roll(depth, 1, -1), torch.roll(valid, 1, -1))

    def chain(*ps):
        state = dict(zip(names, ps))
        z = functional_call(net, state, (grey, depth, valid))
        x = functional_call(net, state, fr)
        g = kcc_response(x, kcc_train(z, 0.5, 0.1), 0.5)
        return soft_argmax(g, 0.05), peak_to_sidelobe(g, window=3)

    assert torch.autograd.gradcheck(chain, params, eps=1e-6, atol=1e-5)


def test_correlator_holds_the_network_and_rejects_mismatches(tmp_path):
    net = _random_net(seed=2)
    ckpt = save_checkpoint(tmp_path / "feat.pt", net, {"architecture": net.architecture()})
    cfg = KCCConfig(features="learned", features_weights=str(ckpt))
    assert cfg.features is FeatureKind.LEARNED
    corr = correlator_for(cfg)
    assert isinstance(corr.features, KCCFeatureNet)
    grey, depth, valid = _images(seed=2)
    img = OrthoImages(grey, depth, valid, torch.ones(2), torch.zeros(2, 2))
    with torch.no_grad():
        expected = net(grey, depth, valid)
        torch.testing.assert_close(corr.channels(img), expected, rtol=0, atol=0)
        torch.testing.assert_close(kcc_channels(img, cfg), expected, rtol=0, atol=0)
        filt = keyframe_filter(img, corr)
    assert filt.z_hat.shape[1] == 4  # the filter is trained on the four channels
    # the hand-crafted default is unchanged
    torch.testing.assert_close(kcc_channels(img, KCCConfig()), kcc_features(grey, depth, valid), rtol=0, atol=0)
    with pytest.raises(ConfigError, match="no network was given"):
        KernelCorrelator(cfg)
    with pytest.raises(ConfigError, match="cfg.features is 'handcrafted'"):
        KernelCorrelator(KCCConfig(), features=net)
    with pytest.raises(ConfigError, match="features: 'deep' is not one of"):
        KCCConfig(features="deep")
    # the network follows the correlator to a device (the stand-in device in tests/diagnostics)
    assert corr.to(torch.float64).features.conv1.weight.dtype == torch.float64


def test_load_feature_net_errors_name_the_file(tmp_path):
    with pytest.raises(DataFormatError, match=r"missing\.pt: no such checkpoint file"):
        load_feature_net(tmp_path / "missing.pt")
    cfg_ckpt = save_checkpoint(tmp_path / "values.pt", learnable(NISlamConfig(), ["kcc.sigma"]))
    with pytest.raises(DataFormatError, match=r"values\.pt: holds config values, not the learned KCC channels"):
        load_feature_net(cfg_ckpt)
    other = save_checkpoint(tmp_path / "pairnet.pt", PairWeightNet())
    with pytest.raises(DataFormatError, match=r"pairnet\.pt: holds the weights of a PairWeightNet"):
        load_feature_net(other)
    wrong = save_checkpoint(tmp_path / "wrong.pt", _random_net(hidden=8), {"architecture": {"learned": 2, "hidden": 4}})
    with pytest.raises(DataFormatError, match=r"wrong\.pt: the weights do not fit KCCFeatureNet"):
        load_feature_net(wrong)
    bad_arch = save_checkpoint(tmp_path / "arch.pt", _random_net(), {"architecture": {"layers": 3}})
    with pytest.raises(DataFormatError, match=r"arch\.pt: architecture"):
        load_feature_net(bad_arch)
    # a rewritten file is read again, not served from the cache
    path = tmp_path / "again.pt"
    save_checkpoint(path, _random_net(seed=7), {"architecture": {"learned": 2, "hidden": 8}})
    a = load_feature_net(path)
    save_checkpoint(path, _random_net(seed=8, hidden=4), {"architecture": {"learned": 2, "hidden": 4}})
    b = load_feature_net(path)
    assert a.hidden == 8 and b.hidden == 4


def test_packaged_weights_are_small_and_load():
    if not PACKAGED_WEIGHTS.is_file():
        pytest.fail(f"{PACKAGED_WEIGHTS}: the learned KCC channels' weights are not in the package")
    assert PACKAGED_WEIGHTS.stat().st_size < 1_000_000
    net = load_feature_net()
    assert net.channels <= 8 and sum(p.numel() for p in net.parameters()) <= 50_000
    corr = correlator_for(dataclasses.replace(NISlamConfig().kcc, features="learned"))
    assert corr.features is not None
