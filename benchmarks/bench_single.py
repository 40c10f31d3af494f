"""One part in, one part out: single synthetic parts through :func:`sqparts.recover`'s defaults.

Cases (``_common.make_case``, seeds 5000 + i, unseen by ``bench_search.py``): random single
parts (sizes 0.08-0.25 m, squareness 0.2-1.8, any orientation), half bent and tapered;
pinhole and orthographic; clean, with Gaussian noise (σ_n = 2 mm) or quantised to 6 bits.
Each image goes through the whole pipeline (search, selection, joint refinement, split,
fill, merge) with recover's defaults and the image's every return as the figure. A case
succeeds when the symmetric Chamfer distance between the whole surfaces of the recovered
parts (their union) and the truth, hidden sides included, is at most 2% of the part's
size (2·max a_i); it is one part when exactly one part comes back.

    python benchmarks/bench_single.py [--cases 48] [--pixels 64] [--grid coarse]

Case i cycles through the 12 combinations (pinhole or not, variant, deformed or not), so
``--cases 48`` runs each four times with different random parts.
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np
from _common import chamfer, make_case, save

import sqparts

VARIANTS = ("clean", "noise", "6-bit")
SEED = 5000


def run_case(k: int, c: dict, recover_kwargs: dict) -> dict:
    t0 = time.perf_counter()
    rec = sqparts.recover(c["depth"], c["camera"], **recover_kwargs)
    wall = time.perf_counter() - t0
    size = 2 * float(np.max(np.asarray(c["truth"].size)))
    ch = chamfer(rec.parts, c["truth"]) / size
    n = len(rec.parts)
    row = {
        "case": k,
        "variant": c["variant"],
        "pinhole": c["pinhole"],
        "deformed": c["deformed"],
        "parts": n,
        "chamfer_rel": ch,
        "success": bool(ch <= 0.02),
        "one_part": n == 1,
        "fraction_explained": rec.fraction_explained,
        "commission_fraction": rec.commission_fraction,
        "description_length_bits": rec.cost.total,
        "pixels": c["visible"],
        "history": [(s, float(e)) for s, e in rec.history],
        "wall_s": wall,
    }
    print(
        f"  case {k:2d} {c['variant']:6s} {'pin' if c['pinhole'] else 'ortho'} "
        f"{'deformed' if c['deformed'] else 'plain   '} {n} part(s) chamfer {ch:.3f} "
        f"explained {rec.fraction_explained:.0%} E {rec.cost.total:.0f} {wall:.1f} s",
        flush=True,
    )
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=48)
    ap.add_argument("--pixels", type=int, default=64)
    ap.add_argument(
        "--search", default=None, help="a search preset for recover (fast, paper, region; default: recover's own)"
    )
    ap.add_argument(
        "--refine-orientations",
        type=int,
        default=None,
        help="SearchSettings.refine_orientations for the preset (default: the preset's own)",
    )
    args = ap.parse_args()
    recorded = {} if args.search is None else {"search": args.search}  # as saved in the JSON
    recover_kwargs = dict(recorded)
    if args.refine_orientations is not None:
        preset = sqparts.search_preset(args.search or "fast")
        recover_kwargs = {"search": dataclasses.replace(preset, refine_orientations=args.refine_orientations)}
        recorded = {"search": args.search or "fast", "refine_orientations": args.refine_orientations}
    rows = [
        run_case(k, make_case(k, VARIANTS, seed=SEED, pixels=args.pixels), recover_kwargs) for k in range(args.cases)
    ]
    success = float(np.mean([r["success"] for r in rows]))
    one = float(np.mean([r["one_part"] for r in rows]))
    both = float(np.mean([r["success"] and r["one_part"] for r in rows]))
    print(
        f"success {success:.0%}, one part {one:.0%}, both {both:.0%}, "
        f"median Chamfer {np.median([r['chamfer_rel'] for r in rows]):.4f}, "
        f"median {statistics.median(r['wall_s'] for r in rows[1:] or rows):.1f} s/case",
        flush=True,
    )
    save(
        "single",
        {
            "cases": args.cases,
            "image": f"{args.pixels}x{args.pixels}",
            "dtype": "float32",
            "recover_kwargs": recorded,
            "success_rate": success,
            "one_part_rate": one,
            "success_and_one_part_rate": both,
            "success_rate_5pct": float(np.mean([r["chamfer_rel"] <= 0.05 for r in rows])),
            "median_chamfer_rel": float(np.median([r["chamfer_rel"] for r in rows])),
            "median_wall_s": statistics.median(r["wall_s"] for r in rows),
            "rows": rows,
        },
    )


if __name__ == "__main__":
    main()
