"""``torchslam.errors.broadcast_shape`` and what it spares a run: importing SymPy."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from torchslam.errors import ShapeError, broadcast_shape


def test_broadcast_shape_agrees_with_torch_on_random_shapes():
    # torch.broadcast_shapes is what it replaces (this process may import SymPy; a run may not).
    import torch

    rng = np.random.default_rng(0)
    checked = 0
    for _ in range(2000):
        shapes = [tuple(int(d) for d in rng.choice([0, 1, 1, 2, 3], size=rng.integers(0, 5))) for _ in range(rng.integers(1, 4))]
        try:
            want = tuple(torch.broadcast_shapes(*shapes))
        except RuntimeError:
            with pytest.raises(ShapeError):
                broadcast_shape(*shapes)
            continue
        assert broadcast_shape(*shapes) == want
        checked += 1
    assert checked > 500  # both branches ran


def test_broadcast_shape_edge_cases_and_message():
    assert broadcast_shape() == ()
    assert broadcast_shape((), ()) == ()
    assert broadcast_shape((3, 1), (4,)) == (3, 4)
    assert broadcast_shape((0,), (1,)) == (0,)
    import torch

    assert broadcast_shape(torch.Size([2, 1, 5]), torch.Size([7, 1])) == (2, 7, 5)
    with pytest.raises(ShapeError, match=r"the rotations: \(2, 3\), \(4, 3\) do not broadcast"):
        broadcast_shape((2, 3), (4, 3), what="the rotations")


def test_a_run_imports_no_sympy():
    # torch.broadcast_shapes imports torch.fx's symbolic shapes and SymPy on its first call:
    # about 0.4 s of every run (reading a ground-truth trajectory, or the first frame's pose).
    code = """
import sys, tempfile
from pathlib import Path
from torchslam.data.synthetic import SyntheticConfig, generate_sequence, write_tum_folder
from torchslam.data.tum import TUMSequence
from torchslam.systems.base import run_sequence
from torchslam.systems.gcslam import GCSlam, GCSlamConfig
from torchslam.systems.nislam import NISlam, NISlamConfig
seq = generate_sequence(SyntheticConfig(frames=12, trajectory="orbit", seed=1, width=160, height=120))
with tempfile.TemporaryDirectory() as d:
    tum = TUMSequence(write_tum_folder(seq, Path(d) / "seq"))
    assert tum.groundtruth is not None
    for system in (NISlam(NISlamConfig()), GCSlam(GCSlamConfig(threaded=False))):
        out = run_sequence(system, tum).output
        assert out.T_wc.shape[0] == 12
print(sorted(m for m in sys.modules if m == "sympy" or m.startswith(("sympy.", "torch.fx.experimental.symbolic_shapes"))))
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out.splitlines()[-1] == "[]"
