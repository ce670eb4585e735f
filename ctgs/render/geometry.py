"""Small geometric helpers: THE quaternion -> rotation of ctgs (training routines and the extension
backends' preprocessing use this one; the reference renderer keeps its own independent copy on purpose)."""

from __future__ import annotations

import torch


def quat_to_rotmat(q: torch.Tensor) -> torch.Tensor:
    """[N, 4] (w, x, y, z), any norm -> [N, 3, 3]; columns = tangent u, tangent v, normal."""
    q = q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], -1).reshape(*q.shape[:-1], 3, 3)


def rotmat_to_quat(r: torch.Tensor) -> torch.Tensor:
    """[N, 3, 3] proper rotations -> [N, 4] unit (w, x, y, z) with w >= 0 (Shepperd: the largest of
    w, x, y, z is computed from the diagonal, the others from off-diagonal sums; stable for any angle)."""
    m = r.reshape(-1, 3, 3)
    t = torch.stack([1 + m[:, 0, 0] + m[:, 1, 1] + m[:, 2, 2], 1 + m[:, 0, 0] - m[:, 1, 1] - m[:, 2, 2],
                     1 - m[:, 0, 0] + m[:, 1, 1] - m[:, 2, 2], 1 - m[:, 0, 0] - m[:, 1, 1] + m[:, 2, 2]], 1)
    k = t.argmax(1)
    s = 2 * t.gather(1, k[:, None]).clamp_min(1e-12).sqrt()[:, 0]  # 4 * |component k|
    d = lambda i, j: m[:, i, j]  # noqa: E731
    cand = torch.stack([
        torch.stack([s / 4, (d(2, 1) - d(1, 2)) / s, (d(0, 2) - d(2, 0)) / s, (d(1, 0) - d(0, 1)) / s], 1),
        torch.stack([(d(2, 1) - d(1, 2)) / s, s / 4, (d(0, 1) + d(1, 0)) / s, (d(0, 2) + d(2, 0)) / s], 1),
        torch.stack([(d(0, 2) - d(2, 0)) / s, (d(0, 1) + d(1, 0)) / s, s / 4, (d(1, 2) + d(2, 1)) / s], 1),
        torch.stack([(d(1, 0) - d(0, 1)) / s, (d(0, 2) + d(2, 0)) / s, (d(1, 2) + d(2, 1)) / s, s / 4], 1),
    ], 1)  # [N, 4 cases, 4]
    q = cand[torch.arange(m.shape[0]), k]
    q = q * torch.where(q[:, :1] < 0, -1.0, 1.0)
    return (q / q.norm(dim=1, keepdim=True)).reshape(*r.shape[:-2], 4)


def frames_from_normals(normals: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
    """[N, 3] unit normals -> [N, 3, 3] rotations whose third column is the normal and whose tangents have a
    random in-plane angle (uniform, from generator)."""
    n = normals / normals.norm(dim=1, keepdim=True).clamp_min(1e-12)
    a = torch.zeros_like(n)
    a[torch.arange(n.shape[0]), n.abs().argmin(1)] = 1.0  # the axis least parallel to n
    t1 = torch.linalg.cross(a, n)
    t1 = t1 / t1.norm(dim=1, keepdim=True)
    t2 = torch.linalg.cross(n, t1)
    phi = 2 * torch.pi * torch.rand(n.shape[0], 1, generator=generator, dtype=n.dtype)
    u = torch.cos(phi) * t1 + torch.sin(phi) * t2
    v = torch.linalg.cross(n, u)
    return torch.stack([u, v, n], 2)
