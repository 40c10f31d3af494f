"""Prototype (not in the package): per-object score normalisation before the rejection
decision, measured on a saved recognition run without matching anything again.

Some stored objects score well against everything (the koala, the wingnut, the hammer
fit many figures a little). Score normalisation as in speaker and face verification
discounts that: each object's scores are shifted by the mean (``m``) or standardised by
the mean and spread (``z``) of the scores the *other* objects' stored views gave it in
the database's calibration (an object's own views never enter its norms; for a query
whose object is left out of the database, that object's views are left out of every
norm too, as a database without it would have them). The evidence is then the best
normalised score itself (``best``), its lead over the mean of the others (``lead``, the
package's statistic) or over the runner-up (``lead2``), and the threshold is calibrated
on the stored views exactly as ``calibrate_threshold`` does (5% of their impostors
through).

Prints, per normalisation and statistic: top-1, known views rejected and unknown views
accepted at the calibrated threshold, the ROC area of known against unknown evidence, and
the known views rejected at the threshold that rejects 90% of the unknown ones (chosen on
the test views: a measure of separation, not a result). ``raw lead`` reproduces the
saved run's own decisions.

    python benchmarks/proto_normalisation.py [results/recognition_128_levels.json]
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from sqparts._recognize import calibrate_threshold  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"


def main(path: Path) -> None:
    saved = json.loads(path.read_text())
    views, rows = saved["calibration"]["views"], saved["rows"]
    objects = sorted({v["object"] for v in views})

    def norms(left_out=()):
        out = {}
        for o in objects:
            s = [v["scores"][o] for v in views if v["object"] not in (o, *left_out) and o in v["scores"]]
            out[o] = (float(np.mean(s)), float(np.std(s)) + 1e-6)
        return out

    def normalise(scores, st, mode):
        if mode == "raw":
            return dict(scores)
        if mode == "m":
            return {o: s - st[o][0] for o, s in scores.items()}
        return {o: (s - st[o][0]) / st[o][1] for o, s in scores.items()}

    def evidence(scores, statistic):
        s = sorted(scores.values(), reverse=True)
        if statistic == "best":
            return s[0]
        return s[0] - (np.mean(s[1:]) if statistic == "lead" else s[1])

    print(
        "| normalisation | statistic | threshold | top-1 | known rejected | unknown accepted | ROC area | known rejected at 90% |"
    )
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    for mode in ("raw", "m", "z"):
        for statistic in ("best", "lead", "lead2"):
            genuine, impostor = [], []
            for v in views:
                n = normalise(v["scores"], norms((v["object"],)), mode)
                if max(n, key=n.__getitem__) == v["object"]:
                    genuine.append(evidence(n, statistic))
                impostor.append(evidence({o: x for o, x in n.items() if o != v["object"]}, statistic))
            threshold = calibrate_threshold(genuine, impostor)
            everyone = norms()
            top1, known, unknown = 0, [], []
            for r in rows:
                n = normalise(r["scores"], everyone, mode)
                right = max(n, key=n.__getitem__) == r["object"]
                top1 += right
                known.append((evidence(n, statistic), right))
                rest = {o: s for o, s in r["scores"].items() if o != r["object"]}
                unknown.append(evidence(normalise(rest, norms((r["object"],)), mode), statistic))
            e = np.array([k for k, _ in known])
            u = np.array(unknown)
            separated = np.array([k if right else -np.inf for k, right in known])
            auc = np.mean([(a > b) + 0.5 * (a == b) for a in separated for b in u])
            bar = np.sort(u)[::-1][int(np.floor(0.1 * len(u)))]
            print(
                f"| {mode} | {statistic} | {threshold:.3f} | {top1}/{len(rows)} | {int((e < threshold).sum())} | "
                f"{int((u >= threshold).sum())} | {auc:.3f} | {int((separated <= bar).sum())} |"
            )


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else RESULTS / "recognition_128_levels.json")
