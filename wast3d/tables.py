"""Tables: one row per (content, style, experiment) from the stages' JSON reports and Snakemake's
``benchmark:`` files. Pure functions build DataFrames; :func:`write_table` is the I/O edge."""

from __future__ import annotations

import logging
from pathlib import Path

import pandas as pd

from .io_utils import atomic_path, read_json
from .stages import artifact, beside

log = logging.getLogger(__name__)


def _bench(path: Path) -> dict:
    """Snakemake benchmark TSV -> seconds and peak memory (max_rss, MB); {} with a warning naming the
    file where there is none (a stage run outside Snakemake): the row's time is then left empty."""
    try:
        df = pd.read_csv(path, sep="\t")
        return {"seconds": float(df["s"].iloc[0]), "max_rss_mb": float(df["max_rss"].iloc[0])}
    except (OSError, KeyError, ValueError, IndexError, pd.errors.EmptyDataError) as e:
        log.warning("%s: no benchmark (%s); time and memory left empty", path, type(e).__name__)
        return {}


def _rule_benchmark(results: Path, rule: str, *wildcards: str) -> Path:
    return Path(artifact("rule_benchmark", results, rule=rule, job="_".join(wildcards)))


def run_row(results: Path, content: str, style: str, experiment: str) -> dict:
    pair = dict(content=content, style=style, experiment=experiment)
    loss = read_json(Path(beside("losses", ".json", results, **pair)))
    final = read_json(Path(beside("final", ".json", results, **pair)))
    b = _bench(_rule_benchmark(results, "sinkhorn", f"{content}__{style}", experiment))
    cfg = loss.get("config", {})
    row = {
        "content": content, "style": style, "experiment": experiment,
        "features": cfg.get("features"), "loss": cfg.get("loss"),
        "blur": cfg.get("sinkhorn", {}).get("blur"), "debias": cfg.get("sinkhorn", {}).get("debias"),
        "clusters": loss.get("clusters"), "gaussians": loss.get("gaussians"),
        "loss_first": loss.get("loss_first_mean"), "loss_last": loss.get("loss_last_mean"),
        "stylize_s": b.get("seconds", loss.get("seconds_total")), "stylize_max_rss_mb": b.get("max_rss_mb"),
        "rescale_ratio_median": final.get("ratio_quantiles", {}).get("0.5"),
    }
    return row


def write_table(rows: list[dict], csv_path: Path, md_path: Path | None = None, html_path: Path | None = None) -> pd.DataFrame:
    df = pd.DataFrame(rows)
    with atomic_path(csv_path) as tmp:
        df.to_csv(tmp, index=False)
    for path, fn in ((md_path, to_markdown), (html_path, to_html)):
        if path:
            with atomic_path(path) as tmp:
                tmp.write_text(fn(df))
    return df


def _cell(v) -> str:
    return f"{v:.4g}" if isinstance(v, float) and v == v else ("" if v is None or v != v else str(v))


def to_html(df: pd.DataFrame) -> str:
    """A standalone HTML page holding the table (what the Snakemake report shows inline; a CSV it only
    offers as a download)."""
    import html

    head = "".join(f"<th>{html.escape(str(c))}</th>" for c in df.columns)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(_cell(v))}</td>" for v in r) + "</tr>\n"
                   for r in df.itertuples(index=False))
    style = ("body{font-family:sans-serif;font-size:13px} table{border-collapse:collapse} "
             "th,td{border:1px solid #bbb;padding:3px 6px;text-align:right} th{background:#eee} "
             "td:first-child,td:nth-child(2),td:nth-child(3){text-align:left}")
    return (f"<!DOCTYPE html>\n<html><head><meta charset=\"utf-8\"><style>{style}</style></head><body>\n"
            f"<table>\n<thead><tr>{head}</tr></thead>\n<tbody>\n{body}</tbody>\n</table>\n</body></html>\n")


def to_markdown(df: pd.DataFrame) -> str:
    """A GitHub table without the optional ``tabulate`` dependency."""
    head = "| " + " | ".join(df.columns) + " |\n|" + "---|" * len(df.columns) + "\n"
    return head + "".join("| " + " | ".join(_cell(v) for v in r) + " |\n" for r in df.itertuples(index=False))


# ---- Table 1 ---------------------------------------------------------------------------------

METRIC_COLUMNS = ("content_chamfer", "coarse_chamfer", "coverage", "coverage_element", "element_share_ratio",
                  "element_intact", "element_whole_ratio", "segment_intact", "segment_whole_ratio",
                  "element_colour_w1", "element_thickness_w1", "relief_w1", "texture_swd", "style_patch_chamfer",
                  "style_patch_sinkhorn", "tilt_w1_deg", "aniso_w1", "colour_sinkhorn")


def without_empty_metrics(rows: list[dict]) -> list[dict]:
    """``rows`` without the metric columns (METRIC_COLUMNS) that no row computed (a metric the evaluation
    leaves out, such as the patch metrics at ``metrics.patches: 0``)."""
    empty = {k for k in METRIC_COLUMNS if all(r.get(k, None) is None for r in rows)}
    return [{k: v for k, v in r.items() if k not in empty} for r in rows]


def method_benchmarks(results: Path, content: str, style: str, method: str, partition: str | None) -> list[Path]:
    """The Snakemake benchmark files of the stages a method needs beyond the shared ones (pretraining,
    surface sampling and k-means are shared by every method and not counted)."""
    pair = f"{content}__{style}"
    if method == "colour_ot":
        return [_rule_benchmark(results, "colour_transfer", pair)]
    if partition is None:  # the unstylized input
        return []
    return [_rule_benchmark(results, "register", pair, partition), _rule_benchmark(results, "select", pair, partition),
            _rule_benchmark(results, "sinkhorn", pair, method), _rule_benchmark(results, "rescale", pair, method)]


def table1_row(results: Path, content: str, style: str, method: str, partition: str | None, label: str) -> dict:
    """One row of Table 1 from ``results/eval/{content}__{style}/{method}.json`` and benchmark files."""
    ev = read_json(Path(artifact("eval", results, content=content, style=style, method=method)))
    benches = [_bench(p) for p in method_benchmarks(results, content, style, method, partition)]
    # where the method's own stage recorded its device (the unstylized input has no such stage)
    report = "final" if method == "colour_ot" else ("losses" if partition is not None else None)
    device = read_json(Path(beside(report, ".json", results, content=content, style=style, method=method))).get("device") \
        if report else None
    clip = ev.get("clip_similarity")
    row = {"content": content, "style": style, "method": label, "run": method,
           "clip_similarity_pct": clip if clip is not None else "not computed",
           **{k: ev.get(k) for k in METRIC_COLUMNS}, "gaussians": ev.get("gaussians"),
           "time_s": sum(x["seconds"] for x in benches) if benches and all(benches) else None,
           "peak_mem_mb": max(x["max_rss_mb"] for x in benches) if benches and all(benches) else None,
           "device": device, "clip_status": ev.get("clip_status")}
    return row


# ---- row specifications (the ``--run`` / ``--row`` arguments of the table commands) ------------


def parse_spec(spec: str, fields: tuple[str, ...]) -> list[str]:
    """``CONTENT__STYLE/F1/.../Fn`` -> ``[content, style, f1, ..., fn]`` (the last field may hold '/')."""
    parts = spec.split("/", len(fields))
    if len(parts) != len(fields) + 1 or "__" not in parts[0]:
        raise ValueError(f"table row '{spec}' is not CONTENT__STYLE/{'/'.join(fields)}")
    return [*parts[0].split("__", 1), *parts[1:]]


def summary_spec_row(results: Path, spec: str) -> dict:
    """:func:`run_row` of ``CONTENT__STYLE/EXPERIMENT``."""
    return run_row(results, *parse_spec(spec, ("EXPERIMENT",)))


def table1_spec_row(results: Path, spec: str) -> dict:
    """:func:`table1_row` of ``CONTENT__STYLE/METHOD/PARTITION/LABEL`` (PARTITION '-': no partition)."""
    c, s, method, part, label = parse_spec(spec, ("METHOD", "PARTITION", "LABEL"))
    return table1_row(results, c, s, method, None if part == "-" else part, label)


# ---- several styles by region -------------------------------------------------------------------

REGION_COLUMNS = ("element_share_ratio", "element_intact", "element_whole_ratio", "coverage", "coverage_element",
                  "coarse_chamfer", "element_colour_w1", "element_thickness_w1", "relief_w1", "texture_swd")


def regions_spec_row(results: Path, spec: str) -> list[dict]:
    """The rows of ``CONTENT__SET/EXPERIMENT``: one per region, its pair's evaluation against its own style
    and the seams' figures for it (``eval/CONTENT__SET/EXPERIMENT_seams.json``)."""
    content, rset, experiment = parse_spec(spec, ("EXPERIMENT",))
    seams = read_json(Path(results) / "eval" / f"{content}__{rset}" / f"{experiment}_seams.json")
    rows = []
    for k, style in enumerate(seams["styles"]):
        ev = read_json(Path(artifact("eval", results, content=f"{rset}-{k}", style=style, method=experiment)))
        reg = seams["regions"].get(str(k), seams["regions"].get(k, {}))
        rows.append({"content": content, "set": rset, "region": k, "style": style, "run": experiment,
                     "points": reg.get("points"), **{c: ev.get(c) for c in REGION_COLUMNS},
                     "seam_density_ratio": reg.get("density_ratio"), "seam_coverage": seams.get("coverage_band"),
                     "seam_coverage_alone": (seams.get("coverage_band_alone") or [None] * (k + 1))[k],
                     "coverage_whole": seams.get("coverage")})
    return rows
