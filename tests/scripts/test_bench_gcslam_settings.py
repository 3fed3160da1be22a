"""scripts/bench_gcslam_settings.py: its cases, its table and one real run of a short synthetic case."""

from pathlib import Path

from tests._helpers import load_script

bench = load_script("bench_gcslam_settings")


def test_cases_carry_their_split_and_follow_the_groups(tmp_path):
    (tmp_path / "hololens_dvmvs").mkdir()
    (tmp_path / "hololens_dvmvs" / "rgb.txt").write_text("")
    every = bench.cases(tmp_path, Path("/rev"), {"shipped", "there-and-back", "stride", "synthetic"})
    names = {c["name"]: c for c in every}
    assert names["hololens_dvmvs"]["split"] == "held-out" and names["hololens_dvmvs/3"]["sets"] == ["data.stride=3"]
    assert names["hololens_dvmvs-there-and-back"]["data"] == "/rev/hololens_dvmvs_palindrome"
    assert "tum_fr1_xyz" not in names  # not in the folder: skipped
    assert names["synthetic-loop-3"]["split"] == "tuning" and names["synthetic-loop-103"]["split"] == "held-out"
    only = bench.cases(tmp_path, None, {"synthetic"})
    assert len(only) == 10 and all(c["kind"] == "synthetic" for c in only)


def test_table_compares_the_last_setting_with_the_first():
    row = dict(name="x", split="tuning", runs={"sparse": {"a": {"ate_cm": 2.0}, "b": {"ate_cm": 1.5}},
                                              "dense": {"a": {"ate_cm": 1.0}, "b": {"error": "boom"}}})
    md = bench.table([row], ["a", "b"], ["sparse", "dense"])
    assert "| tuning | x | 2.000 → 1.500 (-25.0 %) | – → boom |" in md


def test_a_short_synthetic_case_runs_both_settings(tmp_path):
    case = dict(name="s", split="tuning", data="synthetic", kind="synthetic",
                sets=["data.synthetic.frames=6", "data.synthetic.width=160", "data.synthetic.height=120"])
    on = bench.run_case(case, "sparse", "default", tmp_path, 1)
    off = bench.run_case(case, "sparse", "spread_corrections=false+loops=false", tmp_path, 1)
    for res in (on, off):
        assert res.get("ate_cm") is not None and res["ate_cm"] < 5, res
        assert res["keyframes"] >= 1
    assert off["loops"] == 0
