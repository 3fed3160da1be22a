"""scripts/test.sh: a bad TORCHSLAM_TEST_WORKERS is refused before anything is set up."""

from __future__ import annotations

import os
import shutil
import subprocess

import pytest

from tests._helpers import REPO_ROOT


@pytest.mark.skipif(shutil.which("bash") is None, reason="needs bash")
@pytest.mark.parametrize("value", ["0", "abc", "-1", "2x", "1 2"])
def test_a_bad_worker_count_is_refused_before_setup(value, tmp_path):
    # A venv that does not exist: had the script gone on to its set-up, it would have said so
    # ("setup: ...") and started creating it.
    env = {**os.environ, "TORCHSLAM_TEST_WORKERS": value, "TORCHSLAM_VENV": str(tmp_path / "venv")}
    proc = subprocess.run(["bash", str(REPO_ROOT / "scripts" / "test.sh")], env=env, capture_output=True, text=True,
                          timeout=60, check=False)
    assert proc.returncode == 2, proc.stderr
    assert f"TORCHSLAM_TEST_WORKERS={value}: expected a whole number of workers, 1 or more" in proc.stderr
    assert "setup:" not in proc.stderr and not (tmp_path / "venv").exists()
