"""Stage 1, regularized 3DGS pretraining from posed images (paper section 3.2, eq. 1 and 2).

Optimization as in 3DGS (Kerbl et al. 2023): ``L = (1 - lambda) L1 + lambda (1 - SSIM)`` with
lambda = 0.2, Adam with per-parameter learning rates, exponential decay of the position learning rate
(x0.01 over the run, scaled by the scene extent), SH degree raised by one every ``sh_every`` steps up
to ``sh_degree`` (0 is allowed: a scene without view dependence should use it).

Densification and pruning: gsplat's ``DefaultStrategy`` (clone, split, prune by opacity and size,
opacity reset), which is plain PyTorch and runs on CPU tensors: our rasterizer hands it the same
``means2d`` [1, N, 2] / ``radii`` [1, N, 2] layout as gsplat's. ``max_gaussians`` caps the count
(the lowest-opacity Gaussians beyond the cap are pruned after each refinement), so CPU runs stay
bounded.

The paper's regularizers, on the activated scales s = exp(log_scales) of each Gaussian:

- eq. 1, anisotropy: ``L_aniso = mean_i( max(max(s_i) / min(s_i), r) - r )``;
- eq. 2, uniform scale: ``L_unif = mean_i || s_i - (s_hat, s_hat, s_hat) ||^2``, with ``target_scale``
  s_hat given; else ``target_pixels`` times the training views' pixel footprint at the point they look
  at (the median over views of its distance over the focal length: the finest size the images
  resolve); else (both 0) the median of all scales at that step, detached, a pull towards one common
  size that does not fix its level; with ``unif_cap`` (ours) only the excess above s_hat counts,
  ``mean_i || max(s_i - s_hat, 0) ||^2``: a cap on size that leaves thin axes (a blade's width, a
  pebble's thickness) to the images, where the two-sided pull thickens them to s_hat;
- weights ``aniso_weight`` / ``unif_weight``; on for style scenes and off for content scenes by default
  (the paper regularizes style scenes);
- ours, not the paper's: binary opacity ``L_opa = mean_i o_i (1 - o_i)`` (weight ``opacity_weight``,
  with the regularizers, from the end of densification on, whose opacity resets it would fight).
  A trained surface is otherwise a stack of translucent layers whose colours (pink under green, say)
  sum to the right one only from the training views' side; a stylization wraps the style's elements
  around the content and shows them from every side, so those layers came out as haze and tints the
  style's renders never show (the demo's trained pebbles: median opacity 0.14). Opaque Gaussians are
  a surface from every side, as the procedural styles' discs are.

Initialization: a given point cloud / 3DGS PLY, or ``init_points`` random points in a cube around the
cameras' look-at centre of half-size ``init_extent`` (0: 0.35 x the camera distance, 1.41 for
NeRF-Synthetic, close to the reference's 1.3).

Checkpoints (every ``checkpoint_every`` steps, atomically) hold the parameters, optimizer and strategy
state, the step and every RNG state, so a resumed run equals an uninterrupted one with the same seed.
"""

from __future__ import annotations

import logging
import math
import random
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from .datasets import Dataset
from .gaussians import GaussianScene, num_sh_rest
from .options import checked, option
from .rasterizer import rasterize

log = logging.getLogger(__name__)


@dataclass
@checked("pretrain")
class PretrainConfig:
    iterations: int = option(5000, "optimization steps", minimum=0)
    sh_degree: int = option(0, "final spherical-harmonics degree", minimum=0)
    sh_every: int = option(1000, "raise the SH degree every this many steps", minimum=0)
    ssim_lambda: float = option(0.2, "weight of D-SSIM in the photometric loss", minimum=0)
    lr_means: float = option(1.6e-4, "position learning rate (times the scene extent)", minimum=0)
    lr_means_final_factor: float = option(0.01, "the position learning rate decays exponentially to this factor",
                                                minimum=0)
    lr_scales: float = option(5e-3, "Adam learning rate of the log-scales", minimum=0)
    lr_quats: float = option(1e-3, "Adam learning rate of the rotations", minimum=0)
    lr_opacities: float = option(5e-2, "Adam learning rate of the opacity logits", minimum=0)
    lr_sh0: float = option(2.5e-3, "Adam learning rate of the DC colour", minimum=0)
    lr_shN: float = option(2.5e-3 / 20, "Adam learning rate of the higher SH coefficients", minimum=0)
    init_points: int = option(20000, "random initial Gaussians (Blender data has no SfM points)", minimum=0,
                              maximum=1_000_000_000)
    init_extent: float = option(0.0, "half-size of the initial cube (0: from the cameras)", minimum=0)
    init_opacity: float = option(0.1, "initial opacity", minimum=0)
    max_gaussians: int = option(200_000, "cap of the densification", minimum=0, maximum=1_000_000_000)
    refine_start: int = option(300, "first densification step", minimum=0)
    refine_stop: int = option(0, "last densification step (0: 3/4 of iterations)", minimum=0)
    refine_every: int = option(100, "densification period", minimum=0)
    reset_every: int = option(3000, "opacity reset period", minimum=0)
    grow_grad2d: float = option(0.0002, "screen-space gradient above which a Gaussian is split or cloned", minimum=0)
    prune_opa: float = option(0.005, "prune Gaussians below this opacity", minimum=0)
    regularize: bool = option(False, "eq. 1-2 regularizers (unset: on for scenes used as styles, off otherwise)")
    aniso_weight: float = option(0.1, "weight of eq. 1 (anisotropy)", minimum=0)
    aniso_ratio: float = option(3.0, "r of eq. 1: the tolerated max/min scale ratio", minimum=0)
    unif_weight: float = option(100.0, "weight of eq. 2 (uniform scale)", minimum=0)
    opacity_weight: float = option(0.1, "ours, with the regularizers: weight of the binary-opacity term mean o (1 - o) "
                                        "from the end of densification on (opaque surface Gaussians, no translucent "
                                        "layers); 0: off", minimum=0)
    target_scale: float = option(0.0, "s_hat of eq. 2 (0: from target_pixels)", minimum=0)
    target_pixels: float = option(0.7, "s_hat of eq. 2 in pixel footprints of the training views at the point they look"
                                       " at (0, with target_scale 0: the detached median scale)", minimum=0)
    unif_cap: bool = option(False, "eq. 2 one-sided: only scales above s_hat are pulled down (thin axes left to the "
                                   "images)")
    checkpoint_every: int = option(1000, "checkpoint period (resume is bit-identical)", minimum=0)
    eval_every: int = option(0, "held-out evaluation period (0: only at the end)", minimum=0)
    seed: int = option(0, "seed")


# ---- losses ------------------------------------------------------------------------------------


def _gauss_1d(size: int = 11, sigma: float = 1.5, dtype=torch.float32) -> torch.Tensor:
    """[size] normalized Gaussian; the reference 3DGS code's 11x11 SSIM window is its outer product."""
    x = torch.arange(size, dtype=dtype) - size // 2
    g = torch.exp(-(x**2) / (2 * sigma**2))
    return g / g.sum()


def _gauss_blur(x: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """x: [1, C, H, W] -> the 2D Gaussian window's convolution with zero padding, as two 1D passes
    (the window is separable: 22 multiply-adds a pixel instead of 121)."""
    C, k = x.shape[1], len(g)
    x = F.conv2d(x, g.view(1, 1, 1, k).expand(C, 1, 1, k), padding=(0, k // 2), groups=C)
    return F.conv2d(x, g.view(1, 1, k, 1).expand(C, 1, k, 1), padding=(k // 2, 0), groups=C)


def ssim(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """SSIM of the reference 3DGS code (11x11 Gaussian window, sigma 1.5, zero padding); a, b: [H, W, 3]
    in [0, 1]. The five local moments are blurred in one call, each as two 1D passes."""
    x, y = a.permute(2, 0, 1)[None], b.permute(2, 0, 1)[None]
    m = _gauss_blur(torch.cat([x, y, x * x, y * y, x * y], 1), _gauss_1d(dtype=a.dtype).to(a.device))
    mu_x, mu_y, exx, eyy, exy = m.split(x.shape[1], 1)
    sxx, syy, sxy = exx - mu_x**2, eyy - mu_y**2, exy - mu_x * mu_y
    c1, c2 = 0.01**2, 0.03**2
    m = ((2 * mu_x * mu_y + c1) * (2 * sxy + c2)) / ((mu_x**2 + mu_y**2 + c1) * (sxx + syy + c2))
    return m.mean()


def psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    mse = float(((a - b) ** 2).mean())
    return 10 * math.log10(1.0 / max(mse, 1e-12))


def aniso_loss(log_scales: torch.Tensor, r: float) -> torch.Tensor:
    """Eq. 1: mean of max(max(s)/min(s), r) - r."""
    s = log_scales.exp()
    ratio = s.max(dim=1).values / s.min(dim=1).values
    return (ratio.clamp_min(r) - r).mean()


def unif_loss(log_scales: torch.Tensor, target: float = 0.0, cap: bool = False) -> torch.Tensor:
    """Eq. 2: mean of ||s - (t, t, t)||^2; t = median of all scales (detached) when target is 0.

    log_scales: [N, 3]. ``cap``: only the excess counts, ``mean ||max(s - t, 0)||^2`` (a size cap)."""
    s = log_scales.exp()
    t = s.detach().median() if target <= 0 else torch.as_tensor(target, dtype=s.dtype)
    d = (s - t).clamp_min(0) if cap else s - t
    return (d**2).sum(1).mean()


# ---- parameters ----------------------------------------------------------------------------------


def opacity_loss(opacity_logits: torch.Tensor) -> torch.Tensor:
    """``mean_i o_i (1 - o_i)``, o = sigmoid(logit): 0 when every Gaussian is opaque or gone."""
    o = torch.sigmoid(opacity_logits)
    return (o * (1 - o)).mean()


def to_params(scene: GaussianScene, sh_degree: int) -> torch.nn.ParameterDict:
    s = scene.with_sh_degree(sh_degree)
    return torch.nn.ParameterDict({
        "means": torch.nn.Parameter(s.means.float().clone()),
        "scales": torch.nn.Parameter(s.log_scales.float().clone()),
        "quats": torch.nn.Parameter(s.quats.float().clone()),
        "opacities": torch.nn.Parameter(s.opacity_logits.float().clone()),
        "sh0": torch.nn.Parameter(s.sh_dc[:, None, :].float().clone()),
        "shN": torch.nn.Parameter(s.sh_rest.float().clone()),
    })


def to_scene(params) -> GaussianScene:
    return GaussianScene(means=params["means"], log_scales=params["scales"], quats=params["quats"],
                         opacity_logits=params["opacities"], sh_dc=params["sh0"][:, 0], sh_rest=params["shN"])


def random_init(n: int, centre: torch.Tensor, extent: float, opacity: float, seed: int) -> GaussianScene:
    from .ply import init_from_points

    g = torch.Generator().manual_seed(seed)
    pts = centre.float() + (torch.rand(n, 3, generator=g) * 2 - 1) * extent
    rgb = torch.rand(n, 3, generator=g)
    return init_from_points(pts, rgb, opacity=opacity)


def look_at_centre(ds: Dataset) -> torch.Tensor:
    """Least-squares point closest to every camera's optical axis (the point the cameras look at)."""
    A = torch.zeros(3, 3, dtype=torch.float64)
    b = torch.zeros(3, dtype=torch.float64)
    for v in ds.all_views:
        c = v.camera.center.double()
        d = v.camera.world_to_cam[2, :3].double()
        d = d / d.norm()
        P = torch.eye(3, dtype=torch.float64) - d[:, None] * d[None, :]
        A += P
        b += P @ c
    return torch.linalg.lstsq(A, b[:, None]).solution[:, 0].float()


def pixel_footprint(ds: Dataset, centre: torch.Tensor) -> float:
    """The length one pixel covers at ``centre`` [3]: the median over the training views of its
    distance from the camera over the focal length (pixels)."""
    d = [float((v.camera.center - centre).norm()) / v.camera.fx for v in ds.train]
    return float(np.median(d)) if d else 0.0


# ---- training ----------------------------------------------------------------------------------


class Trainer:
    def __init__(self, ds: Dataset, cfg: PretrainConfig, init: GaussianScene | None = None):
        from gsplat.strategy import DefaultStrategy

        self.ds, self.cfg = ds, cfg
        torch.manual_seed(cfg.seed)
        random.seed(cfg.seed)
        np.random.seed(cfg.seed)
        cam_centre, cam_radius = ds.scene_center_radius()
        self.scene_scale = cam_radius
        self.centre = look_at_centre(ds)
        self.target_scale = cfg.target_scale or cfg.target_pixels * pixel_footprint(ds, self.centre)
        if cfg.regularize:
            log.info("pretrain: eq. 2's target scale %s", f"{self.target_scale:.4g}" if self.target_scale else "the median scale")
        if init is None:
            dist = float((torch.stack([v.camera.center for v in ds.all_views]) - self.centre).norm(dim=1).mean())
            ext = cfg.init_extent or 0.35 * dist
            init = random_init(cfg.init_points, self.centre, ext, cfg.init_opacity, cfg.seed)
        self.params = to_params(init, cfg.sh_degree)
        lrs = {"means": cfg.lr_means * self.scene_scale, "scales": cfg.lr_scales, "quats": cfg.lr_quats,
               "opacities": cfg.lr_opacities, "sh0": cfg.lr_sh0, "shN": cfg.lr_shN}
        self.optimizers = {k: torch.optim.Adam([{"params": self.params[k], "lr": lr, "name": k}], eps=1e-15)
                           for k, lr in lrs.items()}
        self.lr_means0 = lrs["means"]
        self.refine_stop = stop = cfg.refine_stop or int(cfg.iterations * 0.75)
        self.strategy = DefaultStrategy(refine_start_iter=cfg.refine_start, refine_stop_iter=stop,
                                        refine_every=cfg.refine_every, reset_every=cfg.reset_every,
                                        grow_grad2d=cfg.grow_grad2d, prune_opa=cfg.prune_opa)
        self.strategy.check_sanity(self.params, self.optimizers)
        self.state = self.strategy.initialize_state(scene_scale=self.scene_scale)
        self.step = 0
        self.gen = torch.Generator().manual_seed(cfg.seed)
        self.log_rows: list[dict] = []
        self.elapsed = 0.0

    # -- checkpointing --
    def state_dict(self) -> dict:
        return {"step": self.step, "params": {k: v.detach() for k, v in self.params.items()},
                "optimizers": {k: o.state_dict() for k, o in self.optimizers.items()},
                "strategy": self.state, "gen": self.gen.get_state(), "torch_rng": torch.get_rng_state(),
                "py_rng": random.getstate(), "np_rng": np.random.get_state(), "log": self.log_rows,
                "elapsed": self.elapsed, "config": asdict(self.cfg)}

    def save(self, path: Path) -> None:
        from .io_utils import atomic_path

        with atomic_path(path) as tmp:
            torch.save(self.state_dict(), tmp)

    def load(self, path: Path) -> None:
        """Resume from the checkpoint ``path``; where it was made with another configuration nothing is loaded
        (logged): the run starts over and overwrites it (the workflow re-runs a stage whose parameters
        changed, and an old run's checkpoint must not stop it)."""
        d = torch.load(path, weights_only=False)
        if d["config"] != asdict(self.cfg):
            now = asdict(self.cfg)
            diff = sorted(k for k in set(now) | set(d["config"]) if now.get(k) != d["config"].get(k))
            log.warning("%s: made with another configuration (%s differ); not resumed: training starts over",
                        path, ", ".join(diff))
            return
        for k, v in d["params"].items():
            self.params[k] = torch.nn.Parameter(v.clone())
        for k, o in self.optimizers.items():
            o.param_groups[0]["params"] = [self.params[k]]
            o.load_state_dict(d["optimizers"][k])
        self.state = d["strategy"]
        self.step = d["step"]
        self.gen.set_state(d["gen"])
        torch.set_rng_state(d["torch_rng"])
        random.setstate(d["py_rng"])
        np.random.set_state(d["np_rng"])
        self.log_rows = d["log"]
        self.elapsed = d["elapsed"]
        log.info("resumed from %s at step %d (%d Gaussians)", path, self.step, len(self.params["means"]))

    # -- one step --
    def sh_degree_now(self) -> int:
        return min(self.cfg.sh_degree, self.step // max(self.cfg.sh_every, 1))

    def train_step(self) -> dict:
        cfg = self.cfg
        i = int(torch.randint(len(self.ds.train), (1,), generator=self.gen))
        view = self.ds.train[i]
        scene = to_scene(self.params)
        out = rasterize(scene, view.camera, background=self.ds.background, sh_degree=self.sh_degree_now(),
                        full_means2d=True)
        self.strategy.step_pre_backward(self.params, self.optimizers, self.state, self.step, out.densify)
        img = out.rgb
        l1 = (img - view.image).abs().mean()
        s = ssim(img, view.image)
        loss = (1 - cfg.ssim_lambda) * l1 + cfg.ssim_lambda * (1 - s)
        terms = {"l1": l1.item(), "ssim": s.item()}
        if cfg.regularize:
            la = aniso_loss(self.params["scales"], cfg.aniso_ratio)
            lu = unif_loss(self.params["scales"], self.target_scale, cfg.unif_cap)
            loss = loss + cfg.aniso_weight * la + cfg.unif_weight * lu
            terms.update(aniso=la.item(), unif=lu.item())
            if cfg.opacity_weight > 0 and self.step >= self.refine_stop:
                lo = opacity_loss(self.params["opacities"])
                loss = loss + cfg.opacity_weight * lo
                terms["opacity"] = lo.item()
        loss.backward()
        frac = self.step / max(cfg.iterations, 1)
        self.optimizers["means"].param_groups[0]["lr"] = self.lr_means0 * cfg.lr_means_final_factor**frac
        for o in self.optimizers.values():
            o.step()
            o.zero_grad(set_to_none=True)
        self.strategy.step_post_backward(self.params, self.optimizers, self.state, self.step, out.densify, packed=False)
        self._cap()
        self.step += 1
        return {"loss": loss.item(), "psnr": psnr(img.detach().clamp(0, 1), view.image), **terms}

    def _cap(self) -> None:
        n = len(self.params["means"])
        if n <= self.cfg.max_gaussians:
            return
        from gsplat.strategy.ops import remove

        op = self.params["opacities"].detach()
        drop = torch.zeros(n, dtype=torch.bool)
        drop[torch.argsort(op)[: n - self.cfg.max_gaussians]] = True
        remove(self.params, self.optimizers, self.state, drop)

    def train(self, ckpt: Path | None = None, progress: bool = True, stop_at: int | None = None) -> None:
        """Train to ``cfg.iterations`` (resuming from ``ckpt`` when it exists); ``stop_at`` ends this call
        early at that step, as an interruption would (tests use it)."""
        from tqdm import tqdm

        cfg = self.cfg
        if ckpt is not None and ckpt.exists():
            self.load(ckpt)
        bar = tqdm(total=cfg.iterations, initial=self.step, desc="pretrain", disable=not progress, mininterval=2.0)
        t_last = time.perf_counter()
        end = cfg.iterations if stop_at is None else min(stop_at, cfg.iterations)
        while self.step < end:
            r = self.train_step()
            now = time.perf_counter()
            self.elapsed += now - t_last
            t_last = now
            row = {"iteration": self.step, "seconds": self.elapsed, "gaussians": len(self.params["means"]), **r}
            if cfg.eval_every and self.step % cfg.eval_every == 0:
                row.update({f"test_{k}": v for k, v in self.evaluate().items() if k in ("psnr", "ssim")})
                t_last = time.perf_counter()  # evaluation is not training time
            self.log_rows.append(row)
            bar.update(1)
            if self.step % 50 == 0:
                bar.set_postfix(psnr=f"{r['psnr']:.2f}", n=len(self.params["means"]))
            if ckpt is not None and cfg.checkpoint_every and self.step % cfg.checkpoint_every == 0:
                self.save(ckpt)
        bar.close()

    @torch.no_grad()
    def evaluate(self) -> dict:
        views = self.ds.test or self.ds.train
        scene = to_scene(self.params).detach()
        ps, ss = [], []
        for v in views:
            img = rasterize(scene, v.camera, background=self.ds.background, sh_degree=self.sh_degree_now()).rgb
            img = img.clamp(0, 1)
            ps.append(psnr(img, v.image))
            ss.append(float(ssim(img, v.image)))
        return {"psnr": float(np.mean(ps)), "ssim": float(np.mean(ss)), "views": len(views),
                "gaussians": len(self.params["means"]), "train_seconds": self.elapsed, "steps": self.step}

    def scene(self) -> GaussianScene:
        return to_scene(self.params).detach().with_sh_degree(self.cfg.sh_degree)


__all__ = ["PretrainConfig", "Trainer", "aniso_loss", "unif_loss", "ssim", "psnr", "num_sh_rest"]
