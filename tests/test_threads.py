"""The intra-op thread setting: precedence, validation, what it applies and what runs record."""

import json
from pathlib import Path

import cv2
import pytest
import torch

from torchslam.cli import main
from torchslam.errors import ConfigError
from torchslam.app.batch import BatchOptions, run_batch
from torchslam.app.run import RunOptions, run
from torchslam.threads import (
    POLICY_THREADS, THREADS_ENV, ThreadSetting, available_cpus, parse_threads, resolve_threads, setup_threads,
)

SMALL = ["data.synthetic.frames=4", "data.synthetic.width=160", "data.synthetic.height=120",
         "kcc.ortho_height=90", "kcc.ortho_width=120", "min_valid_points=100"]
SMALL_ARGS = [a for kv in SMALL for a in ("--set", kv)]


@pytest.fixture
def restore_opencv_threads():
    threads = cv2.getNumThreads()
    yield
    cv2.setNumThreads(threads)


def test_flag_wins_over_variable_which_wins_over_policy():
    assert resolve_threads(3, {THREADS_ENV: "2"}, cpus=8) == ThreadSetting(3, "flag", 3)
    assert resolve_threads("4", {}, cpus=8) == ThreadSetting(4, "flag", 4)
    assert resolve_threads(None, {THREADS_ENV: "2"}, cpus=8) == ThreadSetting(2, "env", 2)
    assert resolve_threads(None, {THREADS_ENV: " 5 "}, cpus=8) == ThreadSetting(5, "env", 5)
    # The policy: one PyTorch thread (OpenMP spins under load), OpenCV on every core (it does not).
    assert resolve_threads(None, {}, cpus=8) == ThreadSetting(POLICY_THREADS, "policy", 8)
    assert resolve_threads(None, {THREADS_ENV: ""}, cpus=2) == ThreadSetting(POLICY_THREADS, "policy", 2)
    assert resolve_threads(None, {}, cpus=0) == ThreadSetting(POLICY_THREADS, "policy", 1)
    assert resolve_threads(None, {}).opencv_threads == available_cpus() >= 1
    assert POLICY_THREADS == 1
    assert ThreadSetting(2, "env", 2).to_dict() == {"threads": 2, "threads_source": "env", "opencv_threads": 2}


@pytest.mark.parametrize("value", [0, -1, "0", "x", "1.5", 1.5, True, "", "2 threads"])
def test_a_bad_flag_names_the_flag(value):
    with pytest.raises(ConfigError, match=r"^--threads: expected a whole number of threads >= 1"):
        resolve_threads(value, {})


@pytest.mark.parametrize("value", ["0", "-3", "two", "1.5", "1e2", "\u00b2"])
def test_a_bad_variable_names_the_variable_even_under_a_flag(value):
    with pytest.raises(ConfigError, match=rf"^{THREADS_ENV}: expected a whole number of threads >= 1, got '{value}'"):
        resolve_threads(None, {THREADS_ENV: value})
    with pytest.raises(ConfigError, match=rf"^{THREADS_ENV}:"):
        resolve_threads(2, {THREADS_ENV: value})
    assert parse_threads("+7", "x") == 7


def test_setup_sets_torch_and_opencv_pools(restore_opencv_threads):
    assert setup_threads(2, {}) == ThreadSetting(2, "flag", 2)
    assert torch.get_num_threads() == 2 and cv2.getNumThreads() == 2
    assert setup_threads(None, {THREADS_ENV: "3"}) == ThreadSetting(3, "env", 3)
    assert torch.get_num_threads() == 3 and cv2.getNumThreads() == 3
    assert setup_threads(None, {}, cpus=2) == ThreadSetting(1, "policy", 2)
    assert torch.get_num_threads() == 1 and cv2.getNumThreads() == 2
    assert setup_threads(1, {}) == ThreadSetting(1, "flag", 1)
    # OpenCV's sequential mode (setNumThreads(0)) reports one thread.
    assert torch.get_num_threads() == 1 and cv2.getNumThreads() == 1


def test_run_records_the_setting_in_metrics(tmp_path, monkeypatch, restore_opencv_threads):
    # Runs use one thread: two collapse on the loaded machines tests run on (the point of the policy).
    monkeypatch.setenv(THREADS_ENV, "1")
    torch.set_num_threads(3)
    m = run(RunOptions(system="nislam", data="synthetic", out=tmp_path / "env", tensorboard=False), overrides=SMALL)
    assert (m["threads"], m["threads_source"], m["environment"]["torch_threads"]) == (1, "env", 1)
    on_disk = json.loads((tmp_path / "env" / "metrics.json").read_text())
    assert (on_disk["threads"], on_disk["threads_source"]) == (1, "env")
    monkeypatch.delenv(THREADS_ENV)
    torch.set_num_threads(3)
    m = run(RunOptions(system="nislam", data="synthetic", out=tmp_path / "policy", tensorboard=False), overrides=SMALL)
    assert (m["threads"], m["threads_source"], m["environment"]["torch_threads"]) == (POLICY_THREADS, "policy", POLICY_THREADS)
    assert m["opencv_threads"] == available_cpus()


def test_batch_records_the_setting_in_runs_and_summary(tmp_path, restore_opencv_threads):
    out = tmp_path / "b"
    torch.set_num_threads(3)
    run_batch(BatchOptions(system="nislam", sources=("synthetic",), out=out, tensorboard=False, threads=1), overrides=SMALL)
    summary = json.loads((out / "summary.json").read_text())
    assert (summary["environment"]["threads"], summary["environment"]["threads_source"]) == (1, "flag")
    assert summary["environment"]["torch_threads"] == 1
    metrics = json.loads((out / summary["rows"][0]["name"] / "metrics.json").read_text())
    assert (metrics["threads"], metrics["threads_source"]) == (1, "flag")


@pytest.mark.parametrize("command", [["run"], ["batch", "synthetic"], ["calibrate-time"]])
def test_cli_refuses_bad_counts_before_any_work(command, tmp_path, monkeypatch, capsys):
    out = ["--out", str(tmp_path / "o")] if command[0] != "calibrate-time" else []
    assert main([*command, *out, "--threads", "0"]) == 2
    assert "--threads: expected a whole number of threads >= 1, got 0" in capsys.readouterr().err
    monkeypatch.setenv(THREADS_ENV, "many")
    assert main([*command, *out]) == 2
    assert f"{THREADS_ENV}: expected a whole number of threads >= 1, got 'many'" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_cli_flag_reaches_the_run(tmp_path, monkeypatch, capsys, restore_opencv_threads):
    monkeypatch.setenv(THREADS_ENV, "3")
    out = tmp_path / "r"
    assert main(["run", "--out", str(out), "--no-progress", "--no-tensorboard", "--threads", "1", *SMALL_ARGS]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert (metrics["threads"], metrics["threads_source"]) == (1, "flag")


def test_synth_takes_the_variable_too(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv(THREADS_ENV, "0")
    assert main(["synth", "--out", str(tmp_path / "s"), "--frames", "2"]) == 2
    assert f"{THREADS_ENV}: expected a whole number of threads >= 1, got '0'" in capsys.readouterr().err
    assert not (tmp_path / "s").exists()


@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="needs Linux's /proc")
def test_name_os_thread_names_the_calling_thread_only():
    import threading

    from torchslam.threads import name_os_thread

    seen = {}

    def work():
        seen["set"] = name_os_thread("tslam-a-very-long-name")
        seen["comm"] = Path(f"/proc/self/task/{threading.get_native_id()}/comm").read_text().strip()

    before = Path(f"/proc/self/task/{threading.get_native_id()}/comm").read_text()
    t = threading.Thread(target=work)
    t.start()
    t.join()
    assert seen == {"set": True, "comm": "tslam-a-very-lo"}  # cut to the kernel's 15 bytes
    assert Path(f"/proc/self/task/{threading.get_native_id()}/comm").read_text() == before  # this thread kept its name


def test_name_os_thread_reports_failure(monkeypatch):
    import builtins

    from torchslam.threads import name_os_thread

    def refuse(*a, **k):
        raise PermissionError("read-only /proc")

    monkeypatch.setattr(builtins, "open", refuse)
    assert name_os_thread("x") is False
