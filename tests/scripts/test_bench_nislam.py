"""scripts/bench_nislam.py: the settings it accepts."""

import sys

import pytest

from tests._helpers import load_script
from torchslam.config import config_from_dict
from torchslam.systems.nislam import NISlamConfig

# The benchmark imports make_revisit by the name it has beside it in scripts/.
sys.modules.setdefault("make_revisit", load_script("make_revisit"))
bench = load_script("bench_nislam")


def test_named_and_dotted_settings():
    assert bench.setting_values("default") == {}
    assert bench.setting_values("frame_taper=0") == {"kcc": {"frame_taper": 0}}
    got = bench.setting_values("pixel_stride=2+kcc.ortho_height=300+kcc.ortho_width=400+kcc.frame_taper=20")
    assert got == {"pixel_stride": 2, "kcc": {"ortho_height": 300, "ortho_width": 400, "frame_taper": 20}}
    cfg = config_from_dict(NISlamConfig, got)
    assert (cfg.pixel_stride, cfg.kcc.ortho_height, cfg.kcc.ortho_width, cfg.kcc.frame_taper) == (2, 300, 400, 20)
    assert cfg.kcc.sigma == NISlamConfig().kcc.sigma  # the rest stays the default's
    assert bench.setting_values("kcc.window=hann") == {"kcc": {"window": "hann"}}
    with pytest.raises(ValueError, match="'stride'.*neither"):
        bench.setting_values("pixel_stride=2+stride")


def test_groups_pick_the_splits(tmp_path):
    cases = bench._cases(tmp_path, ["default"], quick=True, groups=("held-out",))
    assert cases and {c[0] for c in cases} == {"held-out"}  # no real data here: the synthetic seeds
    assert {c[1] for c in cases} == {"synthetic-handheld-100"}


def test_only_filters_the_sequences_before_anything_runs(tmp_path):
    assert bench.accuracy(tmp_path, True, ["default"], groups=("tuning", "held-out"), only=("no-such-*",)) == []


def test_window_starts_cover_the_sequence_evenly():
    assert bench.window_starts(204, 120) == [0, 42, 84]
    assert bench.window_starts(300, 120) == [0, 60, 120, 180]
    assert bench.window_starts(120, 120) == [0]
    assert bench.window_starts(50, 120) == []  # shorter than a window: none
    for frames, length in ((204, 100), (300, 120), (813, 150), (1197, 200)):
        starts = bench.window_starts(frames, length)
        assert starts[0] == 0 and starts[-1] == frames - length  # first frame to last
        assert all(0 < b - a <= length // 2 for a, b in zip(starts, starts[1:]))  # no gap, no repeat
    with pytest.raises(ValueError, match="at least 2 frames"):
        bench.window_starts(100, 1)


def test_windows_are_cases_of_their_sequences_split(tmp_path):
    from tests._helpers import copy_tum_frames, data_root

    src = data_root() / "tum_fr1_xyz"
    if not (src / "rgb.txt").is_file():
        pytest.skip(f"{src}: the shipped fr1/xyz frames are not there (TORCHSLAM_DATA)")
    n = len(bench.TUMSequence(copy_tum_frames(src, tmp_path / "tum_fr1_xyz", 30)))  # frames that pair up
    cases = bench._cases(tmp_path, ["default"], quick=True, groups=("tuning",), windows=20)
    real = [(c[1], c[2], c[4]) for c in cases if not c[1].startswith("synthetic")]
    assert [name for name, att, _ in real if att == "groundtruth"] == ["tum_fr1_xyz", "tum_fr1_xyz@0", f"tum_fr1_xyz@{n - 20}"]
    window = [w for name, att, w in real if name == f"tum_fr1_xyz@{n - 20}"][0]
    assert (window.start, window.end) == (n - 20, n)
    assert len(bench.TUMSequence(window.folder, start=window.start, end=window.end)) == 20
