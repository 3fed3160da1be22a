"""Memory estimate of a configuration and the refusal before anything runs."""

import resource
import time

import pytest

from torchslam.cli import main
from torchslam.config import config_from_dict
from torchslam.data.synthetic import SyntheticConfig, generate_sequence
from torchslam.geometry import PinholeCamera
from torchslam.systems.base import run_sequence
from torchslam.systems.gcslam import GCSlam, GCSlamConfig
from torchslam.systems.lockstep import run_lockstep
from torchslam.systems.memory import (
    BYTES_PER_IMAGE_PIXEL,
    DENSE_BYTES_PER_WORKING_PIXEL,
    DENSE_PAIR_BYTES_PER_WORKING_PIXEL,
    NISLAM_BYTES_PER_ORTHO_PIXEL,
    InsufficientMemoryError,
    check_memory,
    device_memory,
    estimate_memory,
)
from torchslam.systems.nislam import NISlam, NISlamConfig

CAM = PinholeCamera(517.3, 516.5, 318.6, 255.3, 640, 480)
HUGE = {"kcc": {"ortho_height": 100000, "ortho_width": 100000}}


def test_estimate_counts_pixels_batch_and_pyramid():
    ni = estimate_memory(NISlamConfig(), CAM)
    assert ni.parts == {"input images": BYTES_PER_IMAGE_PIXEL * 640 * 480, "orthographic images": NISLAM_BYTES_PER_ORTHO_PIXEL * 360 * 480}
    assert estimate_memory(NISlamConfig(), CAM, batch=4).total == 4 * ni.total
    dense = estimate_memory(config_from_dict(GCSlamConfig, {"frontend": "dense"}), CAM)
    assert dense.parts["dense pyramid"] == DENSE_BYTES_PER_WORKING_PIXEL * 320 * 240  # 640x480 halved
    sparse = estimate_memory(GCSlamConfig(), CAM)
    assert "dense pyramid" not in sparse.parts
    # Densely registered pose-graph pairs (both front-ends' default) add the optimiser's pyramids.
    assert sparse.parts["dense keyframe pairs"] == dense.parts["dense keyframe pairs"] == DENSE_PAIR_BYTES_PER_WORKING_PIXEL * 320 * 240
    for frontend in ("sparse", "dense"):
        assert "dense keyframe pairs" not in estimate_memory(GCSlamConfig(frontend=frontend, keyframe_pairs="sparse"), CAM).parts
    # The default configurations need a fraction of a gigabyte.
    assert ni.total < 0.3e9 and dense.total < 0.4e9 and sparse.total < 0.3e9


def test_huge_orthographic_image_is_refused_with_the_figure():
    cfg = config_from_dict(NISlamConfig, HUGE)
    with pytest.raises(InsufficientMemoryError, match=r"needs ~3,680 GB of memory \(orthographic images ~3,680 GB.*100000 x 100000\), but cpu has 16 GB"):
        check_memory(cfg, CAM, "cpu", available=16 * 10**9)
    assert check_memory(NISlamConfig(), CAM, "cpu", available=16 * 10**9).total == estimate_memory(NISlamConfig(), CAM).total
    assert device_memory("cpu") is None or device_memory("cpu") > 10**8


class _Untouchable:
    """A sequence whose frames must never be read."""

    camera = CAM
    name = "untouchable"

    def __len__(self):
        return 10

    def __iter__(self):
        raise AssertionError("frames were read before the memory check")


def test_run_refuses_before_reading_a_frame_or_allocating():
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t0 = time.perf_counter()
    with pytest.raises(InsufficientMemoryError, match="needs ~"):
        run_sequence(NISlam(config_from_dict(NISlamConfig, HUGE)), _Untouchable())
    with pytest.raises(InsufficientMemoryError, match="needs ~"):
        run_lockstep(config_from_dict(NISlamConfig, HUGE), [_Untouchable(), _Untouchable()])
    big = PinholeCamera(5e4, 5e4, 5e4, 5e4, 100000, 100000)
    seq = _Untouchable()
    seq.camera = big
    with pytest.raises(InsufficientMemoryError, match=r"dense pyramid"):
        run_sequence(GCSlam(config_from_dict(GCSlamConfig, {"frontend": "dense", "threaded": False})), seq)
    assert time.perf_counter() - t0 < 5.0
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - rss0 < 200_000  # KiB: nothing near the estimate


def test_cli_refuses_huge_orthographic_image(tmp_path, capsys):
    out = tmp_path / "run"
    args = ["run", "--system", "nislam", "--data", "synthetic", "--out", str(out)]
    assert main([*args, "--set", "kcc.ortho_height=100000", "--set", "kcc.ortho_width=100000"]) == 2
    err = capsys.readouterr().err
    assert "needs ~3,680 GB" in err and err.count("\n") == 1
    assert not out.exists()


def test_ordinary_run_passes_the_check():
    seq = generate_sequence(SyntheticConfig(frames=2, width=64, height=48))
    cfg = config_from_dict(NISlamConfig, {"min_valid_points": 10, "kcc": {"ortho_height": 32, "ortho_width": 48}})
    assert run_sequence(NISlam(cfg), seq).frames_processed == 2
