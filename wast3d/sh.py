"""Real spherical harmonics of the reference 3DGS code: the basis, colour evaluation, and rotation.

Conventions (those of graphdeco's ``sh_utils.py``, which every 3DGS PLY assumes): coefficients are
stored per Gaussian as ``sh``: [N, K, 3] with ``K = (d + 1)^2`` for SH degree d, index 0 the DC term,
then band l = 1, 2, 3 in the order of :func:`sh_basis`; the colour seen along the unit view direction
``v`` (from the camera centre to the Gaussian, world frame) is ``0.5 + sum_k sh[k] Y_k(v)``.

Rotation. If a Gaussian is moved by a proper rotation ``R`` (``x -> R x + t``), the colour it showed
along ``v`` must now be shown along ``R v``: new coefficients ``c'`` with ``c' . Y(v) = c . Y(R^T v)``
for every ``v``. Each band l is closed under rotation, ``Y_l(R^T v) = M_l(R) Y_l(v)`` with a
(2l+1) x (2l+1) matrix (the real Wigner matrix in this basis), so ``c'_l = M_l(R)^T c_l``.
:func:`sh_rotation_matrices` obtains ``M_l^T`` exactly (to float64 round-off) by least squares on a
fixed set of 64 directions where the band is well conditioned: ``Y_l(D) M_l^T = Y_l(R^T D)``. This
uses the basis below and nothing else, so the signs and ordering cannot disagree with the renderer.
"""

from __future__ import annotations

import math

import torch

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
         -0.4570457994644658, 1.445305721320277, -0.5900435899266435)


def sh_basis(dirs: torch.Tensor, degree: int) -> torch.Tensor:
    """The real SH basis of the reference code. dirs: [N, 3] unit vectors -> [N, (degree+1)^2]."""
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        out += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out += [SH_C2[0] * xy, SH_C2[1] * yz, SH_C2[2] * (2 * zz - xx - yy), SH_C2[3] * xz, SH_C2[4] * (xx - yy)]
    if degree >= 3:
        out += [SH_C3[0] * y * (3 * xx - yy), SH_C3[1] * xy * z, SH_C3[2] * y * (4 * zz - xx - yy),
                SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy), SH_C3[4] * x * (4 * zz - xx - yy),
                SH_C3[5] * z * (xx - yy), SH_C3[6] * x * (xx - 3 * yy)]
    return torch.stack(out, dim=-1)


def eval_sh(sh: torch.Tensor, dirs: torch.Tensor, degree: int) -> torch.Tensor:
    """Colour before the +0.5 offset. sh: [N, K, 3] (K >= (degree+1)^2), dirs: [N, 3] unit -> [N, 3]."""
    k = (degree + 1) ** 2
    return torch.einsum("nk,nkc->nc", sh_basis(dirs, degree), sh[:, :k])


def _fibonacci_sphere(n: int) -> torch.Tensor:
    """[n, 3] float64 nearly uniform unit directions (the golden-angle spiral)."""
    i = torch.arange(n, dtype=torch.float64) + 0.5
    z = 1 - 2 * i / n
    r = (1 - z * z).sqrt()
    phi = i * math.pi * (3 - math.sqrt(5))
    return torch.stack([r * phi.cos(), r * phi.sin(), z], dim=-1)


_DIRS = _fibonacci_sphere(64)


def sh_rotation_matrices(R: torch.Tensor, degree: int) -> list[torch.Tensor]:
    """``M_l(R)^T`` for bands l = 1..degree (see the module docstring): R: [B, 3, 3] proper rotations
    -> list of [B, 2l+1, 2l+1] float64, such that ``c_l' = M_l^T c_l`` rotates band l by R."""
    R = R.to(torch.float64)
    D = _DIRS.to(R.device)
    Y = sh_basis(D, degree)                               # [64, K]
    YR = sh_basis(torch.einsum("kj,bji->bki", D, R), degree)  # rows R^T d_k: [B, 64, K]
    out = []
    for l in range(1, degree + 1):
        band = slice(l * l, (l + 1) * (l + 1))
        pinv = torch.linalg.pinv(Y[:, band])              # [2l+1, 64]
        out.append(torch.einsum("ik,bkj->bij", pinv, YR[:, :, band]))
    return out


def rotate_sh_rest(sh_rest: torch.Tensor, R: torch.Tensor) -> torch.Tensor:
    """Rotate the higher-order coefficients of Gaussians moved by R.

    sh_rest: [N, K, 3] (bands 1..d, K = (d+1)^2 - 1); R: [3, 3] (one rotation for all) or [N, 3, 3]
    -> [N, K, 3] in sh_rest's dtype. Degree 0 (K = 0) is returned as is.
    """
    K = sh_rest.shape[1]
    if K == 0:
        return sh_rest
    degree = round(math.sqrt(K + 1)) - 1
    Rb = R[None] if R.dim() == 2 else R
    mats = sh_rotation_matrices(Rb, degree)
    c = sh_rest.to(torch.float64)
    out = []
    for l, M in enumerate(mats, start=1):
        band = c[:, l * l - 1:(l + 1) * (l + 1) - 1]      # [N, 2l+1, 3]
        out.append(torch.einsum("ij,njc->nic", M[0], band) if R.dim() == 2 else torch.einsum("nij,njc->nic", M, band))
    return torch.cat(out, dim=1).to(sh_rest.dtype)
