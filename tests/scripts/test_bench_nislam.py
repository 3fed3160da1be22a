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
