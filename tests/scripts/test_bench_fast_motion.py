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
