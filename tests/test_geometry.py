"""Tests for slam/geometry.py: golden values, exp/log round trips, singular angles, gradients."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from slam.geometry import (
    compose,
    make_pose,
    matrix_to_quat_wxyz,
    pose_from_tum,
    pose_to_tum,
    quat_wxyz_to_matrix,
    se3_exp,
    se3_inverse,
    se3_log,
    skew,
    so3_exp,
    so3_log,
    transform_points,
)

F64 = torch.float64
R_Z90 = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
R_X90 = [[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]
AXES = [(1, 0, 0), (0, 1, 0), (0, 0, 1), (1, 1, 0), (1, -1, 1), (-0.2, 0.3, 0.9)]


@pytest.fixture(params=["cpu"] + (["cuda"] if torch.cuda.is_available() else []))
def device(request) -> torch.device:
    """Overrides conftest's single device: these checks are cheap, so run the CPU always and CUDA too."""
    return torch.device(request.param)


def tensor(values, device) -> torch.Tensor:
    return torch.as_tensor(values, dtype=F64, device=device)


def unit(axis, device) -> torch.Tensor:
    v = tensor(axis, device)
    return v / v.norm()


def random_axis_angle(gen: torch.Generator, shape: tuple[int, ...], angle: float | None = None):
    """(*shape, 3) rotation vectors, random angle in (0, pi) unless ``angle`` is given."""
    axis = torch.randn(*shape, 3, generator=gen, dtype=F64)
    axis = axis / axis.norm(dim=-1, keepdim=True)
    if angle is None:
        return axis * torch.rand(*shape, 1, generator=gen, dtype=F64) * math.pi * 0.999
    return axis * angle


def random_poses(gen: torch.Generator, n: int) -> torch.Tensor:
    """(n, 4, 4) random rigid transforms."""
    R = so3_exp(random_axis_angle(gen, (n,)))
    return make_pose(R, torch.randn(n, 3, generator=gen, dtype=F64))


def assert_rotation(R: torch.Tensor, atol: float = 1e-12) -> None:
    eye = torch.eye(3, dtype=R.dtype, device=R.device).expand_as(R)
    torch.testing.assert_close(R @ R.transpose(-1, -2), eye, atol=atol, rtol=0)
    torch.testing.assert_close(torch.linalg.det(R), torch.ones_like(R[..., 0, 0]), atol=atol, rtol=0)


# ---------------------------------------------------------------- golden values


def test_skew_is_cross_product(device):
    gen = torch.Generator().manual_seed(0)
    v, u = torch.randn(2, 5, 3, generator=gen, dtype=F64).to(device)
    torch.testing.assert_close((skew(v) @ u[..., None])[..., 0], torch.cross(v, u, dim=-1))


def test_so3_exp_golden_quarter_turns(device):
    torch.testing.assert_close(so3_exp(tensor([0, 0, math.pi / 2], device)), tensor(R_Z90, device))
    torch.testing.assert_close(so3_exp(tensor([math.pi / 2, 0, 0], device)), tensor(R_X90, device))
    torch.testing.assert_close(so3_exp(tensor([0, 0, 0], device)), torch.eye(3, dtype=F64, device=device))


def test_se3_exp_golden_screw_motion(device):
    # rho = e_x, omega = pi/2 e_z: t = V rho = (2/pi, 2/pi, 0) (closed form of the left Jacobian).
    T = se3_exp(tensor([1, 0, 0, 0, 0, math.pi / 2], device))
    torch.testing.assert_close(T[:3, :3], tensor(R_Z90, device))
    torch.testing.assert_close(T[:3, 3], tensor([2 / math.pi, 2 / math.pi, 0], device))
    torch.testing.assert_close(T[3], tensor([0, 0, 0, 1], device))
    # A pure translation twist is a pure translation.
    torch.testing.assert_close(se3_exp(tensor([1, -2, 3, 0, 0, 0], device))[:3, 3], tensor([1, -2, 3], device))


@pytest.mark.parametrize(
    "q_wxyz, R",
    [
        ((math.sqrt(0.5), 0, 0, math.sqrt(0.5)), R_Z90),
        ((math.sqrt(0.5), math.sqrt(0.5), 0, 0), R_X90),
        ((0, 1, 0, 0), [[1, 0, 0], [0, -1, 0], [0, 0, -1]]),
        ((0.5, 0.5, 0.5, 0.5), [[0, 0, 1], [1, 0, 0], [0, 1, 0]]),  # 120 deg about (1, 1, 1)
        ((1, 0, 0, 0), [[1, 0, 0], [0, 1, 0], [0, 0, 1]]),
    ],
)
def test_quaternion_matrix_golden_pairs(q_wxyz, R, device):
    q, R = tensor(q_wxyz, device), tensor(R, device)
    torch.testing.assert_close(quat_wxyz_to_matrix(q), R)
    torch.testing.assert_close(matrix_to_quat_wxyz(R), q)


def test_quaternion_is_normalised_first(device):
    q = tensor([2 * math.sqrt(0.5), 0, 0, 2 * math.sqrt(0.5)], device)
    torch.testing.assert_close(quat_wxyz_to_matrix(q), tensor(R_Z90, device))


def test_pose_from_tum_golden():
    T = pose_from_tum(np.array([1.0, 2.0, 3.0, 0.0, 0.0, math.sqrt(0.5), math.sqrt(0.5)]))
    assert T.dtype == np.float64 and T.shape == (4, 4)
    np.testing.assert_allclose(T[:3, :3], R_Z90, atol=1e-15)
    np.testing.assert_allclose(T[:3, 3], [1, 2, 3])
    np.testing.assert_allclose(T[3], [0, 0, 0, 1])


def test_transform_points_golden(device):
    T = make_pose(tensor(R_Z90, device), tensor([1, 2, 3], device))
    p = tensor([[1, 0, 0], [0, 0, 1]], device)
    torch.testing.assert_close(transform_points(T, p), tensor([[1, 3, 3], [1, 2, 4]], device))


# ---------------------------------------------------------------- round trips


def test_so3_exp_log_round_trip_batched(device):
    gen = torch.Generator().manual_seed(1)
    omega = random_axis_angle(gen, (4, 5)).to(device)
    R = so3_exp(omega)
    assert R.shape == (4, 5, 3, 3)
    assert_rotation(R)
    torch.testing.assert_close(so3_log(R), omega, atol=1e-10, rtol=0)


def test_se3_exp_log_round_trip_batched(device):
    gen = torch.Generator().manual_seed(2)
    xi = torch.cat([torch.randn(3, 7, 3, generator=gen, dtype=F64), random_axis_angle(gen, (3, 7))], -1)
    T = se3_exp(xi.to(device))
    assert T.shape == (3, 7, 4, 4)
    assert_rotation(T[..., :3, :3])
    torch.testing.assert_close(se3_log(T), xi.to(device), atol=1e-10, rtol=0)
    torch.testing.assert_close(se3_exp(se3_log(T)), T, atol=1e-12, rtol=0)


@pytest.mark.parametrize("angle", [0.0, 1e-12, 1e-9, 1e-6, 1e-3 - 1e-9, 1e-3 + 1e-9])
def test_near_identity(angle, device):
    gen = torch.Generator().manual_seed(3)
    omega = random_axis_angle(gen, (16,), angle).to(device)
    torch.testing.assert_close(so3_log(so3_exp(omega)), omega, atol=1e-15, rtol=1e-9)
    xi = torch.cat([torch.randn(16, 3, generator=gen, dtype=F64).to(device), omega], -1)
    torch.testing.assert_close(se3_log(se3_exp(xi)), xi, atol=1e-14, rtol=1e-9)


@pytest.mark.parametrize("axis", AXES)
@pytest.mark.parametrize("angle", [math.pi - 1e-2, math.pi - 5e-3, math.pi - 1e-6])
def test_near_pi_round_trip(axis, angle, device):
    omega = unit(axis, device) * angle
    torch.testing.assert_close(so3_log(so3_exp(omega)), omega, atol=1e-12, rtol=0)
    xi = torch.cat([tensor([0.3, -0.1, 2.0], device), omega])
    torch.testing.assert_close(se3_log(se3_exp(xi)), xi, atol=1e-10, rtol=0)


@pytest.mark.parametrize("axis", AXES)
def test_exactly_pi(axis, device):
    n = unit(axis, device)
    R = 2 * torch.outer(n, n) - torch.eye(3, dtype=F64, device=device)  # exact half turn
    omega = so3_log(R)
    assert torch.isfinite(omega).all()
    assert abs(omega.norm().item() - math.pi) < 1e-12
    # Both +n pi and -n pi are correct logs of a half turn.
    assert min((omega - math.pi * n).norm().item(), (omega + math.pi * n).norm().item()) < 1e-12
    torch.testing.assert_close(so3_exp(omega), R, atol=1e-14, rtol=0)
    T = make_pose(R, tensor([1.0, 2.0, 3.0], device))
    torch.testing.assert_close(se3_exp(se3_log(T)), T, atol=1e-12, rtol=0)


def test_quaternion_round_trip_with_negative_w(device):
    gen = torch.Generator().manual_seed(4)
    q = torch.randn(200, 4, generator=gen, dtype=F64).to(device)
    q = q / q.norm(dim=-1, keepdim=True)
    assert (q[:, 0] < 0).any()
    R = quat_wxyz_to_matrix(q)
    assert_rotation(R)
    q_back = matrix_to_quat_wxyz(R)
    assert (q_back[:, 0] >= 0).all()
    torch.testing.assert_close(q_back, q * torch.sign(q[:, :1]), atol=1e-12, rtol=0)
    torch.testing.assert_close(quat_wxyz_to_matrix(-q), R)


@pytest.mark.parametrize("axis", AXES)
def test_matrix_to_quaternion_near_half_turns(axis, device):
    # Half turns make the trace -1, so the x/y/z Shepperd branches are the ones used.
    for angle in (math.pi, math.pi - 1e-7):
        R = so3_exp(unit(axis, device) * angle)
        torch.testing.assert_close(quat_wxyz_to_matrix(matrix_to_quat_wxyz(R)), R, atol=1e-14, rtol=0)


def test_pose_tum_round_trip():
    gen = torch.Generator().manual_seed(5)
    T = random_poses(gen, 50).numpy()
    rows = pose_to_tum(T)
    assert rows.shape == (50, 7) and rows.dtype == np.float64
    assert (rows[:, 6] >= 0).all()  # qw is last in TUM files
    np.testing.assert_allclose(pose_from_tum(rows), T, atol=1e-14)


def test_pose_from_tum_accepts_negative_w_and_unnormalised():
    row = np.array([0.5, 0.0, -1.0, 0.1, -0.7, 0.2, -0.6])
    T = pose_from_tum(row)
    np.testing.assert_allclose(pose_from_tum(row * np.r_[1, 1, 1, [-1.5] * 4]), T, atol=1e-14)
    back = pose_to_tum(T)
    q = row[3:] / np.linalg.norm(row[3:])
    np.testing.assert_allclose(back[3:], -q, atol=1e-14)
    np.testing.assert_allclose(back[:3], row[:3])


# ---------------------------------------------------------------- inverse and composition


def test_inverse_and_compose_identities(device):
    gen = torch.Generator().manual_seed(6)
    A, B, C = random_poses(gen, 3).to(device)
    eye = torch.eye(4, dtype=F64, device=device)
    torch.testing.assert_close(compose(A, se3_inverse(A)), eye, atol=1e-12, rtol=0)
    torch.testing.assert_close(compose(se3_inverse(A), A), eye, atol=1e-12, rtol=0)
    torch.testing.assert_close(se3_inverse(se3_inverse(A)), A)
    torch.testing.assert_close(se3_inverse(A), torch.linalg.inv(A))
    torch.testing.assert_close(compose(A, B, C), A @ B @ C)
    torch.testing.assert_close(compose(A), A)
    torch.testing.assert_close(se3_inverse(compose(A, B)), compose(se3_inverse(B), se3_inverse(A)))
    xi = se3_log(A)
    torch.testing.assert_close(se3_exp(-xi), se3_inverse(A), atol=1e-12, rtol=0)


def test_transform_points_batched_and_composed(device):
    gen = torch.Generator().manual_seed(7)
    T = random_poses(gen, 6).to(device).reshape(2, 3, 4, 4)
    p = torch.randn(2, 3, 10, 3, generator=gen, dtype=F64).to(device)
    homogeneous = torch.cat([p, torch.ones_like(p[..., :1])], -1)
    expected = (T @ homogeneous.transpose(-1, -2)).transpose(-1, -2)[..., :3]
    torch.testing.assert_close(transform_points(T, p), expected)
    A, B = T[0, 0], T[0, 1]
    torch.testing.assert_close(
        transform_points(compose(A, B), p[0, 0]), transform_points(A, transform_points(B, p[0, 0]))
    )
    torch.testing.assert_close(transform_points(se3_inverse(A), transform_points(A, p[0, 0])), p[0, 0])


def test_float32_stays_float32():
    omega = torch.tensor([0.1, 0.2, 0.3])
    assert so3_exp(omega).dtype == torch.float32
    assert se3_exp(torch.zeros(6)).dtype == torch.float32
    assert so3_log(so3_exp(omega)).dtype == torch.float32


# ---------------------------------------------------------------- gradients


def test_se3_exp_gradcheck_random_points():
    gen = torch.Generator().manual_seed(8)
    xi = torch.cat([torch.randn(4, 3, generator=gen, dtype=F64), random_axis_angle(gen, (4,))], -1)
    assert torch.autograd.gradcheck(se3_exp, (xi.requires_grad_(),))


def test_se3_exp_gradcheck_at_zero():
    # Tracking starts every pose update at exactly zero.
    xi = torch.zeros(6, dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(se3_exp, (xi,))
    assert torch.autograd.gradcheck(so3_exp, (torch.zeros(3, dtype=F64, requires_grad=True),))


def test_se3_exp_jacobian_at_zero_is_generators():
    jac = torch.autograd.functional.jacobian(se3_exp, torch.zeros(6, dtype=F64))  # (4, 4, 6)
    torch.testing.assert_close(jac[:3, 3, :3], torch.eye(3, dtype=F64))
    for i, e in enumerate(torch.eye(3, dtype=F64)):
        torch.testing.assert_close(jac[:3, :3, 3 + i], skew(e))


@pytest.mark.parametrize("angle", [0.0, 1e-9, 0.5, 2.0, math.pi - 1e-6])
def test_so3_log_gradients_are_finite(angle):
    omega = unit((0.3, -0.5, 0.8), "cpu") * angle
    R = so3_exp(omega).detach().requires_grad_(True)
    so3_log(R).sum().backward()
    assert torch.isfinite(R.grad).all()
    # Through exp: d log(exp(w)) / dw = I where exp/log are smooth.
    if angle < 3.0:
        w = omega.clone().requires_grad_(True)
        jac = torch.autograd.functional.jacobian(lambda v: so3_log(so3_exp(v)), w)
        torch.testing.assert_close(jac, torch.eye(3, dtype=F64), atol=1e-8, rtol=0)


def test_so3_log_gradient_at_identity_is_half_vee():
    R = torch.eye(3, dtype=F64, requires_grad=True)
    so3_log(R)[0].backward()  # omega_x = (R21 - R12) / 2 at the identity
    expected = torch.zeros(3, 3, dtype=F64)
    expected[2, 1], expected[1, 2] = 0.5, -0.5
    torch.testing.assert_close(R.grad, expected)


def test_so3_log_gradcheck_generic_rotation():
    R = so3_exp(tensor([0.4, -0.3, 1.1], "cpu")).requires_grad_(True)
    assert torch.autograd.gradcheck(so3_log, (R,))


# ---------------------------------------------------------------- bad shapes


@pytest.mark.parametrize(
    "fn, bad",
    [
        (so3_exp, torch.zeros(4)),
        (se3_exp, torch.zeros(5)),
        (quat_wxyz_to_matrix, torch.zeros(3)),
        (so3_log, torch.zeros(2, 2)),
        (transform_points, None),
    ],
    ids=["so3_exp", "se3_exp", "quat", "so3_log", "transform_points"],
)
def test_bad_shapes_raise(fn, bad):
    with pytest.raises((ValueError, RuntimeError, IndexError)):
        if fn is transform_points:
            transform_points(torch.eye(4), torch.zeros(5, 2))
        else:
            fn(bad)


def test_pose_from_tum_bad_row_raises():
    with pytest.raises((ValueError, RuntimeError, IndexError)):
        pose_from_tum(np.zeros(6))


@pytest.mark.parametrize("scale", [0.0, 1e-5, 1e-3, 0.05, 1.0, 3.0])
def test_se3_exp_compact_matches_se3_exp_and_its_gradient(scale):
    from slam.geometry import se3_exp_compact

    gen = torch.Generator().manual_seed(7)
    xi = (torch.randn(5, 6, generator=gen, dtype=torch.float64) * scale).requires_grad_(True)
    w = torch.randn(5, 4, 4, generator=gen, dtype=torch.float64)
    (ref,) = torch.autograd.grad((se3_exp(xi) * w).sum(), xi)
    (got,) = torch.autograd.grad((se3_exp_compact(xi) * w).sum(), xi)
    assert torch.allclose(se3_exp_compact(xi), se3_exp(xi), atol=1e-12)
    assert torch.allclose(got, ref, atol=1e-9)
    assert se3_exp_compact(xi[0]).shape == (4, 4)
