"""What a plain install needs: presets inside the package, optional plotting and TensorBoard."""

import json
import logging
import sys
import tomllib

import pytest

from torchslam.cli import main
from torchslam.config import config_file, load_config, preset_names
from torchslam.errors import ConfigError
from torchslam.systems.nislam import NISlamConfig

from tests._helpers import REPO_ROOT

TINY = ["--data", "synthetic", "--no-progress", "--max-frames", "4",
        "--set", "data.synthetic.frames=6", "--set", "data.synthetic.width=160", "--set", "data.synthetic.height=120",
        "--set", "kcc.ortho_height=90", "--set", "kcc.ortho_width=120", "--set", "min_valid_points=100"]
RUN_FILES = ("trajectory.txt", "keyframes.txt", "map.ply", "metrics.json", "config.yaml")


def test_presets_ship_inside_the_package():
    import torchslam

    shipped = sorted(p.stem for p in (REPO_ROOT / "torchslam" / "presets").glob("*.yaml"))
    assert preset_names() == shipped and {"nislam", "gcslam", "nislam_fast", "nislam_faster"} <= set(shipped)
    for name in shipped:
        path = config_file(name)
        assert path.parent.parent == REPO_ROOT / "torchslam" == type(path)(torchslam.__file__).parent
        assert config_file(f"{name}.yaml") == path
    # The top-level configs/ is the same folder, for readers of the checkout.
    assert (REPO_ROOT / "configs" / "nislam_fast.yaml").read_text() == config_file("nislam_fast").read_text()


def test_package_data_declares_the_presets():
    project = tomllib.loads((REPO_ROOT / "pyproject.toml").read_text())
    assert "presets/*.yaml" in project["tool"]["setuptools"]["package-data"]["torchslam"]
    deps = project["project"]["dependencies"]
    names = [d.split(">")[0].split("=")[0].split("<")[0] for d in deps]
    assert len(names) == len(set(names)), "a runtime dependency is listed twice"
    # What run, batch and report import at run time is a runtime dependency.
    for needed in ("torch", "numpy", "scipy", "kornia", "opencv-python-headless", "pyyaml", "tqdm", "tensorboard", "matplotlib"):
        assert needed in names, needed


def test_config_file_prefers_an_existing_path_and_names_the_presets(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "nislam_fast").write_text("pixel_stride: 3\n")
    assert config_file("nislam_fast").resolve() == (tmp_path / "nislam_fast").resolve()
    with pytest.raises(ConfigError, match=r"--config nislam_fastest: no such file, and not a preset \(presets: gcslam, nislam, nislam_accurate, nislam_fast"):
        config_file("nislam_fastest")


def test_preset_by_name_is_the_file(tmp_path):
    assert load_config(NISlamConfig, config_file("nislam_fast")).pixel_stride == 2
    out = tmp_path / "run"
    assert main(["run", "--out", str(out), "--config", "nislam_fast", *TINY]) == 0
    resolved = (out / "config.yaml").read_text()
    assert "pixel_stride: 2" in resolved


def test_run_help_lists_the_presets(capsys):
    with pytest.raises(SystemExit):
        main(["run", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "nislam_fast" in text and "nislam_faster" in text and "gcslam" in text


def test_run_without_matplotlib_or_tensorboard_keeps_every_result(tmp_path, monkeypatch, caplog):
    """A missing TensorBoard install costs one warning, never the run; a run needs no matplotlib."""
    for name in ("matplotlib", "matplotlib.figure", "matplotlib.backends.backend_agg", "torch.utils.tensorboard"):
        monkeypatch.setitem(sys.modules, name, None)  # `import name` now raises ImportError
    out = tmp_path / "run"
    with caplog.at_level(logging.WARNING, logger="torchslam"):
        assert main(["run", "--out", str(out), *TINY]) == 0
    for f in RUN_FILES:
        assert (out / f).stat().st_size > 0, f
    assert json.loads((out / "metrics.json").read_text())["tracked_frames"] == 4
    assert not list(out.glob("events.out.tfevents.*"))
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert sum("install tensorboard" in w for w in warnings) == 1, warnings
    assert not any("matplotlib" in w for w in warnings), warnings


def test_run_without_matplotlib_logs_its_top_view(tmp_path, monkeypatch, caplog):
    # The top view a run logs to TensorBoard is drawn with OpenCV (matplotlib's import cost each
    # run's end about 0.5 s); only the report's figures need matplotlib.
    pytest.importorskip("tensorboard")
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    for name in ("matplotlib", "matplotlib.figure", "matplotlib.backends.backend_agg"):
        monkeypatch.setitem(sys.modules, name, None)
    out = tmp_path / "run"
    with caplog.at_level(logging.WARNING, logger="torchslam"):
        assert main(["run", "--out", str(out), *TINY]) == 0
    for f in RUN_FILES:
        assert (out / f).stat().st_size > 0, f
    assert list(out.glob("events.out.tfevents.*"))
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert not any("matplotlib" in w for w in warnings), warnings
    events = EventAccumulator(str(out), size_guidance={"images": 0})
    events.Reload()
    assert "trajectory/top_view" in events.Tags()["images"]
