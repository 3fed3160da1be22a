"""scripts/bench_fast_motion.py: its command line (the runs themselves need the real sequences)."""

import pytest

from tests._helpers import load_script

bench = load_script("bench_fast_motion")


def test_strides_are_parsed_per_sequence_in_order():
    assert bench._strides(["hololens_dvmvs=1,2", "tum_fr1_xyz=6"]) == [
        ("hololens_dvmvs", 1), ("hololens_dvmvs", 2), ("tum_fr1_xyz", 6)
    ]


@pytest.mark.parametrize("item, says", [("tum_fr1_xyz", "SEQUENCE=N"), ("tum_fr1_xyz=two", "integers")])
def test_bad_strides_name_the_item(item, says):
    with pytest.raises(SystemExit, match=says):
        bench._strides([item])


def test_unknown_system_is_refused_by_name():
    with pytest.raises(SystemExit, match="orbslam"):
        bench.system_by_name("orbslam")


def test_blur_cases_and_their_split():
    assert bench._blur_cases(["7:0.02", "107:0"]) == [(7, 0.02), (107, 0.0)]
    assert [bench._seed_split(s) for s in (7, 99, 100, 107)] == ["tuning", "tuning", "held-out", "held-out"]
    assert [bench._real_split(n) for n in ("hololens_dvmvs", "tum_fr1_xyz", "7scenes_redkitchen")] == ["held-out", "tuning", "tuning"]


@pytest.mark.parametrize("item", ["7", "seven:0.02", "7:-0.01"])
def test_bad_blur_cases_name_the_item(item):
    with pytest.raises(SystemExit, match="SEED:EXPOSURE"):
        bench._blur_cases([item])
