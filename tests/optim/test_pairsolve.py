"""The shared per-pair 6x6 Gauss-Newton solve: planted steps, failed pairs, batching, bad input."""

from __future__ import annotations

import pytest
import torch

from torchslam.errors import DTypeError, ShapeError
from torchslam.optim import solve_pair_steps

TOL = {torch.float32: 1e-4, torch.float64: 1e-10}


def _spd(B: int, dtype: torch.dtype, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    A = torch.randn(B, 6, 6, generator=g, dtype=torch.float64)
    return (A @ A.transpose(1, 2) + 6 * torch.eye(6, dtype=torch.float64)).to(dtype)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_planted_step_is_recovered(dtype):
    H = _spd(5, dtype)
    delta = torch.randn(5, 6, generator=torch.Generator().manual_seed(1), dtype=torch.float64).to(dtype)
    g = -(H @ delta[..., None])[..., 0]
    step = solve_pair_steps(H, g)
    assert step.solved.all()
    torch.testing.assert_close(step.delta, delta, rtol=0, atol=TOL[dtype] * 10)


def test_singular_and_non_finite_pairs_take_zero_steps_and_leave_others_alone():
    H = _spd(4, torch.float64)
    g = torch.randn(4, 6, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    alone = solve_pair_steps(H, g)
    H_bad = H.clone()
    H_bad[1] = torch.zeros(6, 6, dtype=torch.float64)  # not positive definite
    g_bad = g.clone()
    g_bad[2, 0] = float("inf")  # a finite factor but a non-finite step
    step = solve_pair_steps(H_bad, g_bad)
    assert step.solved.tolist() == [True, False, False, True]
    assert torch.equal(step.delta[1:3], torch.zeros(2, 6, dtype=torch.float64))
    torch.testing.assert_close(step.delta[[0, 3]], alone.delta[[0, 3]], rtol=0, atol=0)


def test_batched_equals_per_pair():
    H = _spd(6, torch.float64, seed=3)
    g = torch.randn(6, 6, generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    step = solve_pair_steps(H, g)
    for b in range(6):
        one = solve_pair_steps(H[b : b + 1], g[b : b + 1])
        torch.testing.assert_close(one.delta[0], step.delta[b], rtol=0, atol=1e-12)
    assert solve_pair_steps(H[:0], g[:0]).delta.shape == (0, 6)


def test_bad_input_names_the_argument():
    H = _spd(2, torch.float64)
    with pytest.raises(ShapeError, match=r"H: expected \(B, 6, 6\), got \(2, 5, 5\)"):
        solve_pair_steps(H[:, :5, :5], torch.zeros(2, 6, dtype=torch.float64))
    with pytest.raises(ShapeError, match="g: expected"):
        solve_pair_steps(H, torch.zeros(3, 6, dtype=torch.float64))
    with pytest.raises(DTypeError, match="H: expected float32 or float64"):
        solve_pair_steps(H.to(torch.int64), torch.zeros(2, 6, dtype=torch.float64))


def test_host_numpy_path_agrees_with_torch_path():
    H = _spd(5, torch.float64, seed=5)
    g = torch.randn(5, 6, generator=torch.Generator().manual_seed(6), dtype=torch.float64)
    host = solve_pair_steps(H, g, host=True)
    torch.testing.assert_close(host.delta, solve_pair_steps(H, g).delta, rtol=0, atol=1e-12)
    assert host.solved.all()
    # A pair that is not positive definite sends the whole batch down torch's path.
    H_bad = torch.cat([H, torch.zeros(1, 6, 6, dtype=torch.float64)])
    bad = solve_pair_steps(H_bad, torch.cat([g, g[:1]]), host=True)
    assert bad.solved.tolist() == [True] * 5 + [False]
    torch.testing.assert_close(bad.delta[:5], host.delta, rtol=0, atol=1e-12)


def test_host_numpy_path_never_raises_on_non_finite_or_singular_pairs():
    """NumPy's Cholesky lets NaN through and its LU solve raises on what it finds singular: the
    host path then falls back to torch's, which marks the pairs (a loop registration of 7-Scenes
    raised LinAlgError here)."""
    H = _spd(3, torch.float64, seed=7)
    g = torch.randn(3, 6, generator=torch.Generator().manual_seed(8), dtype=torch.float64)
    ref = solve_pair_steps(H, g)
    for name, H_bad, g_bad in (
        ("nan H", torch.cat([H, torch.full((1, 6, 6), float("nan"), dtype=torch.float64)]), torch.cat([g, g[:1]])),
        ("inf g", torch.cat([H, H[:1]]), torch.cat([g, torch.full((1, 6), float("inf"), dtype=torch.float64)])),
        ("rank 1", torch.cat([H, torch.ones(1, 6, 6, dtype=torch.float64)]), torch.cat([g, g[:1]])),
    ):
        step = solve_pair_steps(H_bad, g_bad, host=True)
        assert step.solved.tolist() == [True, True, True, False], name
        assert torch.equal(step.delta[3], torch.zeros(6, dtype=torch.float64)), name
        torch.testing.assert_close(step.delta[:3], ref.delta, rtol=0, atol=1e-12)
    # The matrix that raised: a degenerate loop pair (inliers on a line) whose Cholesky factor
    # exists in round-off while the LU solve meets an exact zero pivot. Torch's path solves it.
    a, b, c, d = 0.09406477010494602, 0.26619864763409734, 0.04780508181906725, 0.0008948954770249615
    degenerate = torch.tensor([
        [a, 0.0, 0.0, 0.0, b, c],
        [0.0, a, 0.0, -b, 0.0, -d],
        [0.0, 0.0, a, -c, d, 0.0],
        [0.0, -b, -c, 0.7776242451700193, -0.0004547988737011973, 0.0025325099449255905],
        [b, 0.0, d, -0.0004547988737011973, 0.7533375222315151, 0.13528601745451935],
        [c, -d, 0.0, 0.0025325099449255905, 0.13528601745451935, 0.024303750310471522],
    ], dtype=torch.float64)
    g_d = torch.tensor([-0.0015310846490743078, -0.0026073834961315803, 0.001876649021628366,
                        0.006425026073361938, -0.00431504013482032, -0.0007533138192364707], dtype=torch.float64)
    Hd, gd = torch.cat([H, degenerate[None]]), torch.cat([g, g_d[None]])
    host = solve_pair_steps(Hd, gd, host=True)
    plain = solve_pair_steps(Hd, gd)
    assert host.solved.tolist() == plain.solved.tolist()
    torch.testing.assert_close(host.delta, plain.delta, rtol=0, atol=0)
