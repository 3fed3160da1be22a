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
