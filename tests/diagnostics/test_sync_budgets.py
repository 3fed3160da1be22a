"""Host-device synchronisation budgets of the solvers' iterations (what an accelerator waits on).

Each budget is checked per iteration: the synchronisations of a run with ``k`` iterations minus
those of a run with ``k - 1`` (setup and result handling cancel out), for every ``k`` past the
first, with tolerances off so that every iteration runs.
"""

from __future__ import annotations

import dataclasses

import pytest
import torch

from torchslam.backend import optimize_pose_graph
from torchslam.data import SyntheticConfig, generate_sequence
from torchslam.diagnostics import count_syncs
from torchslam.fastgo import FastGOConfig, optimize
from torchslam.fastgo.synthetic import loop_route_problem
from torchslam.geometry import se3_exp, se3_inverse
from torchslam.optim import LMConfig
from torchslam.registration import dense as dense_module
from torchslam.registration.dense import DenseConfig, prepare_dense_frame, register_dense_frames

from tests._helpers import seeded


def per_iteration(run, iterations: int) -> list[tuple[int, str]]:
    """``(count, summary)`` of iterations 2..``iterations`` (``run(k)`` runs k iterations)."""
    reports = []
    for k in range(1, iterations + 1):
        with count_syncs() as syncs:
            run(k)
        reports.append(syncs)
    out = []
    for prev, cur in zip(reports, reports[1:]):
        extra = cur.by_location() - prev.by_location()
        out.append((cur.count - prev.count, "\n".join(f"{n} x {op} at {w}" for (op, w), n in extra.items())))
    return out


@pytest.mark.parametrize("ordering, schedule", [("band", "front"), ("nested", "level")])
def test_fastgo_iteration_at_most_two_syncs(ordering, schedule):
    prob = loop_route_problem(24, noise=0.005, seed=1)

    def run(k):
        cfg = FastGOConfig(iterations=k, tol=-1.0, step_tol=-1.0, ordering=ordering, schedule=schedule)
        return optimize(prob.T_init, prob.pairs, prob.stats, config=cfg)

    counts = per_iteration(run, 4)
    assert all(n <= 2 for n, _ in counts), counts
    # Gauss-Newton iterations take one; the Newton iterations (exact Hessian, tried from the
    # third iteration on here) one more, to learn whether their factorisation failed.
    assert [n for n, _ in counts] == [1, 2, 2], counts
    assert run(4).iterations == 4


def _pose_graph(n: int = 30):
    g = seeded(0)
    angles = torch.linspace(0, 6, n, dtype=torch.float64)
    xi = torch.zeros(n, 6, dtype=torch.float64)
    xi[:, 0], xi[:, 2], xi[:, 4] = 2 * torch.cos(angles), 2 * torch.sin(angles), -angles
    T_gt = se3_exp(xi)
    i = torch.cat([torch.arange(n - 1), torch.tensor([n - 1, n - 2, 0])])
    j = torch.cat([torch.arange(1, n), torch.tensor([0, 0, 5])])
    T_ij = se3_exp(0.01 * torch.randn(len(i), 6, generator=g, dtype=torch.float64)) @ se3_inverse(T_gt[i]) @ T_gt[j]
    info = torch.eye(6, dtype=torch.float64).expand(len(i), 6, 6).clone()
    T0 = se3_exp(0.05 * torch.randn(n, 6, generator=g, dtype=torch.float64)) @ T_gt
    return T0, i, j, T_ij, info


def test_pose_graph_iteration_at_most_two_syncs():
    T0, i, j, T_ij, info = _pose_graph()

    def run(k):
        return optimize_pose_graph(T0, i, j, T_ij, info, config=LMConfig(iterations=k, tol=-1.0, step_tol=-1.0))

    counts = per_iteration(run, 5)
    assert all(n <= 2 for n, _ in counts), counts
    assert run(5).iterations == 5


@pytest.fixture
def device_path(monkeypatch):
    """The dense registration's device path: its CPU-only NumPy fast paths never run on an accelerator."""
    monkeypatch.setattr(dense_module, "HOST_FAST_PATHS", False)


@pytest.fixture(scope="module")
def small_frames():
    seq = generate_sequence(SyntheticConfig(frames=5, width=160, height=120, depth_noise=False, trajectory="handheld", batch_size=5))
    rgb, depth = seq.render([0, 2, 4])
    cfg = DenseConfig(width=160, height=120, levels=2, iterations=(0, 1))
    fi = prepare_dense_frame(rgb[[0, 0]], depth[[0, 0]], seq.camera, cfg)
    fj = prepare_dense_frame(rgb[1:], depth[1:], seq.camera, cfg)
    return fi, fj, cfg


@pytest.mark.parametrize("robust", ["student_t", "huber"])
def test_dense_iteration_at_most_one_sync(small_frames, robust, device_path):
    fi, fj, cfg = small_frames

    def run(k):
        # tol 0: no pair stops by its step, every iteration runs (or a step that raised the cost ends it)
        return register_dense_frames(fi, fj, None, dataclasses.replace(cfg, iterations=(0, k), tol=0.0, finest_tol=0.0, robust=robust))

    counts = per_iteration(run, 5)
    assert all(n <= 1 for n, _ in counts), counts
    assert (run(5).iterations >= 3).all()
