"""SO(3) and SE(3) on batched torch tensors.

Conventions (DESIGN.md): poses are 4x4 camera-to-world matrices ``T_world_cam``; a twist
``xi = (rho, omega)`` has the translational part first; quaternions are ``wxyz``.
Every function broadcasts over leading dimensions ``...``. Small-angle branches use Taylor
series so that values and gradients are finite at exactly zero rotation (tracking starts
its pose update there).
"""

from __future__ import annotations

import json
import math

import numpy as np
import torch

_EPS = 1e-6


def skew(v: torch.Tensor) -> torch.Tensor:
    """(..., 3) -> (..., 3, 3) matrix ``[v]_x`` with ``[v]_x @ u == cross(v, u)``."""
    x, y, z = v.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack([o, -z, y, z, o, -x, -y, x, o], dim=-1).reshape(*v.shape[:-1], 3, 3)


def _sin_coeffs(theta: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A = sin t / t, B = (1 - cos t) / t^2, C = (t - sin t) / t^3, with Taylor near 0."""
    small = theta < 1e-3
    t = torch.where(small, torch.ones_like(theta), theta)
    t2 = theta * theta
    a = torch.where(small, 1 - t2 / 6 + t2 * t2 / 120, torch.sin(t) / t)
    b = torch.where(small, 0.5 - t2 / 24 + t2 * t2 / 720, (1 - torch.cos(t)) / (t * t))
    c = torch.where(small, 1.0 / 6 - t2 / 120 + t2 * t2 / 5040, (t - torch.sin(t)) / (t * t * t))
    return a, b, c


def _safe_norm(v: torch.Tensor) -> torch.Tensor:
    """Norm over the last axis whose gradient is finite (zero) at v = 0."""
    sq = (v * v).sum(-1)
    return torch.sqrt(torch.clamp(sq, min=1e-24)) * (sq > 1e-24)


def so3_exp(omega: torch.Tensor) -> torch.Tensor:
    """(..., 3) axis-angle -> (..., 3, 3) rotation (Rodrigues)."""
    theta = _safe_norm(omega)
    a, b, _ = _sin_coeffs(theta)
    k = skew(omega)
    eye = torch.eye(3, dtype=omega.dtype, device=omega.device).expand_as(k)
    return eye + a[..., None, None] * k + b[..., None, None] * (k @ k)


def so3_log(R: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) rotation -> (..., 3) axis-angle with angle in [0, pi].

    Near pi the antisymmetric part vanishes, so the axis is read from the symmetric
    part ``(R + I) / 2 = n n^T`` instead.
    """
    trace = R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2]
    cos = torch.clamp((trace - 1) / 2, -1.0, 1.0)
    vee = torch.stack(
        [R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1
    )
    # atan2, not acos: acos has an infinite slope at cos = +-1 (NaN gradients at the identity,
    # ~1e-8 rad of noise at pi); |vee| / 2 = sin(theta).
    theta = torch.atan2(_safe_norm(vee) / 2, (trace - 1) / 2)
    sin = torch.sin(theta)
    small = theta < 1e-3
    # General and small-angle branches: omega = theta / (2 sin theta) * vee.
    factor = torch.where(small, 0.5 + theta * theta / 12, theta / (2 * torch.where(small, 1.0, sin)))
    omega = factor[..., None] * vee
    # Near-pi branch, computed for every entry and selected (a test of whether any entry is
    # near pi would read the device back in the trackers' loops).
    near_pi = theta > np.pi - 1e-2
    sym = (R + R.transpose(-1, -2)) / 2
    eye = torch.eye(3, dtype=R.dtype, device=R.device)
    # sym = cos I + (1 - cos) n n^T exactly; the clamp only guards batch entries not near pi.
    nn = (sym - cos[..., None, None] * eye) / torch.clamp(1 - cos, min=1.0)[..., None, None]
    diag = torch.diagonal(nn, dim1=-2, dim2=-1)
    col = diag.argmax(-1)
    n = torch.gather(nn, -1, col[..., None, None].expand(*nn.shape[:-1], 1)).squeeze(-1)
    n = n / torch.clamp(n.norm(dim=-1, keepdim=True), min=_EPS)
    # Pick the sign that agrees with the (small) antisymmetric part.
    sign = torch.where((n * vee).sum(-1) < 0, -1.0, 1.0).to(R.dtype)
    omega_pi = n * (theta * sign)[..., None]
    omega = torch.where(near_pi[..., None], omega_pi, omega)
    return omega


def se3_exp(xi: torch.Tensor) -> torch.Tensor:
    """(..., 6) twist ``(rho, omega)`` -> (..., 4, 4) rigid transform."""
    rho, omega = xi[..., :3], xi[..., 3:]
    theta = _safe_norm(omega)
    a, b, c = _sin_coeffs(theta)
    k = skew(omega)
    k2 = k @ k
    eye = torch.eye(3, dtype=xi.dtype, device=xi.device).expand_as(k)
    R = eye + a[..., None, None] * k + b[..., None, None] * k2
    V = eye + b[..., None, None] * k + c[..., None, None] * k2
    t = (V @ rho[..., None])[..., 0]
    return make_pose(R, t)


_GENERATORS: dict[tuple[torch.device, torch.dtype], torch.Tensor] = {}


def _so3_generators(like: torch.Tensor) -> torch.Tensor:
    """(3, 3, 3) ``[e_k]_x`` for k = x, y, z on ``like``'s device and dtype, made once (set
    element by element: no upload of host data)."""
    key = (like.device, like.dtype)
    E = _GENERATORS.get(key)
    if E is None:
        E = torch.zeros(3, 3, 3, dtype=like.dtype, device=like.device)
        for k, (i, j) in enumerate(((2, 1), (0, 2), (1, 0))):
            E[k, i, j], E[k, j, i] = 1.0, -1.0
        _GENERATORS[key] = E
    return E


def se3_exp_compact(xi: torch.Tensor) -> torch.Tensor:
    """``se3_exp`` in about a fifth of the operators, forward and backward (the static-shape
    trackers and mappers call it every iteration under autograd): the skew matrix as one
    contraction with the generators, the coefficients from theta^2 with second-order Taylor
    terms below theta = 1e-3 (the neglected terms are under 1e-13). (..., 6) -> (..., 4, 4);
    ``se3_exp`` is the reference it is tested against."""
    rho, omega = xi[..., :3], xi[..., 3:]
    k = torch.tensordot(omega, _so3_generators(xi), dims=([-1], [0]))          # (..., 3, 3)
    t2 = (omega * omega).sum(-1)
    small = t2 < 1e-6
    t2s = torch.where(small, torch.ones_like(t2), t2)
    t = torch.sqrt(t2s)
    sin, cos = torch.sin(t), torch.cos(t)
    a = torch.where(small, 1 - t2 / 6, sin / t)
    b = torch.where(small, 0.5 - t2 / 24, (1 - cos) / t2s)
    c = torch.where(small, 1.0 / 6 - t2 / 120, (t - sin) / (t2s * t))
    k2 = k @ k
    eye = torch.eye(3, dtype=xi.dtype, device=xi.device)
    R = eye + a[..., None, None] * k + b[..., None, None] * k2
    V = eye + b[..., None, None] * k + c[..., None, None] * k2
    return make_pose(R, (V @ rho[..., None])[..., 0])


def se3_log(T: torch.Tensor) -> torch.Tensor:
    """(..., 4, 4) rigid transform -> (..., 6) twist ``(rho, omega)``."""
    R, t = T[..., :3, :3], T[..., :3, 3]
    omega = so3_log(R)
    theta = omega.norm(dim=-1)
    k = skew(omega)
    small = theta < 1e-3
    th = torch.where(small, torch.ones_like(theta), theta)
    half = th / 2
    # V^-1 = I - K/2 + (1/t^2)(1 - (t/2) cot(t/2)) K^2
    coef = torch.where(
        small, 1.0 / 12 + theta * theta / 720, (1 - half * torch.cos(half) / torch.sin(half)) / (th * th)
    )
    eye = torch.eye(3, dtype=T.dtype, device=T.device).expand_as(k)
    V_inv = eye - 0.5 * k + coef[..., None, None] * (k @ k)
    rho = (V_inv @ t[..., None])[..., 0]
    return torch.cat([rho, omega], -1)


def make_pose(R: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) rotation and (..., 3) translation -> (..., 4, 4)."""
    top = torch.cat([R, t[..., None]], -1)
    bottom = torch.zeros(*R.shape[:-2], 1, 4, dtype=R.dtype, device=R.device)
    bottom[..., 0, 3] = 1
    return torch.cat([top, bottom], -2)


def se3_inverse(T: torch.Tensor) -> torch.Tensor:
    """(..., 4, 4) -> (..., 4, 4) inverse of a rigid transform (no general matrix inverse)."""
    Rt = T[..., :3, :3].transpose(-1, -2)
    return make_pose(Rt, -(Rt @ T[..., :3, 3:4])[..., 0])


def pose_moved(T: torch.Tensor, min_metres: float, min_degrees: float) -> bool:
    """Whether the relative pose T (4, 4) translates at least ``min_metres`` or turns at least
    ``min_degrees`` (a minimum <= 0 is not asked for; with neither, True).

    Example: a 2 cm step with minimums (0.01, 1.0) -> True; a 0.5 degree turn -> False.
    """
    if min_metres <= 0 and min_degrees <= 0:
        return True
    cos = ((T[0, 0] + T[1, 1] + T[2, 2] - 1.0) / 2.0).clamp(-1.0, 1.0)
    degrees = math.degrees(math.acos(float(cos)))
    metres = float(torch.linalg.vector_norm(T[:3, 3]))
    return (min_metres > 0 and metres >= min_metres) or (min_degrees > 0 and degrees >= min_degrees)


def compose(*transforms: torch.Tensor) -> torch.Tensor:
    """Product ``T_a_b @ T_b_c @ ...`` of (..., 4, 4) transforms, left to right."""
    out = transforms[0]
    for T in transforms[1:]:
        out = out @ T
    return out


def transform_points(T: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Apply (..., 4, 4) ``T`` to (..., N, 3) points -> (..., N, 3)."""
    return points @ T[..., :3, :3].transpose(-1, -2) + T[..., None, :3, 3]


def quat_wxyz_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """(..., 4) unit quaternion ``wxyz`` -> (..., 3, 3) rotation (normalised first)."""
    q = q / torch.clamp(q.norm(dim=-1, keepdim=True), min=_EPS)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        -1,
    ).reshape(*q.shape[:-1], 3, 3)


def matrix_to_quat_wxyz(R: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) rotation -> (..., 4) unit quaternion ``wxyz`` with w >= 0.

    Uses the numerically best of the four Shepperd branches per matrix.
    """
    m = R
    trace = m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2]
    cands = torch.stack(
        [
            torch.stack([1 + trace, m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]], -1),
            torch.stack([m[..., 2, 1] - m[..., 1, 2], 1 + m[..., 0, 0] - m[..., 1, 1] - m[..., 2, 2], m[..., 0, 1] + m[..., 1, 0], m[..., 0, 2] + m[..., 2, 0]], -1),
            torch.stack([m[..., 0, 2] - m[..., 2, 0], m[..., 0, 1] + m[..., 1, 0], 1 - m[..., 0, 0] + m[..., 1, 1] - m[..., 2, 2], m[..., 1, 2] + m[..., 2, 1]], -1),
            torch.stack([m[..., 1, 0] - m[..., 0, 1], m[..., 0, 2] + m[..., 2, 0], m[..., 1, 2] + m[..., 2, 1], 1 - m[..., 0, 0] - m[..., 1, 1] + m[..., 2, 2]], -1),
        ],
        -2,
    )  # (..., 4, 4): row i is 4 q q_i for branch i
    diag = torch.stack([trace, m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]], -1)
    best = diag.argmax(-1)
    q = torch.gather(cands, -2, best[..., None, None].expand(*best.shape, 1, 4)).squeeze(-2)
    q = q / q.norm(dim=-1, keepdim=True)
    return torch.where(q[..., :1] < 0, -q, q)


def parse_pose(text: str, source: str = "--pose") -> np.ndarray:
    """(4, 4) float64 from 16 numbers (row-major, separated by commas or spaces), a JSON 4x4
    list, or the path of a file holding either. Raises ValueError naming ``source`` (or the
    file) and what was wrong; rigidity is the caller's to check."""
    from pathlib import Path

    name = text.strip()
    try:
        is_file = bool(name) and Path(name).is_file()  # an inline pose can be too long for a file name
    except (OSError, ValueError):
        is_file = False
    if is_file:
        try:
            source, text = name, Path(name).read_text()
        except (OSError, UnicodeDecodeError) as error:
            raise ValueError(f"{source}: cannot read {name} ({error})") from None
    try:
        values = np.asarray(json.loads(text), dtype=np.float64)
    except (json.JSONDecodeError, TypeError, ValueError):
        try:
            values = np.asarray(text.replace(",", " ").split(), dtype=np.float64)
        except ValueError:
            raise ValueError(f"{source}: not a file, and not 16 numbers or a JSON 4x4 list: {text[:80]!r}") from None
    if values.size != 16:
        raise ValueError(f"{source}: a pose needs 16 numbers (4x4 row-major), found {values.size}")
    return values.reshape(4, 4)


def pose_from_tum(txyz_qxyzw: np.ndarray) -> np.ndarray:
    """(..., 7) TUM row ``tx ty tz qx qy qz qw`` -> (..., 4, 4) float64 numpy pose."""
    row = torch.as_tensor(np.asarray(txyz_qxyzw, dtype=np.float64))
    q_wxyz = torch.cat([row[..., 6:7], row[..., 3:6]], -1)
    return make_pose(quat_wxyz_to_matrix(q_wxyz), row[..., :3]).numpy()


def pose_to_tum(T: np.ndarray) -> np.ndarray:
    """(..., 4, 4) pose -> (..., 7) TUM row ``tx ty tz qx qy qz qw`` (float64 numpy)."""
    Tt = torch.as_tensor(np.asarray(T, dtype=np.float64))
    q = matrix_to_quat_wxyz(Tt[..., :3, :3])
    return torch.cat([Tt[..., :3, 3], q[..., 1:], q[..., :1]], -1).numpy()
