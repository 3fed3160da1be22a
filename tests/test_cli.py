import json
import subprocess
import sys

import pytest
import torch

from torchslam.cli import main
from torchslam.data import Trajectory, TUMSequence, read_tum_trajectory, write_tum_trajectory
from torchslam.geometry import se3_exp


def _perturbed_copy(gt: Trajectory, seed: int = 0) -> Trajectory:
    g = torch.Generator().manual_seed(seed)
    T = se3_exp(torch.randn(6, generator=g, dtype=torch.float64))
    noise = se3_exp(0.01 * torch.randn(len(gt), 6, generator=g, dtype=torch.float64))
    return Trajectory(gt.timestamps, T @ gt.T_wc @ noise)


def test_eval_json_matches_evo(shared_data, tmp_path, capsys):
    from evo.core import metrics
    from evo.tools import file_interface

    gt_path = shared_data / "tum_fr1_xyz" / "groundtruth.txt"
    est_path = tmp_path / "est.txt"
    write_tum_trajectory(est_path, _perturbed_copy(read_tum_trajectory(gt_path)))
    assert main(["eval", "--est", str(est_path), "--gt", str(gt_path), "--json"]) == 0
    ours = json.loads(capsys.readouterr().out)
    ref = file_interface.read_tum_trajectory_file(str(gt_path))
    est = file_interface.read_tum_trajectory_file(str(est_path))
    est.align(ref, correct_scale=False)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, est))
    # The written file rounds to 1e-9 m, far below the tolerance.
    assert ours["ate_rmse_m"] == pytest.approx(ape.get_statistic(metrics.StatisticsType.rmse), abs=1e-6)
    assert ours["align"] == "se3" and ours["matched"] == len(ref.timestamps)


def test_eval_table_and_bad_file(shared_data, tmp_path, capsys):
    gt_path = shared_data / "tum_fr1_xyz" / "groundtruth.txt"
    assert main(["eval", "--est", str(gt_path), "--gt", str(gt_path)]) == 0
    out = capsys.readouterr().out
    assert "| ATE | se3 | 0.000000" in out
    bad = tmp_path / "bad.txt"
    bad.write_text("# header\n1.0 0 0 0 0 0 0 1\n2.0 0 0 nan 0 0 0 1\n")
    assert main(["eval", "--est", str(bad), "--gt", str(gt_path)]) == 2
    assert f"{bad}:3: NaN or infinite value" in capsys.readouterr().err


def test_run_reports_unavailable_or_unknown_system(capsys):
    assert main(["run", "--system", "nope"]) == 2
    err = capsys.readouterr().err
    assert "unknown system" in err and "available systems" in err


def test_info_prints_sequence_summary(shared_data, capsys):
    assert main(["info", str(shared_data / "tum_fr1_xyz"), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["rgb_list_count"] == 210 and info["depth_list_count"] == 210
    assert info["frames"] == info["associated_count"] > 190
    assert info["intrinsics_source"] == "preset:freiburg1"
    assert main(["info", str(shared_data)]) == 2  # the parent folder is not a sequence
    assert "rgb.txt" in capsys.readouterr().err


def test_python_dash_m_is_the_same_entry_point():
    proc = subprocess.run([sys.executable, "-m", "torchslam", "--help"], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0
    for cmd in ("run", "eval", "info", "synth"):
        assert cmd in proc.stdout


def test_synth_writes_a_folder_that_info_and_run_read(tmp_path, capsys):
    out = tmp_path / "seq"
    assert main(["synth", "--out", str(out), "--frames", "4", "--width", "160", "--height", "120", "--trajectory", "translate"]) == 0
    assert "wrote 4 frames" in capsys.readouterr().out
    assert main(["info", str(out), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["frames"] == 4 and info["intrinsics_source"].startswith("calibration.txt")
    assert main(["synth", "--out", str(tmp_path / "x"), "--trajectory", "spiral"]) == 2
    assert "trajectory" in capsys.readouterr().err


def test_synth_set_reaches_every_generator_setting(tmp_path, capsys):
    small = ["--frames", "2", "--width", "160", "--height", "120", "--trajectory", "loop", "--no-noise"]
    sharp, blurred = tmp_path / "sharp", tmp_path / "blurred"
    assert main(["synth", "--out", str(sharp), *small, "--set", "period=3.4"]) == 0
    assert main(["synth", "--out", str(blurred), *small, "--set", "period=3.4", "--set", "exposure=0.02"]) == 0
    a, b = (TUMSequence(p)[1].rgb for p in (sharp, blurred))
    assert (a - b).abs().mean() > 0.01  # blurred
    assert main(["synth", "--out", str(tmp_path / "x"), *small, "--set", "exposur=0.02"]) == 2
    assert "exposur: unknown key" in capsys.readouterr().err


# ------------------------------------------------------------------ parser, help examples, pipes

def _help_texts() -> dict[str, str]:
    import argparse

    from torchslam.cli import build_parser

    parser = build_parser()
    texts = {"torchslam": parser.format_help()}
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                texts[f"torchslam {name}"] = sub.format_help()
    return texts


def _set_examples(text: str) -> list[str]:
    """Every ``--set KEY=VALUE`` example in ``text``; ``a|b`` alternatives expanded, placeholders left out."""
    import re

    found = []
    for key, value in re.findall(r"--set[ =]+([A-Za-z_][\w.]*)=([^\s`'\"]+)", text.replace("\\|", "|")):
        value = value.rstrip(",.;:)]")
        for alternative in value.split("|"):
            if key.lower() == "key" or re.fullmatch(r"[A-Z]+|<.*>|\{.*\}", alternative):
                continue  # a placeholder, not an example
            found.append(f"{key}={alternative}")
    return found


def _resolves_for_some_system(example: str, where: str = "") -> bool:
    from torchslam.errors import ConfigError
    from torchslam.systems.registry import available_systems
    from torchslam.app.run import resolve_config

    if where == "torchslam synth":  # its --set keys are the generator's own (SyntheticConfig)
        from torchslam.config import config_from_dict, parse_overrides
        from torchslam.data import SyntheticConfig

        try:
            config_from_dict(SyntheticConfig, parse_overrides([example]), source="test")
        except ConfigError:
            return False
        return True
    for system in available_systems():
        try:
            resolve_config(system, None, [example])
        except ConfigError:
            continue
        return True
    return False


def test_every_set_example_in_the_help_texts_readme_and_docs_resolves():
    from tests._helpers import REPO_ROOT

    sources = dict(_help_texts())
    sources["README.md"] = (REPO_ROOT / "README.md").read_text()
    for path in sorted((REPO_ROOT / "docs").rglob("*.md")):
        sources[str(path.relative_to(REPO_ROOT))] = path.read_text()
    for path in sorted(REPO_ROOT.glob("configs/*.yaml")) + sorted((REPO_ROOT / "torchslam").rglob("*.yaml")):
        sources[str(path.relative_to(REPO_ROOT))] = path.read_text()
    examples = {(where, ex) for where, text in sources.items() for ex in _set_examples(text)}
    assert any(where == "torchslam run" for where, _ in examples), "torchslam run --help shows no --set example"
    wrong = sorted((where, ex) for where, ex in examples if not _resolves_for_some_system(ex, where))
    assert not wrong, f"--set examples that no system's config accepts: {wrong}"


def test_set_example_checker_rejects_a_wrong_key():
    assert _set_examples("e.g. --set sigma=0.3 or --set attitude=imu|groundtruth, --set key=value") == [
        "sigma=0.3", "attitude=imu", "attitude=groundtruth"]
    assert not _resolves_for_some_system("sigma=0.3")
    assert _resolves_for_some_system("kcc.sigma=0.3")


def test_no_parser_takes_abbreviations():
    import argparse

    from torchslam.cli import build_parser

    parser = build_parser()
    parsers = [parser]
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            parsers += list(action.choices.values())
    assert len(parsers) == 8 and all(p.allow_abbrev is False for p in parsers)


@pytest.mark.parametrize(
    "argv, prog, wrong",
    [
        (["run", "--sytem", "gcslam"], "torchslam run", "--sytem gcslam"),
        (["run", "--max-frame", "3"], "torchslam run", "--max-frame 3"),
        (["batch", "synthetic", "--out", "x", "--batch-siz", "2"], "torchslam batch", "--batch-siz 2"),
        (["eval", "--est", "a", "--gt", "b", "--alig", "none"], "torchslam eval", "--alig none"),
        (["synth", "--out", "x", "--frame", "3"], "torchslam synth", "--frame 3"),
    ],
)
def test_a_mistyped_option_prints_the_subcommands_usage(tmp_path, monkeypatch, capsys, argv, prog, wrong):
    monkeypatch.chdir(tmp_path)  # nothing may be written, but if it were, not into the checkout
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith(f"usage: {prog} ") and f"{prog}: error: unrecognized arguments: {wrong}" in err


def test_verbose_counts_and_full_options_still_parse():
    from torchslam.cli import build_parser

    args = build_parser().parse_args(["-vv", "run", "--max-frames", "3", "--system", "gcslam"])
    assert args.verbose == 2 and args.max_frames == 3 and args.system == "gcslam"


@pytest.mark.parametrize("value", ["0", "-3"])
def test_run_refuses_a_frame_limit_below_one_as_batch_does(tmp_path, capsys, value):
    out = tmp_path / "run"
    # A data folder that does not exist: the frame limit is refused before anything is read.
    assert main(["run", "--data", str(tmp_path / "absent"), "--out", str(out), "--max-frames", value]) == 2
    run_err = capsys.readouterr().err.strip().splitlines()[-1]
    assert run_err == f"torchslam run: error: --max-frames: expected an integer >= 1, got {value}"
    assert main(["batch", "synthetic", "--out", str(tmp_path / "b"), "--max-frames", value]) == 2
    assert capsys.readouterr().err.strip().splitlines()[-1] == run_err.replace("torchslam run", "torchslam batch")
    assert not out.exists()


@pytest.mark.parametrize("command", ["info", "eval"])
def test_a_reader_that_closes_the_pipe_early_ends_quietly(shared_data, command):
    import os

    from tests._helpers import REPO_ROOT

    seq = shared_data / "tum_fr1_xyz"
    argv = {"info": ["info", str(seq)], "eval": ["eval", "--est", str(seq / "groundtruth.txt"), "--gt", str(seq / "groundtruth.txt")]}
    env = {**os.environ, "PYTHONPATH": str(REPO_ROOT), "OMP_NUM_THREADS": "1"}
    proc = subprocess.Popen([sys.executable, "-m", "torchslam", *argv[command]], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, env=env)
    proc.stdout.close()  # the reader is gone before the first line is written (torch takes seconds to import)
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=120) == 141, err
    assert "Traceback" not in err and "BrokenPipeError" not in err and "Exception ignored" not in err, err



def test_synth_refuses_a_non_empty_folder_and_overwrite_replaces_only_its_own(tmp_path, capsys):
    small = ["--width", "64", "--height", "48", "--trajectory", "translate"]
    out = tmp_path / "seq"
    assert main(["synth", "--out", str(out), "--frames", "6", *small]) == 0
    assert len(list((out / "rgb").glob("*.png"))) == 6
    assert main(["synth", "--out", str(out), "--frames", "3", *small]) == 2
    assert "not empty" in capsys.readouterr().err and len(list((out / "rgb").glob("*.png"))) == 6
    # --overwrite clears the old sequence first: no stale images beside the new lists.
    assert main(["synth", "--out", str(out), "--frames", "3", "--overwrite", *small]) == 0
    capsys.readouterr()
    for kind in ("rgb", "depth"):
        listed = {ln.split()[1] for ln in (out / f"{kind}.txt").read_text().splitlines() if not ln.startswith("#")}
        assert {f"{kind}/{p.name}" for p in (out / kind).iterdir()} == listed and len(listed) == 3
    # A folder holding anything else, or a look-alike torchslam did not write, is never cleared.
    (out / "notes.txt").write_text("mine\n")
    assert main(["synth", "--out", str(out), "--overwrite", *small]) == 2
    assert "notes.txt" in capsys.readouterr().err and (out / "notes.txt").is_file() and (out / "rgb.txt").is_file()
    (out / "notes.txt").unlink()
    (out / "calibration.txt").write_text("517.3 516.5 318.6 255.3 5000 64 48\n")
    assert main(["synth", "--out", str(out), "--overwrite", *small]) == 2
    assert "calibration.txt was not written by torchslam synth" in capsys.readouterr().err
    assert len(list((out / "rgb").glob("*.png"))) == 3
    empty = tmp_path / "empty"
    empty.mkdir()
    assert main(["synth", "--out", str(empty), "--frames", "2", *small]) == 0
    (tmp_path / "file").write_text("x")
    assert main(["synth", "--out", str(tmp_path / "file"), "--frames", "2", *small]) == 2
    assert "is not a folder" in capsys.readouterr().err


def test_a_bare_torchslam_with_top_level_options_runs_the_default_job(monkeypatch):
    import torchslam.cli as cli

    seen = []
    monkeypatch.setitem(cli.COMMANDS, "run", lambda args: seen.append(args) or 0)
    assert main(["-v"]) == 0 and main([]) == 0
    assert [(a.command, a.verbose, a.system, a.max_frames) for a in seen] == [("run", 1, "nislam", None), ("run", 0, "nislam", None)]


def test_eval_help_states_every_default(capsys):
    with pytest.raises(SystemExit):
        main(["eval", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    for default in ("default se3", "default 0.01, evo's --t_max_diff and the headline's", "nearest: evo's",
                    "(default, the headline's)", "(default 0)", "RPE step (default 1)", "(default frames)", "(default: table)"):
        assert default in text, default


def test_eval_by_default_reproduces_the_run_headline(shared_data, tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["run", "--data", str(shared_data / "tum_fr1_xyz"), "--max-frames", "15", "--out", str(out),
                 "--no-progress", "--no-tensorboard"]) == 0
    capsys.readouterr()
    m = json.loads((out / "metrics.json").read_text())
    gt = shared_data / "tum_fr1_xyz" / "groundtruth.txt"
    assert main(["eval", "--est", str(out / "trajectory.txt"), "--gt", str(gt), "--json"]) == 0
    ours = json.loads(capsys.readouterr().out)
    assert ours["ate_rmse_m"] == m["ate_rmse_m"] and ours["matched"] == m["matched"] == 15
    assert ours["ate_association"] == "nearest" and ours["ate_association_max_dt_s"] == 0.01
