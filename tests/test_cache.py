"""The FIFO cache helper and the caches built on it: bounded, insertion-ordered, no device sync in a key."""

import pytest
import torch
from torch.overrides import TorchFunctionMode

from torchslam.cache import FifoCache, tensor_key
from torchslam.kcc import ortho


def test_fifo_cache_drops_the_oldest_inserted_entry():
    cache = FifoCache(2)
    cache.put("a", 1)
    cache.put("b", 2)
    assert cache.get("a") == 1  # a hit does not refresh the age
    cache.put("c", 3)
    assert "a" not in cache and cache.get("b") == 2 and cache.get("c") == 3 and len(cache) == 2
    cache.put("b", 20)  # replacing a key evicts nothing
    assert len(cache) == 2 and cache.get("b") == 20 and cache.get("c") == 3


def test_get_or_compute_computes_once_per_key():
    cache = FifoCache(3)
    calls = []

    def compute(v):
        calls.append(v)
        return v * 10

    assert [cache.get_or_compute(k, lambda k=k: compute(k)) for k in (1, 2, 1, 2, 3)] == [10, 20, 10, 20, 30]
    assert calls == [1, 2, 3]
    cache.clear()
    assert len(cache) == 0 and cache.get(1) is None


@pytest.mark.parametrize("size", [0, -1, 2.0, None])
def test_fifo_cache_needs_a_positive_size(size):
    with pytest.raises(ValueError, match="maxsize"):
        FifoCache(size)


def test_tensor_key_follows_identity_and_in_place_changes():
    t = torch.tensor([1.0, 2.0])
    key = tensor_key(t)
    assert tensor_key(t) == key
    assert tensor_key(t.clone()) != key
    t.add_(1.0)
    assert tensor_key(t) != key


class _HostReads(TorchFunctionMode):
    """Records the tensor methods that copy values to the host (a device sync on an accelerator)."""

    NAMES = {"cpu", "item", "tolist", "numpy", "__bool__", "__float__", "__int__", "__index__"}

    def __init__(self):
        super().__init__()
        self.calls: list[str] = []

    def __torch_function__(self, func, types, args=(), kwargs=None):
        name = getattr(func, "__name__", "")
        if name in self.NAMES:
            self.calls.append(name)
        return func(*args, **(kwargs or {}))


def test_ortho_ray_cache_lookup_reads_no_tensor_value(monkeypatch):
    ortho._RAYS.clear()
    intr = torch.tensor([[500.0, 510.0, 31.5, 23.5]])
    with _HostReads() as mode:
        first = ortho._pixel_rays(intr, 48, 64)
        again = ortho._pixel_rays(intr, 48, 64)
    assert mode.calls == []
    assert again[0] is first[0] and again[1] is first[1]
    # An in-place change of the intrinsics is seen (version bump), and the values follow it.
    intr[0, 0] = 250.0
    changed = ortho._pixel_rays(intr, 48, 64)
    assert changed[0] is not first[0]
    v, u = torch.meshgrid(torch.arange(48.0), torch.arange(64.0), indexing="ij")
    assert torch.equal(changed[0], ((u.reshape(1, -1) - 31.5) / 250.0))


def test_rgbd_to_points_reads_no_tensor_value_through_the_cache():
    ortho._RAYS.clear()
    intr = torch.tensor([[500.0, 510.0, 31.5, 23.5]])
    rgb, depth = torch.rand(1, 3, 48, 64), torch.rand(1, 1, 48, 64) + 0.5
    ref = ortho.rgbd_to_points(rgb, depth, intr)
    # A hit on the same tensor, and a miss on an equal one, give the same points.
    for k in (intr, intr.clone()):
        out = ortho.rgbd_to_points(rgb, depth, k)
        assert all(torch.equal(a, b) for a, b in zip(out, ref))
    with _HostReads() as mode:
        ortho._pixel_rays(intr, 48, 64)
    assert mode.calls == []


def test_fourier_tables_are_cached_per_size():
    from torchslam.kcc import correlator

    a = correlator._fourier_tables(8, 12, 0.5, torch.float64, "cpu")
    assert correlator._fourier_tables(8, 12, 0.5, torch.float64, "cpu") is a
    assert correlator._fourier_tables(8, 12, 0.25, torch.float64, "cpu") is not a


def test_node_rays_are_cached_per_rays_tensor_and_follow_in_place_changes():
    from torchslam.kcc import ortho

    H, W = 6, 8
    rays = torch.rand(H * W, 2, dtype=torch.float64)
    vn, un = torch.linspace(0, H - 1, 3, dtype=torch.float64), torch.linspace(0, W - 1, 4, dtype=torch.float64)
    a = ortho._node_rays(rays, torch.float64, H, W, vn, un)
    assert a.shape == (2, 3, 4) and ortho._node_rays(rays, torch.float64, H, W, vn, un) is a
    # the corner nodes are the corner pixels' rays
    assert torch.allclose(a[:, 0, 0], rays[0]) and torch.allclose(a[:, -1, -1], rays[-1])
    rays.mul_(2)  # a new version: recomputed
    b = ortho._node_rays(rays, torch.float64, H, W, vn, un)
    assert b is not a and torch.allclose(b, 2 * a)


def test_fifo_cache_stays_bounded_and_consistent_under_threads():
    """Frames are prepared on another thread beside tracking: concurrent insertions into one
    full cache never raise, never exceed the bound, and every stored value is its key's."""
    import threading

    cache = FifoCache(4)
    errors = []

    def hammer(offset: int) -> None:
        try:
            for i in range(5000):
                key = (offset + i) % 13
                assert cache.get_or_compute(key, lambda: key * 10) == key * 10
        except Exception as exc:  # noqa: BLE001 - collected for the assertion below
            errors.append(exc)

    threads = [threading.Thread(target=hammer, args=(k,)) for k in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert errors == [] and len(cache) <= 4
    assert all(cache.get(k) in (None, k * 10) for k in range(13))
