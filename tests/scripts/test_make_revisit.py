"""scripts/make_revisit.py: the there-and-back stand-in of a TUM folder."""

import pytest
import torch

from tests._helpers import load_script
from torchslam.data import TUMSequence
from torchslam.data.synthetic import SyntheticConfig, generate_sequence, write_tum_folder

revisit = load_script("make_revisit")


def test_order_goes_forward_back_forward_back_without_repeating_a_turn():
    assert revisit.revisit_order(3) == [0, 1, 2, 1, 0, 1, 2, 1, 0]
    assert revisit.revisit_order(2) == [0, 1, 0, 1, 0]
    with pytest.raises(ValueError, match="1 frame"):
        revisit.revisit_order(1)


def test_written_folder_reads_back_with_each_source_frame_and_its_pose(tmp_path):
    src = write_tum_folder(generate_sequence(SyntheticConfig(frames=4, width=64, height=48)), tmp_path / "seq")
    n = revisit.write_revisit(src, tmp_path / "out" / "seq_palindrome", fps=30.0)
    original, stand_in = TUMSequence(src), TUMSequence(tmp_path / "out" / "seq_palindrome")
    order = revisit.revisit_order(4)
    assert n == len(stand_in) == len(order) == 13
    assert torch.allclose(torch.diff(torch.as_tensor(stand_in.timestamps)), torch.full((12,), 1 / 30, dtype=torch.float64), atol=2e-6)
    for k in (0, 4, 7, 12):
        a, b = stand_in[k], original[order[k]]
        assert torch.equal(a.rgb, b.rgb) and torch.equal(a.depth, b.depth)
        assert torch.allclose(a.T_wc, b.T_wc, atol=1e-6)
    with pytest.raises(SystemExit, match="not empty"):
        revisit.write_revisit(src, tmp_path / "out" / "seq_palindrome")


@pytest.mark.parametrize("planted", [0.0, 0.03])
def test_the_stand_in_keeps_the_camera_and_declares_a_global_shutter(tmp_path, planted):
    # Half its frames play backward: a rolling-shutter model would double their distortion.
    src = write_tum_folder(generate_sequence(SyntheticConfig(frames=3, width=64, height=48, readout_time=planted)), tmp_path / "seq")
    original = TUMSequence(src)
    assert original.readout_time == planted
    revisit.write_revisit(src, tmp_path / "out" / "seq_palindrome")
    stand_in = TUMSequence(tmp_path / "out" / "seq_palindrome")
    assert stand_in.camera == original.camera and stand_in.depth_scale == original.depth_scale
    assert (stand_in.readout_time, stand_in.readout_source) == (0.0, "calibration.txt")


def test_a_preset_named_source_gets_its_preset_camera_written_out(tmp_path):
    folder = tmp_path / "tum_fr1_tiny"
    src = write_tum_folder(generate_sequence(SyntheticConfig(frames=3, width=640, height=480)), tmp_path / "seq")
    folder.mkdir()
    for name in ("rgb", "depth", "rgb.txt", "depth.txt", "groundtruth.txt"):
        (folder / name).symlink_to(src / name)
    original = TUMSequence(folder)  # no calibration.txt: the freiburg1 preset, distortion and all
    assert original.calibration_source == "preset:freiburg1" and original.readout_time == 0.03
    revisit.write_revisit(folder, tmp_path / "out" / "tum_fr1_tiny_palindrome")
    stand_in = TUMSequence(tmp_path / "out" / "tum_fr1_tiny_palindrome")
    assert stand_in.camera == original.camera and stand_in.depth_scale == original.depth_scale
    assert (stand_in.readout_time, stand_in.readout_source) == (0.0, "calibration.txt")
