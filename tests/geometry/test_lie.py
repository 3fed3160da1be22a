import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from torchslam.errors import DTypeError, ShapeError
from torchslam.geometry import (
    quat_xyzw_slerp,
    quat_xyzw_to_rotmat,
    rotmat_to_quat_xyzw,
    se3_act,
    se3_adjoint,
    se3_compose,
    se3_exp,
    se3_exp_numpy,
    se3_inverse,
    se3_inverse_numpy,
    se3_log,
    se3_log_numpy,
    skew,
    so3_exp,
    so3_log,
    vex,
)

from tests._helpers import TOL, seeded

BATCHES = [(), (1,), (5,), (2, 3)]


def random_twist(shape, dtype=torch.float64, max_angle=3.0, seed=0):
    g = seeded(seed)
    rho = torch.randn(*shape, 3, generator=g, dtype=dtype)
    axis = torch.randn(*shape, 3, generator=g, dtype=dtype)
    axis = axis / axis.norm(dim=-1, keepdim=True)
    angle = torch.rand(*shape, 1, generator=g, dtype=dtype) * max_angle
    return torch.cat([rho, axis * angle], dim=-1)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("shape", BATCHES)
def test_exp_log_roundtrip_all_batch_shapes(shape, dtype):
    xi = random_twist(shape, dtype)
    T = se3_exp(xi)
    assert T.shape == shape + (4, 4) and T.dtype == dtype
    torch.testing.assert_close(se3_log(T), xi, atol=TOL[dtype] * 10, rtol=0)
    torch.testing.assert_close(so3_log(so3_exp(xi[..., 3:])), xi[..., 3:], atol=TOL[dtype] * 10, rtol=0)


@pytest.mark.parametrize("angle", [0.0, 1e-12, 1e-8, 1e-4, 0.049, 0.05, 0.051, 0.5, 2.0, math.pi - 1e-3, math.pi - 1e-7])
def test_so3_roundtrip_across_branches_float64(angle):
    g = seeded(1)
    axis = torch.randn(50, 3, generator=g, dtype=torch.float64)
    phi = axis / axis.norm(dim=-1, keepdim=True) * angle
    R = so3_exp(phi)
    torch.testing.assert_close(R.transpose(-1, -2) @ R, torch.eye(3, dtype=torch.float64).expand(50, 3, 3), atol=1e-14, rtol=0)
    err = (so3_log(R) - phi).abs().max()
    assert err < 1e-10 * max(1.0, angle) or angle > math.pi - 1e-6 and err < 1e-7


def test_so3_log_exactly_pi_gives_an_angle_pi_vector():
    for axis in torch.eye(3, dtype=torch.float64):
        R = so3_exp(axis * math.pi)
        phi = so3_log(R)
        assert abs(phi.norm().item() - math.pi) < 1e-12
        torch.testing.assert_close(so3_exp(phi), R, atol=1e-12, rtol=0)


def test_against_scipy_rotation():
    xi = random_twist((200,), max_angle=math.pi, seed=3)
    R = so3_exp(xi[:, 3:])
    ref = Rotation.from_rotvec(xi[:, 3:].numpy())
    np.testing.assert_allclose(R.numpy(), ref.as_matrix(), atol=1e-12)
    np.testing.assert_allclose(so3_log(R).numpy(), ref.as_rotvec(), atol=1e-10)
    q = rotmat_to_quat_xyzw(R).numpy()
    q_ref = ref.as_quat()  # xyzw
    q_ref = q_ref * np.sign(q_ref[:, 3:4])
    np.testing.assert_allclose(q, q_ref, atol=1e-12)
    np.testing.assert_allclose(quat_xyzw_to_rotmat(torch.from_numpy(q_ref)).numpy(), ref.as_matrix(), atol=1e-12)


def test_quaternion_of_half_turns_and_sign_canonical():
    # trace = -1 rotations exercise the non-w Shepperd branches.
    for axis in torch.eye(3, dtype=torch.float64):
        q = rotmat_to_quat_xyzw(so3_exp(axis * math.pi))
        torch.testing.assert_close(q.abs(), torch.cat([axis, axis.new_zeros(1)]), atol=1e-12, rtol=0)
    q = torch.tensor([0.1, -0.2, 0.3, -0.9], dtype=torch.float64)
    q_out = rotmat_to_quat_xyzw(quat_xyzw_to_rotmat(q))
    assert q_out[3] > 0
    torch.testing.assert_close(q_out, -q / q.norm(), atol=1e-14, rtol=0)


def test_slerp_against_scipy():
    from scipy.spatial.transform import Slerp

    g = seeded(4)
    q0, q1 = torch.randn(2, 4, generator=g, dtype=torch.float64)
    q0, q1 = q0 / q0.norm(), q1 / q1.norm()
    alphas = torch.linspace(0, 1, 7, dtype=torch.float64)
    ours = quat_xyzw_slerp(q0.expand(7, 4), q1.expand(7, 4), alphas)
    ref = Slerp([0, 1], Rotation.from_quat(np.stack([q0.numpy(), q1.numpy()])))(alphas.numpy()).as_matrix()
    np.testing.assert_allclose(quat_xyzw_to_rotmat(ours).numpy(), ref, atol=1e-12)


def test_group_identities_float64():
    A = se3_exp(random_twist((20,), seed=5))
    B = se3_exp(random_twist((20,), seed=6))
    eye = torch.eye(4, dtype=torch.float64).expand(20, 4, 4)
    torch.testing.assert_close(se3_compose(A, se3_inverse(A)), eye, atol=1e-12, rtol=0)
    torch.testing.assert_close(se3_compose(A, B), A @ B, atol=1e-12, rtol=0)
    # Compare poses through the log of the relative transform.
    assert se3_log(se3_inverse(A @ B) @ se3_compose(A, B)).abs().max() < 1e-12
    # Adjoint: T exp(xi) T^-1 == exp(Ad_T xi).
    xi = random_twist((20,), max_angle=1.0, seed=7)
    lhs = A @ se3_exp(xi) @ se3_inverse(A)
    rhs = se3_exp((se3_adjoint(A) @ xi[..., None])[..., 0])
    torch.testing.assert_close(lhs, rhs, atol=1e-10, rtol=0)
    # Action agrees with the homogeneous product.
    p = torch.randn(20, 7, 3, generator=seeded(8), dtype=torch.float64)
    ph = torch.cat([p, torch.ones_like(p[..., :1])], -1)
    torch.testing.assert_close(se3_act(A, p), (A[:, None] @ ph[..., None])[..., :3, 0], atol=1e-12, rtol=0)


def test_skew_vex():
    v = torch.randn(4, 3, generator=seeded(9), dtype=torch.float64)
    u = torch.randn(4, 3, generator=seeded(10), dtype=torch.float64)
    torch.testing.assert_close((skew(v) @ u[..., None])[..., 0], torch.cross(v, u, dim=-1), atol=1e-14, rtol=0)
    torch.testing.assert_close(vex(skew(v)), v, atol=0, rtol=0)


def test_batched_equals_per_item():
    xi = random_twist((6,), seed=11)
    T = se3_exp(xi)
    for k in range(6):
        torch.testing.assert_close(T[k], se3_exp(xi[k]), atol=1e-15, rtol=0)
        torch.testing.assert_close(se3_log(T)[k], se3_log(T[k]), atol=1e-15, rtol=0)


def test_gradcheck_at_identity_and_random_points():
    zero = torch.zeros(6, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(se3_exp, (zero,))
    assert torch.autograd.gradcheck(lambda x: se3_log(se3_exp(x)), (zero,))
    assert torch.autograd.gradcheck(lambda x: so3_log(so3_exp(x)), (zero[3:].detach().clone().requires_grad_(),))
    xi = random_twist((3,), max_angle=2.5, seed=12).requires_grad_()
    assert torch.autograd.gradcheck(se3_exp, (xi,))
    assert torch.autograd.gradcheck(lambda x: se3_log(se3_exp(x)), (xi,))
    # Gradient of log at the identity matrix is finite.
    T = torch.eye(4, dtype=torch.float64, requires_grad=True)
    (g,) = torch.autograd.grad(se3_log(T).sum(), T)
    assert torch.isfinite(g).all()


def test_bad_input_raises():
    with pytest.raises(ShapeError, match=r"xi: expected \(\.\.\., 6\), got \(2, 5\)"):
        se3_exp(torch.zeros(2, 5))
    with pytest.raises(ShapeError, match="T: expected"):
        se3_log(torch.zeros(3, 3))
    with pytest.raises(DTypeError, match="phi: expected float32 or float64"):
        so3_exp(torch.zeros(3, dtype=torch.int64))
    with pytest.raises(ShapeError, match="points_b"):
        se3_act(torch.eye(4), torch.zeros(5, 2))


@pytest.mark.parametrize("scale", [1e-7, 1e-3, 0.05, 0.3, 2.0])
def test_se3_exp_numpy_matches_se3_exp(scale):
    """The host exponential (batched, and one twist in scalars) equals ``se3_exp`` to round-off
    on both sides of the small-angle switch, and is a rigid motion; the host inverse equals
    ``se3_inverse``."""
    g = torch.Generator().manual_seed(11)
    xi = torch.randn(6, 6, generator=g, dtype=torch.float64) * scale
    ref = se3_exp(xi).numpy()
    batched = se3_exp_numpy(xi.numpy())
    single = np.stack([se3_exp_numpy(x[None])[0] for x in xi.numpy()])
    np.testing.assert_allclose(batched, ref, rtol=0, atol=1e-15)
    np.testing.assert_allclose(single, ref, rtol=0, atol=1e-15)
    R = single[:, :3, :3]
    np.testing.assert_allclose(R @ R.transpose(0, 2, 1), np.broadcast_to(np.eye(3), R.shape), atol=1e-14)
    assert (single[:, 3] == [0.0, 0.0, 0.0, 1.0]).all()
    np.testing.assert_allclose(se3_inverse_numpy(batched), se3_inverse(se3_exp(xi)).numpy(), rtol=0, atol=1e-14)


@pytest.mark.parametrize("angle", [1e-9, 1e-3, 0.3, 2.0, math.pi - 1e-3, math.pi - 1e-8, math.pi])
def test_se3_log_numpy_matches_se3_log(angle):
    """The host logarithm equals ``se3_log`` to round-off near the identity, in between and at
    and near pi (the axis-from-symmetric-part branch), and inverts ``se3_exp_numpy``."""
    g = torch.Generator().manual_seed(12)
    axis = torch.randn(8, 3, generator=g, dtype=torch.float64)
    axis = axis / axis.norm(dim=-1, keepdim=True)
    xi = torch.cat([torch.randn(8, 3, generator=g, dtype=torch.float64), axis * angle], -1)
    T = se3_exp(xi)
    log = se3_log_numpy(T.numpy())
    np.testing.assert_allclose(log, se3_log(T).numpy(), rtol=0, atol=1e-12)
    np.testing.assert_allclose(se3_exp_numpy(log), T.numpy(), rtol=0, atol=1e-12)
