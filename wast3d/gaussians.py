"""The 3D Gaussian scene model.

A scene stores the parameters of the reference 3DGS code *before* activation, so that a PLY round
trip is exact:

- ``means``: [N, 3] world positions;
- ``log_scales``: [N, 3], the scale of each principal axis is ``exp(log_scales)``;
- ``quats``: [N, 4] unnormalized quaternions (w, x, y, z);
- ``opacity_logits``: [N], the opacity is ``sigmoid(opacity_logits)``;
- ``sh_dc``: [N, 3] degree-0 spherical-harmonic coefficients, ``rgb = 0.5 + SH_C0 * sh_dc``;
- ``sh_rest``: [N, K, 3] higher-order coefficients, ``K = (d + 1)^2 - 1`` for SH degree d (K = 0
  for degree 0);
- ``element``: optional [N] int64 label, not a parameter: which element of a style scene each Gaussian
  belongs to (0 = the ground, 1.. = pebbles, blades, strands, stones; see :mod:`wast3d.procedural`).
  It travels with the Gaussians through ``subset``/``concat``/``transform`` (selection, stylization and
  rescale are index maps), so the element metrics (:mod:`wast3d.elements`) can follow each element
  into a result. ``None`` for unlabelled scenes.

The covariance of a Gaussian is ``Sigma = R S S^T R^T`` with ``R`` the rotation of the normalized
quaternion and ``S = diag(scales)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Iterable

import torch

from .sh import SH_C0, rotate_sh_rest

FIELDS = ("means", "log_scales", "quats", "opacity_logits", "sh_dc", "sh_rest")


def num_sh_rest(degree: int) -> int:
    """Number of non-DC SH coefficients per channel for an SH degree (0..3)."""
    if degree not in (0, 1, 2, 3):
        raise ValueError(f"SH degree must be 0..3, got {degree}")
    return (degree + 1) ** 2 - 1


def sh_degree_from_rest(k: int) -> int:
    """Inverse of :func:`num_sh_rest`; raises ValueError for a count that is no SH degree."""
    for d in range(4):
        if num_sh_rest(d) == k:
            return d
    raise ValueError(f"{k} rest coefficients per channel match no SH degree 0..3 (expect 0, 3, 8 or 15)")


def rgb_to_sh_dc(rgb: torch.Tensor) -> torch.Tensor:
    """rgb: [..., 3] in [0, 1] -> DC coefficients, the inverse of ``0.5 + SH_C0 * dc``."""
    return (rgb - 0.5) / SH_C0


def sh_dc_to_rgb(dc: torch.Tensor) -> torch.Tensor:
    return 0.5 + SH_C0 * dc


def quat_to_rotmat(quats: torch.Tensor) -> torch.Tensor:
    """quats: [N, 4] (w, x, y, z), any norm -> rotation matrices [N, 3, 3]."""
    q = quats / quats.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(*q.shape[:-1], 3, 3)


def rotmat_to_quat(R: torch.Tensor) -> torch.Tensor:
    """R: [N, 3, 3] proper rotations -> unit quaternions [N, 4] (w, x, y, z), w >= 0.

    Uses the numerically stable branch on the largest diagonal term (Shepperd's method).
    """
    m = R
    tr = m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2]
    cands = torch.stack(
        [
            torch.stack([1 + tr, m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]], -1),
            torch.stack([m[..., 2, 1] - m[..., 1, 2], 1 + m[..., 0, 0] - m[..., 1, 1] - m[..., 2, 2], m[..., 0, 1] + m[..., 1, 0], m[..., 0, 2] + m[..., 2, 0]], -1),
            torch.stack([m[..., 0, 2] - m[..., 2, 0], m[..., 0, 1] + m[..., 1, 0], 1 - m[..., 0, 0] + m[..., 1, 1] - m[..., 2, 2], m[..., 1, 2] + m[..., 2, 1]], -1),
            torch.stack([m[..., 1, 0] - m[..., 0, 1], m[..., 0, 2] + m[..., 2, 0], m[..., 1, 2] + m[..., 2, 1], 1 - m[..., 0, 0] - m[..., 1, 1] + m[..., 2, 2]], -1),
        ],
        dim=-2,
    )  # [..., 4, 4]; row i is 4*q*q_i, largest q_i is the stable one
    diag = torch.stack([1 + tr, 1 + m[..., 0, 0] - m[..., 1, 1] - m[..., 2, 2],
                        1 - m[..., 0, 0] + m[..., 1, 1] - m[..., 2, 2], 1 - m[..., 0, 0] - m[..., 1, 1] + m[..., 2, 2]], -1)
    idx = diag.argmax(-1)
    q = torch.gather(cands, -2, idx[..., None, None].expand(*idx.shape, 1, 4)).squeeze(-2)
    q = q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    return torch.where(q[..., :1] < 0, -q, q)


@dataclass
class GaussianScene:
    """A set of 3D Gaussians; see the module docstring for the parameterization and shapes."""

    means: torch.Tensor
    log_scales: torch.Tensor
    quats: torch.Tensor
    opacity_logits: torch.Tensor
    sh_dc: torch.Tensor
    sh_rest: torch.Tensor
    element: torch.Tensor | None = None

    def __post_init__(self) -> None:
        n = self.means.shape[0]
        expect = {
            "means": (n, 3), "log_scales": (n, 3), "quats": (n, 4), "opacity_logits": (n,), "sh_dc": (n, 3),
        }
        for name, shape in expect.items():
            got = tuple(getattr(self, name).shape)
            if got != shape:
                raise ValueError(f"GaussianScene.{name}: expected shape {list(shape)}, got {list(got)}")
        r = self.sh_rest
        if r.ndim != 3 or r.shape[0] != n or r.shape[2] != 3:
            raise ValueError(f"GaussianScene.sh_rest: expected shape [N, K, 3], got {list(r.shape)}")
        sh_degree_from_rest(r.shape[1])
        if self.element is not None and tuple(self.element.shape) != (n,):
            raise ValueError(f"GaussianScene.element: expected shape [{n}], got {list(self.element.shape)}")

    # ---- construction -------------------------------------------------------------------------
    @classmethod
    def from_activated(
        cls,
        means: torch.Tensor,
        scales: torch.Tensor,
        quats: torch.Tensor | None = None,
        opacities: torch.Tensor | float = 0.9,
        rgb: torch.Tensor | None = None,
        sh_degree: int = 0,
    ) -> "GaussianScene":
        """Build a scene from activated values: scales [N, 3] > 0, opacities in (0, 1), rgb [N, 3]."""
        n = means.shape[0]
        dt, dev = means.dtype, means.device
        if quats is None:
            quats = torch.zeros(n, 4, dtype=dt, device=dev)
            quats[:, 0] = 1
        op = torch.as_tensor(opacities, dtype=dt, device=dev).expand(n).clamp(1e-6, 1 - 1e-6)
        if rgb is None:
            rgb = torch.full((n, 3), 0.5, dtype=dt, device=dev)
        return cls(
            means=means.clone(),
            log_scales=scales.clamp_min(1e-12).log(),
            quats=quats.clone(),
            opacity_logits=torch.logit(op),
            sh_dc=rgb_to_sh_dc(rgb),
            sh_rest=torch.zeros(n, num_sh_rest(sh_degree), 3, dtype=dt, device=dev),
        )

    @classmethod
    def empty(cls, sh_degree: int = 0, dtype=torch.float32, device="cpu") -> "GaussianScene":
        z = lambda *s: torch.zeros(*s, dtype=dtype, device=device)  # noqa: E731
        return cls(z(0, 3), z(0, 3), z(0, 4), z(0), z(0, 3), z(0, num_sh_rest(sh_degree), 3))

    # ---- basic properties -----------------------------------------------------------------------
    def __len__(self) -> int:
        return self.means.shape[0]

    @property
    def sh_degree(self) -> int:
        return sh_degree_from_rest(self.sh_rest.shape[1])

    @property
    def device(self) -> torch.device:
        return self.means.device

    @property
    def dtype(self) -> torch.dtype:
        return self.means.dtype

    # ---- activated views ---------------------------------------------------------------------
    @property
    def scales(self) -> torch.Tensor:
        """[N, 3]"""
        return self.log_scales.exp()

    @property
    def opacities(self) -> torch.Tensor:
        """[N]"""
        return torch.sigmoid(self.opacity_logits)

    @property
    def rgb(self) -> torch.Tensor:
        """[N, 3] view-independent (DC) colour, clamped at 0 like the renderer."""
        return sh_dc_to_rgb(self.sh_dc).clamp_min(0.0)

    @property
    def rotations(self) -> torch.Tensor:
        """[N, 3, 3]"""
        return quat_to_rotmat(self.quats)

    @property
    def covariances(self) -> torch.Tensor:
        """[N, 3, 3] ``R S S^T R^T``"""
        M = self.rotations * self.scales[:, None, :]
        return M @ M.transpose(-1, -2)

    @property
    def sh(self) -> torch.Tensor:
        """[N, (d+1)^2, 3] all SH coefficients, DC first."""
        return torch.cat([self.sh_dc[:, None, :], self.sh_rest], dim=1)

    # ---- manipulation ---------------------------------------------------------------------------
    def tensors(self) -> dict[str, torch.Tensor]:
        """The six parameter tensors (``element``, a label, is not one of them)."""
        return {k: getattr(self, k) for k in FIELDS}

    def map(self, fn, element_fn=None) -> "GaussianScene":
        """``fn`` applied to every parameter tensor, ``element_fn`` (default: none) to the labels."""
        el = self.element if self.element is None or element_fn is None else element_fn(self.element)
        return GaussianScene(**{k: fn(v) for k, v in self.tensors().items()}, element=el)

    def to(self, device=None, dtype=None) -> "GaussianScene":
        return self.map(lambda t: t.to(device=device, dtype=dtype), lambda e: e.to(device=device))

    def detach(self) -> "GaussianScene":
        return self.map(lambda t: t.detach())

    def clone(self) -> "GaussianScene":
        return self.map(lambda t: t.clone())

    def subset(self, index: torch.Tensor) -> "GaussianScene":
        """index: a boolean mask [N] or integer indices [M]."""
        return self.map(lambda t: t[index], lambda e: e[index.to(e.device) if torch.is_tensor(index) else index])

    def with_sh_degree(self, degree: int) -> "GaussianScene":
        """Truncate or zero-pad the SH coefficients to ``degree``."""
        k = num_sh_rest(degree)
        r = self.sh_rest
        if k <= r.shape[1]:
            r = r[:, :k]
        else:
            r = torch.cat([r, r.new_zeros(len(self), k - r.shape[1], 3)], dim=1)
        return replace(self, sh_rest=r.contiguous())

    @staticmethod
    def concat(scenes: Iterable["GaussianScene"]) -> "GaussianScene":
        scenes = list(scenes)
        if not scenes:
            raise ValueError("concat of no scenes")
        deg = max(s.sh_degree for s in scenes)
        scenes = [s.with_sh_degree(deg) for s in scenes]
        # labels survive only if every part has them (a half-labelled scene would mislead the metrics)
        el = torch.cat([s.element for s in scenes]) if all(s.element is not None for s in scenes) else None
        return GaussianScene(**{k: torch.cat([getattr(s, k) for s in scenes]) for k in FIELDS}, element=el)

    def transform(
        self,
        rotation: torch.Tensor | None = None,
        translation: torch.Tensor | None = None,
        scale: torch.Tensor | float | None = None,
    ) -> "GaussianScene":
        """Apply ``x -> R (s * x) + t`` to means *and* covariances.

        rotation: [3, 3] proper rotation; translation: [3]; scale: scalar or [3] per-axis scale applied
        in the *input* frame (``A = R diag(s)``). The new covariance ``A Sigma A^T`` is re-factored into
        a rotation and scales by an eigendecomposition when the scale is anisotropic (a sheared
        Gaussian is still a Gaussian); for a uniform scale the quaternion is rotated exactly.
        Higher-order SH coefficients (degree >= 1) are rotated by R (:func:`wast3d.sh.rotate_sh_rest`), so
        each Gaussian shows the colour it showed along ``v`` now along ``R v``. For an anisotropic map
        ``A = R diag(s)`` that is the rotation of A's polar decomposition ``A = U P`` (U orthogonal, P
        symmetric positive definite): here ``U = R`` and ``P = diag(s)`` exactly. A stretch has no exact
        counterpart for view-dependent colour; U is the rotation nearest to A (Frobenius norm).
        """
        dt, dev = self.dtype, self.device
        R = torch.eye(3, dtype=dt, device=dev) if rotation is None else rotation.to(dt)
        t = torch.zeros(3, dtype=dt, device=dev) if translation is None else translation.to(dt)
        s = torch.ones(3, dtype=dt, device=dev) if scale is None else torch.as_tensor(scale, dtype=dt, device=dev).expand(3)
        if torch.linalg.det(R).item() < 0:
            raise ValueError("transform: rotation must be proper (det = +1)")
        A = R * s[None, :]
        means = self.means @ A.T + t
        if torch.allclose(s, s[0].expand(3)):
            qR = rotmat_to_quat(R[None])[0]
            quats = quat_multiply(qR.expand_as(self.quats), self.quats / self.quats.norm(dim=-1, keepdim=True))
            log_scales = self.log_scales + torch.log(s[0].abs())
        else:
            cov = A @ self.covariances @ A.T
            cov = 0.5 * (cov + cov.transpose(-1, -2))
            evals, evecs = torch.linalg.eigh(cov)
            # eigh may return a reflection; flipping the last eigenvector makes it a proper rotation
            sign = torch.where(torch.linalg.det(evecs) < 0, -1.0, 1.0).to(dt)
            evecs = torch.cat([evecs[:, :, :2], evecs[:, :, 2:] * sign[:, None, None]], dim=2)
            quats = rotmat_to_quat(evecs)
            log_scales = 0.5 * evals.clamp_min(1e-30).log()
        sh_rest = self.sh_rest if rotation is None else rotate_sh_rest(self.sh_rest, R)
        return replace(self, means=means, quats=quats, log_scales=log_scales, sh_rest=sh_rest)


def quat_multiply(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product of quaternions [..., 4] (w, x, y, z)."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        dim=-1,
    )


def luminance(rgb: torch.Tensor) -> torch.Tensor:
    """Rec. 601 luma ``Y = 0.299 R + 0.587 G + 0.114 B``; rgb: [..., 3] -> [...]."""
    return rgb @ rgb.new_tensor([0.299, 0.587, 0.114])


def footprint(scales: torch.Tensor, opacities: torch.Tensor) -> torch.Tensor:
    """``o s_1 s_2`` per Gaussian: opacity times the product of its two largest scales, the integral of
    its alpha seen face-on over 2 pi. scales: [N, 3], opacities: [N] -> [N] (float64)."""
    sc = scales.detach().double().sort(dim=-1, descending=True).values
    return opacities.detach().double() * sc[:, 0] * sc[:, 1]


def anisotropy(scales: torch.Tensor) -> torch.Tensor:
    """max(s) / min(s) per Gaussian; scales: [N, 3] -> [N]."""
    return scales.max(dim=-1).values / scales.min(dim=-1).values.clamp_min(1e-30)




def shortest_axis(quats: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
    """Unit direction of each Gaussian's shortest axis (its normal, for a flat Gaussian; sign arbitrary).

    quats: [N, 4] (w, x, y, z), scales: [N, 3] -> [N, 3].
    """
    R = quat_to_rotmat(quats)
    i = scales.argmin(dim=-1)
    return R.gather(2, i[:, None, None].expand(-1, 3, 1))[..., 0]
