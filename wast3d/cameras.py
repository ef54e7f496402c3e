"""Pinhole cameras, and orbit rigs fitted to a scene (:func:`fit_orbit`).

Conventions (OpenCV, as gsplat): camera looks down +z, x right, y down; ``world_to_cam`` is a 4x4
matrix mapping world points to camera coordinates; pixel (i, j) covers [i, i+1) x [j, j+1) so its
centre is at (i + 0.5, j + 0.5); a centred principal point is (W/2, H/2).

Blender/NeRF-Synthetic ``transform_matrix`` is camera-to-world in OpenGL axes (looks down -z, y up):
:func:`camera_from_blender` flips the y and z camera axes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import torch

from .geometry import robust_bounds

if TYPE_CHECKING:
    from .gaussians import GaussianScene


@dataclass
class Camera:
    """A pinhole camera. world_to_cam: [4, 4]; fx, fy, cx, cy in pixels."""

    world_to_cam: torch.Tensor
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    near: float = 0.01
    far: float = 1e10
    name: str = ""

    @property
    def K(self) -> torch.Tensor:
        """[3, 3] intrinsics."""
        return torch.tensor([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]],
                            dtype=self.world_to_cam.dtype)

    @property
    def cam_to_world(self) -> torch.Tensor:
        return torch.linalg.inv(self.world_to_cam)

    @property
    def center(self) -> torch.Tensor:
        """[3] camera position in world coordinates."""
        R, t = self.world_to_cam[:3, :3], self.world_to_cam[:3, 3]
        return -R.T @ t

    def to(self, device=None, dtype=None) -> "Camera":
        return replace(self, world_to_cam=self.world_to_cam.to(device=device, dtype=dtype))

    def scaled(self, factor: float) -> "Camera":
        """The same camera at ``factor`` times the resolution."""
        return replace(self, fx=self.fx * factor, fy=self.fy * factor, cx=self.cx * factor, cy=self.cy * factor,
                       width=max(1, round(self.width * factor)), height=max(1, round(self.height * factor)))

    def crop(self, x0: int, y0: int, w: int, h: int) -> "Camera":
        """The sub-window [x0, x0+w) x [y0, y0+h) as a camera of its own (close-ups)."""
        return replace(self, cx=self.cx - x0, cy=self.cy - y0, width=w, height=h)


def fov_to_focal(fov: float, pixels: int) -> float:
    return 0.5 * pixels / math.tan(0.5 * fov)


def camera_from_blender(c2w_gl: torch.Tensor, camera_angle_x: float, width: int, height: int,
                        name: str = "") -> Camera:
    """c2w_gl: [4, 4] camera-to-world in OpenGL/Blender axes -> :class:`Camera`."""
    c2w = c2w_gl.clone().double()
    c2w[:3, 1:3] *= -1  # OpenGL (y up, -z forward) -> OpenCV (y down, +z forward)
    w2c = torch.linalg.inv(c2w)
    f = fov_to_focal(camera_angle_x, width)
    return Camera(w2c.float(), f, f, width / 2.0, height / 2.0, width, height, name=name)


def camera_to_blender(cam: Camera) -> torch.Tensor:
    """Inverse of :func:`camera_from_blender`'s extrinsics: [4, 4] camera-to-world in OpenGL axes."""
    c2w = torch.linalg.inv(cam.world_to_cam.double())
    c2w[:3, 1:3] *= -1
    return c2w.float()


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> torch.Tensor:
    """World-to-camera [4, 4] (OpenCV axes) of a camera at ``eye`` looking at ``target``."""
    eye = torch.as_tensor(eye, dtype=torch.float64)
    target = torch.as_tensor(target, dtype=torch.float64)
    up = torch.as_tensor(up, dtype=torch.float64)
    z = target - eye
    z = z / z.norm()
    x = torch.linalg.cross(z, up)
    if x.norm() < 1e-8:  # looking along up: pick another up
        x = torch.linalg.cross(z, torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))
    x = x / x.norm()
    y = torch.linalg.cross(z, x)
    R = torch.stack([x, y, z])  # rows: camera axes in world
    w2c = torch.eye(4, dtype=torch.float64)
    w2c[:3, :3] = R
    w2c[:3, 3] = -R @ eye
    return w2c.float()


# a scene's up: a world axis by name (a scene's config, registration's style up)
UP_AXES = {"z": (0.0, 0.0, 1.0), "-z": (0.0, 0.0, -1.0), "y": (0.0, 1.0, 0.0), "-y": (0.0, -1.0, 0.0),
           "x": (1.0, 0.0, 0.0), "-x": (-1.0, 0.0, 0.0)}


def up_vector(up) -> torch.Tensor:
    """[3] unit vector of ``up``: a name of UP_AXES or a direction."""
    if isinstance(up, str):
        if up not in UP_AXES:
            raise ValueError(f"up must be one of {', '.join(UP_AXES)}, got '{up}'")
        up = UP_AXES[up]
    u = torch.as_tensor(up, dtype=torch.float64)
    if u.shape != (3,) or not bool(torch.isfinite(u).all()) or float(u.norm()) == 0:
        raise ValueError(f"up must be a non-zero 3-vector, got {up}")
    return u / u.norm()


def orbit_frame(up) -> torch.Tensor:
    """[3, 3] rows e1, e2, u: a right-handed frame whose third axis is ``up`` (:func:`up_vector`); for z up,
    the world axes x, y, z."""
    u = up_vector(up)
    a = torch.tensor([1.0, 0.0, 0.0] if abs(float(u[0])) < 0.9 else [0.0, 1.0, 0.0], dtype=torch.float64)
    e1 = a - (a @ u) * u
    e1 = e1 / e1.norm()
    return torch.stack([e1, torch.linalg.cross(u, e1), u])


def orbit_cameras(n: int, radius: float, width: int, height: int, fov_deg: float = 40.0,
                  elevations_deg: tuple[float, ...] = (20.0, 45.0), target=(0.0, 0.0, 0.0),
                  up=(0.0, 0.0, 1.0), phase_deg: float = 0.0) -> list[Camera]:
    """``n`` cameras on rings around ``target`` about the axis ``up`` (:func:`up_vector`; z by default),
    cycling through ``elevations_deg`` above the plane normal to it."""
    f = fov_to_focal(math.radians(fov_deg), width)
    cams = []
    t = torch.as_tensor(target, dtype=torch.float64)
    frame = orbit_frame(up)
    for i in range(n):
        az = math.radians(phase_deg + 360.0 * i / n)
        el = math.radians(elevations_deg[i % len(elevations_deg)])
        d = torch.tensor([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)], dtype=torch.float64)
        eye = t + radius * (d @ frame)
        cams.append(Camera(look_at(eye, t, frame[2]), f, f, width / 2.0, height / 2.0, width, height,
                           name=f"orbit_{i:03d}"))
    return cams


# ---- camera rigs fitted to a scene --------------------------------------------------------------


def scene_bounds(scene: GaussianScene, q: float = 0.005) -> tuple[torch.Tensor, float]:
    """Robust centre [3] and radius of a scene (:func:`wast3d.geometry.robust_bounds` of its means)."""
    return robust_bounds(scene.means, q)


def fit_orbit(scene: GaussianScene, n: int, width: int, height: int | None = None, fov_deg: float = 40.0,
              elevations_deg=(25.0, 45.0), margin: float = 0.95, phase_deg: float = 30.0, up="z") -> list[Camera]:
    """``n`` orbit cameras around the scene's centre, about its ``up`` (:func:`up_vector`), at a distance
    that frames it."""
    centre, radius = scene_bounds(scene)
    dist = margin * radius / math.sin(math.radians(fov_deg) / 2)
    return orbit_cameras(n, dist, width, height or width, fov_deg, tuple(elevations_deg),
                         tuple(centre.tolist()), up=up, phase_deg=phase_deg)
