"""The I/O edge of every stage: read artifacts, call the pure stage functions, write artifacts.

Each ``run_*`` function is what one ``wast3d <stage>`` command (and one Snakemake rule) does; its
keywords are the stage's files as :mod:`wast3d.stages` declares them (``out_<name>`` for an output).
Stage parameters arrive as a dict (the rule's JSON ``--params``) and are checked by the stage's config
dataclass: an unknown key is an error naming the stage and the key.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from pathlib import Path
from typing import NamedTuple

import numpy as np
import pandas as pd
import torch

from .device import resolve_device
from .io_utils import atomic_path, load_npz, read_json, save_npz, write_json
from .options import make_config
from .ply import read_ply, write_ply

log = logging.getLogger(__name__)


def run_surface(*, scene: Path, out_ply: Path, out_json: Path, params: dict) -> None:
    from .surface import SurfaceConfig, surface_points

    cfg = make_config(SurfaceConfig, params, "surface")
    out, report = surface_points(read_ply(scene), cfg)
    report["source"] = str(scene)
    write_ply(out_ply, out)
    write_json(out_json, report)


def run_style_clean(*, scene: Path, out_ply: Path, out_json: Path, params: dict, labels_from: Path | None = None) -> None:
    """Clean a style scene with the style's rules (:func:`wast3d.surface.clean_style`); ``labels_from``: the
    labelled scene a trained style was rendered from (each Gaussian takes its nearest source's element)."""
    from .surface import StyleCleanConfig, clean_style

    cfg = make_config(StyleCleanConfig, params, "style_clean")
    source, scene = scene, read_ply(scene)
    if labels_from is not None:
        from .elements import transfer_elements

        src = read_ply(labels_from)
        if src.element is None:
            raise ValueError(f"{labels_from}: no property 'element' to take the labels from")
        scene.element = transfer_elements(scene.means, src.means, src.element)
    idx, report = clean_style(scene, cfg)
    report["source"] = str(source)
    report["labels_from"] = None if labels_from is None else str(labels_from)
    out = scene.subset(idx)
    if not report.get("skipped"):  # enabled: false is the style as it is: no refit, recolouring or dilation
        out = _finish_style(out, scene, cfg, report)
    if report.get("form") == "volume":
        from .volume import element_sheet, piece_size, volume_pieces

        report["elements_from"] = "labels" if out.element is not None else "pieces"
        if out.element is None:
            size = piece_size(out.means.detach().numpy())
            log.info("style form volume: no element labels: its elements are pieces about %.4g across (k-means on "
                     "position and colour)", size)
            out.element = torch.from_numpy(volume_pieces(out.means.detach().numpy(), out.rgb.detach().numpy()))
            report["piece_size"] = size
        try:
            out, report["sheet"] = element_sheet(out, cfg.seed)
        except ValueError as e:
            raise ValueError(f"{source}: read as a volume ({report['form_reason']}): {e}") from None
    if out.element is not None:
        report["element_share_of_gaussians"] = float((out.element > 0).double().mean())
    write_ply(out_ply, out)
    write_json(out_json, report)


def _finish_style(out, scene, cfg, report: dict):
    """The cleaned style ``out`` refitted, recoloured and dilated as ``cfg`` asks (each reported);
    ``scene`` is the style before cleaning (the refit's reference)."""
    from .surface import dilate_gaussians, in_patch, recolour_outliers, refit_appearance, shown_colours

    if cfg.refit > 0:
        out, report["refit"] = refit_appearance(out, scene.subset(in_patch(scene, cfg)), cfg.refit, cfg.views,
                                                cfg.resolution, cfg.seed, progress=True)
    if cfg.recolour > 0:
        shown = shown_colours(out, cfg.views, cfg.resolution) if cfg.shown_limit > 0 else None
        out, report["recoloured_colour_outliers"] = recolour_outliers(out, cfg.colour_k, cfg.recolour, shown,
                                                                      cfg.shown_limit)
    if cfg.dilate > 0:
        out, report["dilated_by"] = dilate_gaussians(out, cfg.dilate)
    return out


def run_cluster(*, content: Path, out_npz: Path, params: dict, out_picture: Path | None = None) -> None:
    from .clustering import ClusterConfig, cluster_content

    cfg = make_config(ClusterConfig, params, "cluster")
    content = read_ply(content)
    cl = cluster_content(content, cfg)
    labels = cl.labels.numpy()
    extra = {} if cl.normals is None else {"normals": cl.normals.numpy()}
    save_npz(out_npz, labels=labels, centroids=cl.centroids, sizes=np.bincount(labels), **extra)
    write_json(Path(out_npz).with_suffix(".json"), cl.info)
    if out_picture:
        from .figures import clusters_picture

        clusters_picture(content.means.numpy(), labels, out_picture, f"{cl.info['clusters']} clusters")


def _clusters(path: Path, n: int) -> dict[str, np.ndarray]:
    """The clusters file of a content scene of ``n`` Gaussians, its per-point arrays checked against n."""
    d = load_npz(path, required=("labels",))
    for key, shape in (("labels", (n,)), ("normals", (n, 3))):
        if key in d and d[key].shape != shape:
            raise ValueError(f"{path}: '{key}' has shape {d[key].shape} but the content scene has {n} Gaussians "
                             f"(expected {shape}; the clusters were made for another content scene)")
    return d


def _labels(path: Path, n: int) -> torch.Tensor:
    return torch.from_numpy(_clusters(path, n)["labels"]).long()


def is_sheet(style_form: Path | None) -> bool:
    """Whether the style stage's report (``style_form``; None: a style without one, a patch) read the
    style as a volume and laid it out as an element sheet."""
    return style_form is not None and read_json(style_form).get("form") == "volume"


def run_register(*, content: Path, clusters: Path, style: Path, out_npz: Path, params: dict,
                 region: Path | None = None, out_picture: Path | None = None, style_form: Path | None = None) -> None:
    from .registration import RegistrationConfig, element_size_report, register

    cfg = make_config(RegistrationConfig, params, "register")
    style_path, content, style = style, read_ply(content), read_ply(style)
    cl = _clusters(clusters, len(content))
    labels, normals = torch.from_numpy(cl["labels"]).long(), cl.get("normals")
    reg = register(content.means, labels, style.means, cfg,
                   normals=None if normals is None else torch.from_numpy(normals),
                   diameter=_region_diameter(region) if region else None, sheet=is_sheet(style_form))
    save_npz(out_npz, **reg.to_npz())
    size = element_size_report(reg, cfg.scale_range)
    (log.warning if abs(math.log(size["median"])) > math.log(1.2) else log.info)(  # a fifth off: say it louder
        "registration: %s's elements come out a median %.2fx (10-90 %%: %.2f-%.2fx) the size s0 asks; eq. 7's "
        "scale moves within register.scale_range %.3g (%.0f %% of clusters at a bound in the style's plane)",
        style_path, size["median"], size["p10"], size["p90"], cfg.scale_range, 100 * size["clusters_at_scale_bound"])
    write_json(Path(out_npz).with_suffix(".json"), {
        "clusters": len(reg.R), "s0": reg.s0, "style_spacing": reg.style_spacing,
        "residual_init_mean": float(reg.residual_init.mean()), "residual_mean": float(reg.residual.mean()),
        "residual_quantiles": {q: float(torch.quantile(reg.residual, q)) for q in (0.05, 0.5, 0.95)},
        "units": "mean nearest-style-neighbour distance / mean style spacing",
        "element_size_factor": size})
    if out_picture:
        from .figures import registration_picture

        mapped = reg.apply(content.means.double(), labels)
        panels = []
        for i in np.linspace(0, len(reg.R) - 1, min(6, len(reg.R))).astype(int):
            m = mapped[labels == i]
            c, r = m.mean(0), float((m - m.mean(0)).norm(dim=1).max()) * 1.5 + 1e-9
            near = ((style.means.double() - c).norm(dim=1) < r)
            panels.append((m.numpy(), style.means[near].numpy(), style.rgb[near].numpy()))
        registration_picture(panels, out_picture)


def _region_diameter(path: Path) -> float:
    """The whole content's diameter a region's JSON (region-content) gives; errors name the file."""
    d = read_json(path).get("content_diameter")
    if not isinstance(d, (int, float)) or not math.isfinite(d) or d <= 0:
        raise ValueError(f"{path}: 'content_diameter' must be a positive number, got {d!r}")
    return float(d)


def load_registration(path: Path):
    """The :class:`~wast3d.registration.Registration` in ``path``; errors name the file."""
    from .registration import Registration

    d = load_npz(path)  # names the file when it is missing or unreadable
    try:
        return Registration.from_npz(d)
    except ValueError as e:
        raise ValueError(f"{path}: {e}") from None


def run_select(*, content: Path, clusters: Path, style: Path, registration: Path, out_npz: Path, params: dict) -> None:
    from .selection import SelectConfig, select_style

    cfg = make_config(SelectConfig, params, "select")
    k = cfg.k
    content, style = read_ply(content), read_ply(style)
    labels = _labels(clusters, len(content))
    sel = select_style(cfg, content, labels, style, load_registration(registration))
    sizes = sel.sizes.numpy()
    if (sizes == 0).any():
        log.warning("select: %d clusters got no style Gaussians (they are skipped by stylize)", int((sizes == 0).sum()))
    thinned = int((sel.log_gain != 0).sum())
    if thinned:
        log.info("select: %d of %d clusters had more than max_per_point %g style Gaussians per content point; each "
                 "kept a uniform subset, enlarged by a median %.2fx", thinned, len(sizes), cfg.max_per_point,
                 float(sel.log_gain[sel.log_gain != 0].exp().median()))
    else:
        log.info("select: no cluster over max_per_point %g style Gaussians per content point; nothing thinned",
                 cfg.max_per_point)
    save_npz(out_npz, offsets=sel.offsets.numpy(), indices=sel.indices.numpy(), sizes=sizes, k=k,
             log_gain=sel.log_gain.numpy())
    write_json(Path(out_npz).with_suffix(".json"), {"k": k, "mode": cfg.mode, "radius": cfg.radius, "extent": cfg.extent,
                                                    "max_per_point": cfg.max_per_point, "clusters_thinned": thinned,
                                                    "clusters": len(sizes), "selected_total": int(sizes.sum()),
                                                    "size_min": int(sizes.min()), "size_median": float(np.median(sizes)),
                                                    "size_max": int(sizes.max())})


def run_stylize(*, content: Path, clusters: Path, style: Path, registration: Path, selection: Path,
                out_ply: Path, out_npz: Path, out_csv: Path, params: dict, progress: bool = True,
                style_form: Path | None = None) -> None:
    from .selection import Selection
    from .stylize import StylizeConfig, stylize

    cfg = make_config(StylizeConfig, params, "stylize")
    content, style = read_ply(content), read_ply(style)
    labels = _labels(clusters, len(content))
    reg = load_registration(registration)
    sel_npz = selection
    sel = load_npz(sel_npz, required=("offsets", "indices"))
    if int(sel["indices"].max(initial=0)) >= len(style):
        raise ValueError(f"{sel_npz}: 'indices' point past the style scene's {len(style)} Gaussians")
    K = len(sel["offsets"]) - 1
    gain = sel["log_gain"] if "log_gain" in sel else np.zeros(K)  # selections written before the cap have none
    if len(gain) != K or not np.isfinite(gain).all():
        raise ValueError(f"{sel_npz}: 'log_gain' must hold {K} finite values (one per cluster)")
    selection = Selection(torch.from_numpy(sel["offsets"]), torch.from_numpy(sel["indices"]),
                          torch.from_numpy(np.asarray(gain, dtype=np.float64)))
    sheet = is_sheet(style_form)
    res = stylize(content, labels, style, reg, selection, cfg, progress, sheet=sheet)
    out, curves, secs = res.scene, res.curves, res.seconds
    write_ply(out_ply, out)
    # each cluster's element size against the one scale s0 (below 1 where follow_thickness shrinks them)
    save_npz(out_npz, labels=res.labels.numpy(), before_means=res.before_means.numpy(), source=res.source.numpy(),
             size_factor=(float(reg.s0) / reg.base.double()).numpy())
    rows = [{"cluster": i, "iteration": j, "loss": v} for i, c in enumerate(curves) for j, v in enumerate(c)]
    with atomic_path(out_csv) as tmp:
        pd.DataFrame(rows).to_csv(tmp, index=False)
    from .figures import loss_curves_picture

    loss_curves_picture(curves, Path(out_csv).with_suffix(".png"), f"{cfg.loss}, {cfg.features}, {len(curves)} clusters")
    write_json(Path(out_csv).with_suffix(".json"), {
        "clusters": len(curves), "gaussians": len(out), "seconds_total": float(sum(secs)),
        "seconds_per_cluster_step": float(sum(secs) / max(1, sum(len(c) for c in curves))),
        "loss_first_mean": float(np.mean([c[0] for c in curves])) if curves and curves[0] else None,
        "loss_last_mean": float(np.mean([c[-1] for c in curves])) if curves and curves[0] else None,
        "device": str(resolve_device(cfg.device)), "config": dataclasses.asdict(cfg)})


def run_rescale(*, stylized: Path, stylize_npz: Path, out_ply: Path, params: dict) -> None:
    from .rescale import RescaleConfig, rescale

    cfg = make_config(RescaleConfig, params, "rescale")
    scene = read_ply(stylized)
    d = load_npz(stylize_npz, required=("labels", "before_means"))
    out, ratio = rescale(scene, torch.from_numpy(d["before_means"]), torch.from_numpy(d["labels"]), cfg)
    write_ply(out_ply, out)
    if ratio is None:
        log.info("scale readjustment disabled: the stylized scene is passed through")
        write_json(Path(out_ply).with_suffix(".json"), {"skipped": True, "reason": "rescale.enabled is false"})
        return
    write_json(Path(out_ply).with_suffix(".json"), {
        "ratio_quantiles": {q: float(torch.quantile(ratio, q)) for q in (0.05, 0.5, 0.95)},
        "at_bound": float(((ratio <= 1 / cfg.bound + 1e-9) | (ratio >= cfg.bound - 1e-9)).double().mean())})


def run_pretrain(*, data: Path, out_ply: Path, out_csv: Path, out_json: Path, params: dict,
                 checkpoint: Path | None = None, init: Path | None = None, progress: bool = True) -> None:
    """Train a 3DGS scene from a Blender-format folder; ``holdout_every``/``background``/``max_views``
    select the data, the rest are :class:`wast3d.pretrain.PretrainConfig` fields."""
    from .datasets import load_blender
    from .pretrain import PretrainConfig, Trainer

    params = dict(params)
    sel = {k: params.pop(k) for k in ("holdout_every", "background", "max_views") if k in params}
    cfg = make_config(PretrainConfig, params, "pretrain")
    ds = load_blender(data, holdout_every=sel.get("holdout_every", 8),
                      background=tuple(sel.get("background", (1.0, 1.0, 1.0))), max_views=sel.get("max_views"))
    tr = Trainer(ds, cfg, read_ply(init) if init else None)
    tr.train(checkpoint, progress=progress)
    ev = tr.evaluate()
    write_ply(out_ply, tr.scene())
    with atomic_path(out_csv) as tmp:
        pd.DataFrame(tr.log_rows).to_csv(tmp, index=False)
    write_json(out_json, {**ev, "config": dataclasses.asdict(cfg), "data": str(data),
                          "train_views": len(ds.train), "test_views": len(ds.test)})
    log.info("pretrain: %d Gaussians, held-out PSNR %.2f dB, SSIM %.4f, %.0f s", ev["gaussians"], ev["psnr"],
             ev["ssim"], ev["train_seconds"])


# ---- stages 7-9: rendering, evaluation, baselines ---------------------------------------------


def run_render(*, scene: Path, reference: Path, out_folder: Path, params: dict, progress: bool = True) -> None:
    """Turntable, key views and close-up of a scene, with cameras fitted to ``reference`` and turning about
    its up (``params["up"]``: the reference scene's, ``scenes.NAME.up``; z when not given)."""
    from .render import RenderConfig, render_turntable

    params = dict(params)
    up = params.pop("up", "z")
    cfg = make_config(RenderConfig, params, "render")
    s = read_ply(scene)
    ref = s if Path(reference) == Path(scene) else read_ply(reference)
    info = render_turntable(s, ref, out_folder, cfg, progress, up)
    log.info("render: %s -> %s (%d frames about up %s, fragment at pixel %s)", scene, out_folder, info["frames"], up,
             info["fragment_pixel"])


def run_texture_reference(*, style: Path, content: Path, out_folder: Path, params: dict, progress: bool = True,
                          registration: Path | None = None, style_form: Path | None = None) -> None:
    """The style's frames at the pixel scale its elements have on renders fitted to the content
    (:func:`~wast3d.render.texture_reference_cameras`, with the clusters' median base scale in
    ``registration``: s0, or the elements' typical size where ``follow_thickness`` shrinks them);
    ``params``: the render block, and ``up``: the style scene's up (z when not given). Where the style has
    a relief, ``segments.npz`` beside the frames holds its label-free elements, which ``segment_whole``
    and ``segment_intact`` read (:mod:`wast3d.elements`): ``segments`` [M], the relief's basins
    (:func:`~wast3d.registration.relief_basins`, one per dome of its top surface), or on a volume's
    element sheet (``style_form``: the style stage's report) its laid-out elements, which the style
    stage made from labels or, without, from label-free pieces (:mod:`wast3d.volume`)."""
    from .registration import relief_basins, relief_length
    from .render import RenderConfig, render_texture_reference

    params = dict(params)
    up = params.pop("up", "z")
    cfg = make_config(RenderConfig, params, "render")
    style_ply, style = style, read_ply(style)
    reg = None if registration is None else load_registration(registration)
    s0, length = None if reg is None else reg.s0, None
    if reg is not None:
        try:  # one relief length of the style, in content units: the coarse Chamfer's smoothing length
            length = relief_length(style.means, up=reg.style_up.tolist()) / s0
        except ValueError as e:
            log.warning("texture reference: %s: no element length (%s); the coarse Chamfer will not be computed",
                        style_ply, e)
    # the elements' typical size on the content: s0, or smaller where follow_thickness shrinks most clusters'
    scale = None if reg is None else float(reg.base.double().median())
    info = render_texture_reference(style, read_ply(content), out_folder, cfg, progress, scale, length, up,
                                    size_factor=1.0 if reg is None else float(reg.s0) / scale)
    sheet = is_sheet(style_form)
    if sheet and style.element is None:
        raise ValueError(f"{style_ply}: a volume's element sheet ({style_form}) without element labels")
    if sheet:  # the elements the style stage laid out, one segment each
        segments = torch.unique(style.element.long(), return_inverse=True)[1]
        how = "laid-out elements of the volume's sheet"
    elif length is not None:
        segments, how = relief_basins(style.means, reg.style_up.tolist(), length * s0), "relief basins"
    if sheet or length is not None:  # the style's own elements, label-free: the element metrics' segments
        save_npz(Path(out_folder) / "segments.npz", segments=segments.numpy(), how=how)
        log.info("texture reference: %d segments (%s) of %s", int(segments.max()) + 1, how, style_ply)
    log.info("texture reference: %s at zoom %.3f (cameras fitted to it, its elements at their size on %s) -> %s",
             style_ply, info["zoom"], content, out_folder)


def run_colour_transfer(*, content: Path, style: Path, out_ply: Path, params: dict) -> None:
    """Baseline: the content with its colours mapped to the style's by entropic OT."""
    import time

    from .baselines import ColourTransferConfig, colour_transfer

    cfg = make_config(ColourTransferConfig, params, "colour_transfer")
    content, style = read_ply(content), read_ply(style)
    t = time.perf_counter()
    out = colour_transfer(content, style, cfg)
    secs = time.perf_counter() - t
    write_ply(out_ply, out)
    write_json(Path(out_ply).with_suffix(".json"), {"method": "colour_ot", "seconds": secs, "device": str(out.means.device),
                                                    "gaussians": len(out), "config": dataclasses.asdict(cfg)})


def coarse_shape(result, content, texture_reference: Path, cfg) -> dict:
    """``coarse_chamfer`` of :mod:`wast3d.metrics` and its smoothing length: ``metrics.coarse_scale`` x
    the content's diameter if set, else the style's element length that the texture reference recorded."""
    from .geometry import robust_bounds
    from .metrics import coarse_chamfer

    if cfg.coarse_scale > 0:
        length, source = cfg.coarse_scale * 2 * robust_bounds(content.means)[1], "metrics.coarse_scale"
    else:
        info = read_json(Path(texture_reference) / "render.json")
        length, source = info.get("element_length"), f"{texture_reference}/render.json element_length"
        if length is None:
            why = f"not computed: {texture_reference}/render.json has no element_length (a flat style, or no registration)"
            log.warning("evaluate: coarse Chamfer %s", why)
            return {"coarse_chamfer": None, "coarse_length": None, "coarse_status": why}
    value = coarse_chamfer(result.means, content.means, float(length), cfg.coarse_support, cfg.seed)
    return {"coarse_chamfer": value, "coarse_length": float(length), "coarse_status": f"computed, length from {source}"}


def element_coverage(frames: torch.Tensor, reference: torch.Tensor, content, content_render: Path,
                     length: float | None) -> dict:
    """``coverage_element``: :func:`~wast3d.image_metrics.coverage_at_scale` with the result's gaps
    narrower than one style element closed (``length``: the coarse Chamfer's element length, content
    units; the radius in pixels per view at the content's centre, cameras from ``content_render``)."""
    from .image_metrics import coverage_at_scale, projected_radii

    if length is None:
        return {"coverage_element": None}
    info = read_json(Path(content_render) / "render.json")
    cams = info.get("cameras")
    if not isinstance(cams, list) or len(cams) < len(frames):
        raise ValueError(f"{content_render}/render.json: 'cameras' must list the {len(frames)} frames' cameras")
    radii = projected_radii(cams[:len(frames)], content.means.double().median(0).values, length)
    return {"coverage_element": coverage_at_scale(frames[..., 3], reference[..., 3], radii)}


def piece_weight(d, stylize_npz: Path, texture_reference: Path) -> torch.Tensor | None:
    """What a pixel of each result Gaussian's element copy counts in ``element_whole`` (:mod:`wast3d.elements`):
    (f_ref / f_k)^2 for a Gaussian of cluster k, f the ``size_factor`` [K] the stylize stage wrote, f_ref the
    texture reference's (its ``render.json``): a copy made smaller on purpose counts at the reference's
    size. None where every ratio is 1 (or the stylize file predates the factors)."""
    if "size_factor" not in d:
        return None
    f, labels = np.asarray(d["size_factor"], dtype=np.float64), np.asarray(d["labels"])
    if not (np.isfinite(f).all() and (f > 0).all()) or (len(labels) and int(labels.max()) >= len(f)):
        raise ValueError(f"{stylize_npz}: 'size_factor' must hold a finite value > 0 for each of the "
                         f"{int(labels.max(initial=-1)) + 1} clusters")
    ref = read_json(Path(texture_reference) / "render.json").get("size_factor", 1.0)
    if not isinstance(ref, (int, float)) or not math.isfinite(ref) or ref <= 0:
        raise ValueError(f"{texture_reference}/render.json: 'size_factor' must be a number > 0, got {ref!r}")
    w = (ref / f) ** 2
    return None if np.allclose(w, 1.0) else torch.from_numpy(w[labels])


def evaluate_elements(result, style, frames: torch.Tensor, result_render: Path, style_frames: torch.Tensor,
                      texture_reference: Path, stylize_npz: Path | None, cfg) -> dict:
    """The element metrics of one result (:mod:`wast3d.elements`): ``element_share`` and ``element_whole``
    of the result's turntable (``frames``, cameras in ``result_render``) against the style's texture
    reference (``style_frames``, read from ``texture_reference``), and ``element_intact`` against the
    collage (the positions before optimization in ``stylize_npz``)."""
    from .elements import copy_ids, element_intact, element_share, element_whole, share_blind
    from .render import element_pieces, read_cameras, read_element_frames

    out = {"element_share": None, "element_share_style": None, "element_share_ratio": None, "element_intact": None,
           "element_whole": None, "element_whole_style": None, "element_whole_ratio": None}
    style_el = read_element_frames(texture_reference)
    if style.element is None or style_el is None:
        return {**out, "element_status": "not computed: the style has no element labels"}
    out["element_share_style"] = element_share(style_el, style_frames[..., 3], cfg.min_alpha)
    out["element_whole_style"] = element_whole(element_pieces(
        style, torch.where(style.element > 0, style.element.long(), -1), read_cameras(texture_reference, len(style_frames)),
        cfg.piece_tol, cfg.min_alpha))
    res_el = read_element_frames(result_render)
    # an unlabelled result (the content, a colour transfer) has no Gaussian of the style: no element pixel
    out["element_share"] = 0.0 if res_el is None else element_share(res_el, frames[..., 3], cfg.min_alpha)
    blind = share_blind(style.element)
    out["element_share_ratio"] = None if blind else out["element_share"] / max(out["element_share_style"], 1e-12)
    status = f"share ratio not valid: {blind}" if blind else "share computed"
    clusters, weight = None, None
    if stylize_npz is not None and result.element is not None:
        d = load_npz(stylize_npz, required=("labels", "before_means"))
        weight = piece_weight(d, stylize_npz, texture_reference)
        if len(d["labels"]) != len(result):
            raise ValueError(f"{stylize_npz}: 'labels' has {len(d['labels'])} entries, the result {len(result)} Gaussians")
        clusters = torch.from_numpy(d["labels"])
        intact = element_intact(torch.from_numpy(d["before_means"]), result.means, copy_ids(result.element, clusters), cfg)
        out["element_intact"] = intact.pop("intact")
        out["element_intact_detail"] = intact
        status += ", intact computed"
    else:
        status += "; intact not computed (no stylized elements)"
    if out["element_whole_style"]:
        whole = 0.0  # no copy of an element (the content, a colour transfer): no piece
        if result.element is not None:
            # a result's copies: one element selected by one cluster (one copy per element without clusters)
            copies = (copy_ids(result.element, clusters) if clusters is not None
                      else torch.where(result.element > 0, result.element.long(), -1))
            whole = element_whole(element_pieces(result, copies, read_cameras(result_render, len(frames)),
                                                 cfg.piece_tol, cfg.min_alpha, weight)) or 0.0
        out["element_whole"] = whole
        out["element_whole_ratio"] = whole / out["element_whole_style"]
        status += ", whole computed"
    return {**out, "element_status": status}


class StyleSegments(NamedTuple):
    """The style's label-free elements (:func:`style_segments`)."""

    file: Path  # the texture reference's segments.npz
    segments: torch.Tensor | None  # [M] long: the segment of each of the style's M Gaussians; None: no file
    how: str | None  # how they were made (relief basins of a patch, laid-out elements of a sheet)


def style_segments(texture_reference: Path, style) -> StyleSegments:
    """The style's label-free elements that the texture reference wrote (:func:`run_texture_reference`),
    ``segments`` None where it wrote none. A file that does not number the style's Gaussians is an error
    naming it."""
    seg_file = Path(texture_reference) / "segments.npz"
    if not seg_file.exists():
        return StyleSegments(seg_file, None, None)
    seg_npz = load_npz(seg_file, required=("segments",))
    segments = torch.from_numpy(seg_npz["segments"]).long()
    if len(segments) != len(style):
        raise ValueError(f"{seg_file}: 'segments' has {len(segments)} entries, the style {len(style)} Gaussians")
    return StyleSegments(seg_file, segments, str(seg_npz["how"]) if "how" in seg_npz else "relief basins")


def evaluate_whole_elements(result, style, texture_reference: Path, cfg) -> dict:
    """``element_colour_w1`` and ``element_thickness_w1`` (:func:`wast3d.metrics.element_metrics`) at the
    style's element size: the median Gaussians per segment of ``texture_reference``/segments.npz."""
    from .metrics import element_metrics

    seg = style_segments(texture_reference, style)
    if seg.segments is None:
        return {"element_colour_w1": None, "element_thickness_w1": None,
                "whole_status": f"not computed: {seg.file} does not exist (no element size: a texture reference "
                                "without a registration, or a style without relief)"}
    counts = np.bincount(seg.segments.numpy())
    n_e = int(np.median(counts[counts > 0]))
    return {**element_metrics(result, style, n_e, cfg),
            "whole_status": f"computed at {n_e} Gaussians per element (the median of {seg.file})"}


def evaluate_segments(result, style, n_frames: int, result_render: Path, n_style: int, texture_reference: Path,
                      stylize_npz: Path | None, cfg) -> dict:
    """The label-free element metrics of one result (``segment_whole``, ``segment_intact``,
    :mod:`wast3d.elements`): the style's segments from ``texture_reference``/segments.npz, each result
    Gaussian's from the style Gaussian it copies (``source`` in ``stylize_npz``); the result's ``n_frames``
    turntable views against the texture reference's ``n_style``. No stylize_npz (the content, a colour
    transfer): no copy of the style, 0."""
    from .elements import element_intact, element_whole, segment_copies
    from .render import element_pieces, read_cameras

    out = {"segment_whole": None, "segment_whole_style": None, "segment_whole_ratio": None, "segment_intact": None}
    seg = style_segments(texture_reference, style)
    if seg.segments is None:
        return {**out, "segment_status": f"not computed: {seg.file} does not exist "
                                         "(a texture reference without a registration, or a style without relief)"}
    segments, how = seg.segments, seg.how
    style_whole = element_whole(element_pieces(style, segments, read_cameras(texture_reference, n_style),
                                               cfg.piece_tol, cfg.min_alpha))
    out["segment_whole_style"] = style_whole
    if stylize_npz is None:
        whole = 0.0 if style_whole else None
        return {**out, "segment_whole": whole, "segment_whole_ratio": whole,
                "segment_status": "no copy of a style Gaussian (not a stylized result): whole 0"}
    d = load_npz(stylize_npz, required=("labels", "before_means"))
    if "source" not in d:
        return {**out, "segment_status": f"not computed: {stylize_npz} has no 'source' (written by an older wast3d: "
                                         "run the stylize stage again)"}
    for key in ("labels", "before_means", "source"):
        if len(d[key]) != len(result):
            raise ValueError(f"{stylize_npz}: '{key}' has {len(d[key])} entries, the result {len(result)} Gaussians")
    copies = segment_copies(segments, torch.from_numpy(d["source"]), torch.from_numpy(d["labels"]))
    out["segment_intact"] = element_intact(torch.from_numpy(d["before_means"]), result.means, copies, cfg)["intact"]
    if style_whole:
        whole = element_whole(element_pieces(result, copies, read_cameras(result_render, n_frames), cfg.piece_tol,
                                             cfg.min_alpha, piece_weight(d, stylize_npz, texture_reference))) or 0.0
        out.update(segment_whole=whole, segment_whole_ratio=whole / style_whole)
    return {**out, "segment_status": f"{int(segments.max()) + 1} segments ({how})"}


def run_evaluate(*, result: Path, content: Path, style: Path, result_render: Path, style_render: Path,
                 texture_reference: Path, content_render: Path, out_json: Path, params: dict,
                 stylize_npz: Path | None = None) -> None:
    """Weights-free metrics, texture SWD, coverage and CLIP crop similarity of one result; ``params``:
    ``metrics``, ``texture``, ``crops`` and ``clip`` blocks (:class:`~wast3d.metrics.MetricsConfig`,
    :class:`~wast3d.image_metrics.TextureConfig`, :class:`~wast3d.clip_eval.CropConfig`,
    :class:`~wast3d.clip_eval.ClipConfig`). ``style_render``: the style's turntable (CLIP crops);
    ``texture_reference``: the style at the result's pixel scale (:func:`run_texture_reference`, texture
    SWD); ``content_render``: the unstylized content's render with the same cameras (coverage)."""
    from .clip_eval import ClipUnavailable, clip_similarity, load_clip, random_crops
    from .image_metrics import coverage, texture_levels
    from .metrics import weights_free_metrics
    from .render import read_frames
    from .stages import stage_configs

    cfgs = stage_configs("evaluate", params)  # block name -> its config
    mcfg, tcfg, ccfg, kcfg, ecfg = (cfgs[k] for k in ("metrics", "texture", "crops", "clip", "elements"))
    result_ply, style_ply, content_ply = result, style, content
    result, style, content = read_ply(result_ply), read_ply(style_ply), read_ply(content_ply)
    for path, scene in ((result_ply, result), (style_ply, style), (content_ply, content)):
        if len(scene) < 2:
            raise ValueError(f"{path}: {len(scene)} Gaussian(s); the metrics need at least 2")
    out = weights_free_metrics(result, content.means, style, mcfg)
    out.update(coarse_shape(result, content, texture_reference, mcfg))
    out.update({"clip_similarity": None, "clip_status": "", "clip_model": kcfg.model})
    frames = read_frames(result_render)
    reference = read_frames(content_render)
    if frames.shape != reference.shape:
        raise ValueError(f"{result_render}: frames {list(frames.shape)} differ from the content render "
                         f"{content_render} {list(reference.shape)}; render both with the same settings")
    out["coverage"] = coverage(frames[..., 3], reference[..., 3])
    out.update(element_coverage(frames, reference, content, content_render, out["coarse_length"]))
    texture_frames = read_frames(texture_reference)  # a missing or corrupt reference is an error, not a result
    out.update(evaluate_elements(result, style, frames, result_render, texture_frames, texture_reference, stylize_npz,
                                 ecfg))
    out.update(evaluate_segments(result, style, len(frames), result_render, len(texture_frames), texture_reference,
                                 stylize_npz, ecfg))
    out.update(evaluate_whole_elements(result, style, texture_reference, mcfg))
    try:
        tex = texture_levels(frames, texture_frames, tcfg)
        out["texture_swd"] = tex["texture_swd"]
        out["texture_levels"] = tex["levels"]
        left = [f"level {r['level']} ({r['result_windows']} result / {r['style_windows']} style reference windows)"
                for r in tex["levels"] if r["swd"] is None]
        out["texture_status"] = "computed" + (f"; left out (< {tcfg.min_windows} windows): {', '.join(left)}" if left else "")
        if left:
            log.info("evaluate: texture SWD %s", out["texture_status"])
    except ValueError as e:  # a collapsed or scattered result (e.g. entropic OT without debiasing) is a
        # result, not bad input: it gets no texture metric, and the table says why
        out.update({"texture_swd": None, "texture_status": f"not computed: {result_render}: {e}"})
        log.warning("evaluate: texture SWD not computed: %s", e)
    crops_b, _ = random_crops(read_frames(style_render), ccfg)
    try:
        crops_a, _ = random_crops(frames, ccfg)
    except ValueError as e:
        crops_a = None
        why = f"not computed: {result_render}: no crop with mean alpha >= {ccfg.min_alpha} ({e}; coverage {out['coverage']:.3f})"
        log.warning("evaluate: CLIP similarity %s", why)
        out["clip_status"] = why
    out["crops"] = {"result": 0 if crops_a is None else len(crops_a), "style": len(crops_b), "size": ccfg.size,
                    "seed": ccfg.seed, "min_alpha": ccfg.min_alpha}
    if crops_a is not None:
        try:
            model = load_clip(kcfg)
        except ClipUnavailable as e:
            out["clip_status"] = f"not computed: {e}"
            log.warning("evaluate: CLIP similarity not computed: %s", e)
        else:
            out["clip_similarity"] = clip_similarity(model, crops_a, crops_b, kcfg.batch, kcfg.device)
            out["clip_status"] = "computed"
    out.update({"result": str(result_ply), "content": str(content_ply), "style": str(style_ply),
                "config": {k: dataclasses.asdict(c) for k, c in cfgs.items()}})
    write_json(out_json, out)


# ---- several styles on one content, by region (wast3d/regions.py) ---------------------------------


def run_regions(*, content: Path, out_npz: Path, params: dict, scene: Path | None = None,
                out_picture: Path | None = None) -> None:
    """Each content point's region; ``params["regions"]``: the set's entries (:func:`wast3d.regions.parse_set`),
    ``scene``: the content scene the ``labels`` regions' files number (each point takes its nearest
    Gaussian's label)."""
    from .regions import assign, nearest_labels, parse_set, read_labels

    regions = parse_set(params.get("regions"), "regions")
    pts = read_ply(content)
    x = pts.means.double().numpy()
    scene_labels = None
    labelled = [r for r in regions if r.kind == "labels"]
    if labelled:
        if scene is None:
            raise ValueError("regions: a labels region needs the content scene its file numbers (--scene)")
        sc = read_ply(scene)
        lab = read_labels(labelled[0].spec["path"], len(sc))
        if any(r.spec["path"] != labelled[0].spec["path"] for r in labelled):
            raise ValueError("regions: the labels regions of one set read one label file")
        scene_labels = nearest_labels(x, sc.means.double().numpy(), lab)
    region = assign(x, pts.rgb.double().numpy(), regions, scene_labels)
    counts = np.bincount(region, minlength=len(regions))
    save_npz(out_npz, region=region, styles=np.array([r.style for r in regions]))
    write_json(Path(out_npz).with_suffix(".json"), {
        "regions": [{"style": r.style, "kind": r.kind, **r.spec, "points": int(c)} for r, c in zip(regions, counts)],
        "points": len(x)})
    log.info("regions: %s", ", ".join(f"{r.style} ({r.kind}) {c} points" for r, c in zip(regions, counts)))
    if out_picture:
        from .figures import clusters_picture

        clusters_picture(x, region, out_picture, " | ".join(f"{i}: {r.style}" for i, r in enumerate(regions)))


def _region_of(regions: Path, n: int, index: int) -> np.ndarray:
    d = load_npz(regions, required=("region",))
    if d["region"].shape != (n,):
        raise ValueError(f"{regions}: 'region' has shape {d['region'].shape} for {n} content points")
    if not 0 <= index < len(d["styles"]):
        raise ValueError(f"{regions}: no region {index} (it has {len(d['styles'])})")
    return d["region"]


def run_region_content(*, content: Path, regions: Path, out_ply: Path, params: dict) -> None:
    """The content points of region ``params["index"]``: the content a region's style rebuilds; the JSON
    beside it gives the whole content's diameter, which the region's elements are sized by (stage 4)."""
    from .geometry import robust_bounds

    pts = read_ply(content)
    k = int(params.get("index", -1))
    region = _region_of(regions, len(pts), k)
    write_ply(out_ply, pts.subset(torch.from_numpy(np.nonzero(region == k)[0])))
    write_json(Path(out_ply).with_suffix(".json"), {"region": k, "of": str(content), "points": int((region == k).sum()),
                                                      "content_diameter": 2 * robust_bounds(pts.means)[1]})


def run_region_clusters(*, clusters: Path, regions: Path, out_npz: Path, params: dict) -> None:
    """The content's clusters cut by region ``params["index"]`` (:func:`wast3d.regions.split_clusters`), for
    the region's content points in their order there."""
    from .regions import split_clusters

    cl = load_npz(clusters, required=("labels",))
    k = int(params.get("index", -1))
    region = _region_of(regions, len(cl["labels"]), k)
    idx, labels, report = split_clusters(cl["labels"], region, k, cl.get("normals"))
    extra = {"normals": cl["normals"][idx]} if "normals" in cl else {}
    save_npz(out_npz, labels=labels, sizes=np.bincount(labels), **extra)
    write_json(Path(out_npz).with_suffix(".json"), {**report, "region": k, "clusters_source": str(clusters)})
    log.info("region %d: %d points in %d clusters (%d of the content's clusters cut by its border)", k,
             report["points"], report["clusters"], report["clusters_cut_by_the_border"])


def merge_regions(parts: list[tuple[str, Path]], out_ply: Path) -> None:
    """One scene of the regions' results [(style, final PLY)], in that order; ``final.json`` beside it
    lists each part's style and Gaussians (the seams stage reads which Gaussian came from which region)."""
    from .gaussians import GaussianScene

    scenes = [read_ply(p) for _, p in parts]
    if len({s.sh_degree for s in scenes}) > 1:
        top = max(s.sh_degree for s in scenes)
        scenes = [s.with_sh_degree(top) for s in scenes]
    if any(s.element is None for s in scenes) and any(s.element is not None for s in scenes):
        for s in scenes:
            s.element = None  # element labels mean one style's elements: kept only where every part has them
    out = GaussianScene.concat(scenes)
    write_ply(out_ply, out)
    write_json(Path(out_ply).with_suffix(".json"), {"parts": [{"style": st, "source": str(p), "gaussians": len(s)}
                                                              for (st, p), s in zip(parts, scenes)],
                                                    "gaussians": len(out)})


def run_seams(*, content: Path, regions: Path, result: Path, result_render: Path, content_render: Path,
              out_json: Path, params: dict) -> None:
    """The seams of a result of several styles, each figure beside the same of each style alone on the whole
    content (``params["alone"]``: their final PLYs, ``params["alone_renders"]``: their render folders, in the
    set's order). The band: the content points within ``params["band"]`` content spacings (default 3) of
    another region. Coverage along the seam (:func:`wast3d.regions.band_coverage`: the band drawn from the
    content render's cameras, its points in white over the rest in black) and the Gaussians' density there
    (:func:`wast3d.regions.seam_density`); the whole result's coverage."""
    from .elements import element_pixels, label_colours
    from .geometry import mean_spacing
    from .image_metrics import coverage
    from .rasterizer import rasterize
    from .regions import band_coverage, band_of, seam_density
    from .render import read_cameras, read_frames

    pts, res = read_ply(content), read_ply(result)
    region = load_npz(regions, required=("region",))["region"]
    if len(region) != len(pts):
        raise ValueError(f"{regions}: {len(region)} regions for {len(pts)} content points")
    parts = read_json(Path(result).with_suffix(".json")).get("parts")
    if not parts or sum(p["gaussians"] for p in parts) != len(res):
        raise ValueError(f"{Path(result).with_suffix('.json')}: 'parts' must count the result's {len(res)} Gaussians")
    x = pts.means.double().numpy()
    in_band = band_of(x, region, float(params.get("band", 3.0)) * mean_spacing(pts.means))
    alone = params.get("alone", [])
    out = {"styles": [p["style"] for p in parts], "band_points": int(in_band.sum()),
           "regions": seam_density(x, region, in_band, res.means.double().numpy(),
                                   {k: read_ply(p).means.double().numpy() for k, p in enumerate(alone)})}
    content_frames = read_frames(content_render)
    cams = read_cameras(content_render, len(content_frames))
    lab = label_colours(torch.from_numpy(in_band.astype(np.int64)), pts.dtype)
    band = []
    for cam in cams:  # the share of each pixel the band's points draw, in the content render's frames
        m = rasterize(pts, cam, colors=lab)
        band.append(element_pixels(m.rgb, m.alpha))
    band = torch.stack(band)
    out["coverage_band"] = band_coverage(read_frames(result_render)[..., 3], content_frames[..., 3], band)
    out["coverage_band_alone"] = [band_coverage(read_frames(f)[..., 3], content_frames[..., 3], band)
                                  for f in params.get("alone_renders", [])]
    out["coverage"] = coverage(read_frames(result_render)[..., 3], content_frames[..., 3])
    write_json(out_json, out)
    log.info("seams: coverage along the seam %s (each style alone: %s), density against each style alone %s",
             out["coverage_band"], out["coverage_band_alone"],
             {out["styles"][r]: v.get("density_ratio") for r, v in out["regions"].items()})
