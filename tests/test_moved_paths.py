"""The old ``torchslam.slam`` paths still import, as the very modules they moved to, and warn."""

import importlib
import sys
import warnings

import pytest

MOVED = {
    "torchslam.slam.base": "torchslam.systems.base",
    "torchslam.slam.registry": "torchslam.systems.registry",
    "torchslam.slam.lockstep": "torchslam.systems.lockstep",
    "torchslam.slam.monitor": "torchslam.systems.monitor",
    "torchslam.slam.memory": "torchslam.systems.memory",
    "torchslam.slam.nislam": "torchslam.systems.nislam",
    "torchslam.slam.gcslam": "torchslam.systems.gcslam",
    "torchslam.slam.run": "torchslam.app.run",
    "torchslam.slam.outputs": "torchslam.app.outputs",
    "torchslam.slam.progress": "torchslam.app.progress",
    "torchslam.slam.report": "torchslam.app.report",
    "torchslam.slam.runfolder": "torchslam.app.runfolder",
    "torchslam.slam.batch": "torchslam.app.batch",
    "torchslam.slam.time_offset": "torchslam.app.calibrate_time",
}


@pytest.mark.parametrize("old, new", sorted(MOVED.items()))
def test_old_path_is_the_new_module_and_warns(old, new, monkeypatch):
    for name in [n for n in sys.modules if n == "torchslam.slam" or n.startswith("torchslam.slam.")]:
        monkeypatch.delitem(sys.modules, name)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        module = importlib.import_module(old)
    assert module is importlib.import_module(new)
    messages = [str(w.message) for w in caught if issubclass(w.category, FutureWarning)]
    assert any(f"{old} moved to {new}" in m for m in messages), messages


def test_readme_names_of_the_old_package_still_work():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FutureWarning)
        from torchslam.slam import run_sequence
        from torchslam.slam.nislam import NISlam, NISlamConfig
    from torchslam.systems import run_sequence as new_run
    from torchslam.systems.nislam import NISlam as new_nislam

    assert run_sequence is new_run and NISlam is new_nislam and NISlamConfig().kcc is not None
