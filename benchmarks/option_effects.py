"""Each stylize option's effect against the seed spread, from the evaluations of studies/options.

    python benchmarks/option_effects.py [--results results] [--out results/benchmarks/option_effects.csv]

For each pair and variant of the `options` sweep (studies/options/config.yaml, run first), the metrics
that define "works" (element share, intact, whole, coverage, coarse shape, relief_w1) and each one's
difference from the default; the spread is each metric's difference between the default and `seed1`
(other k-means and registration seeds). A variant *changes* a pair when some metric moves by more than
`--factor` (1.5) times its spread and by more than 0.005; it *does not act* on a pair when every metric
equals the default's. Writes the CSV, a Markdown table beside it, and prints per variant
on how many pairs it changes anything.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import OUT, ROOT  # noqa: E402

METRICS = {"element_share_ratio": "share", "element_intact": "intact", "element_whole_ratio": "whole",
           "coverage": "coverage", "coarse_chamfer": "coarse", "relief_w1": "relief_w1"}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--results", type=Path, default=ROOT / "results")
    ap.add_argument("--out", type=Path, default=OUT / "option_effects.csv")
    ap.add_argument("--factor", type=float, default=1.5, help="a change must exceed this many seed spreads")
    a = ap.parse_args()
    rows = []
    for f in sorted((a.results / "eval").glob("*/options-*.json")):
        ev = json.loads(f.read_text())
        rows.append({"pair": f.parent.name, "variant": f.stem.removeprefix("options-"),
                     **{short: ev.get(k) for k, short in METRICS.items()}})
    if not rows:
        raise SystemExit(f"{a.results}/eval: no evaluations of the options sweep (run studies/options first)")
    df = pd.DataFrame(rows)
    out = []
    for pair, d in df.groupby("pair"):
        base = d[d.variant == "default"]
        seed = d[d.variant == "seed1"]
        if base.empty or seed.empty:
            continue
        base, seed = base.iloc[0], seed.iloc[0]
        spread = {m: abs(float(base[m]) - float(seed[m])) if pd.notna(base[m]) and pd.notna(seed[m]) else None
                  for m in METRICS.values()}
        for _, r in d.iterrows():
            row = {"pair": pair, "variant": r.variant}
            beyond, same = [], True
            for m in METRICS.values():
                row[m] = r[m]
                if pd.isna(r[m]) or pd.isna(base[m]):
                    continue
                delta = float(r[m]) - float(base[m])
                row[f"d_{m}"] = delta
                same = same and delta == 0.0
                if r.variant not in ("default", "seed1") and abs(delta) > max(a.factor * (spread[m] or 0.0), 0.005):
                    beyond.append(f"{m} {delta:+.3f} (spread {spread[m]:.3f})")
            row["beyond_spread"] = "(does not act)" if same and r.variant != "default" else "; ".join(beyond)
            out.append(row)
    res = pd.DataFrame(out)
    a.out.parent.mkdir(parents=True, exist_ok=True)
    res.to_csv(a.out, index=False)
    cols = ["pair", "variant", *METRICS.values(), "beyond_spread"]
    a.out.with_suffix(".md").write_text(res[cols].to_markdown(index=False, floatfmt=".3f") + "\n")
    summary = res[~res.variant.isin(["default", "seed1"])].groupby("variant").beyond_spread.apply(
        lambda s: f"{((s != '') & (s != '(does not act)')).sum()} of {(s != '(does not act)').sum()} pairs it acts on")
    print(res[cols].to_string(index=False))
    print(f"\nchanges beyond {a.factor}x the seed spread, per variant:\n" + summary.to_string())
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
