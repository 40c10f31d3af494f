"""Compare two run.py results.

    python benchmarks/unseen/cmp.py A.json B.json [--tol 0.5]

Per scene: E_A, E_B (first figure's E; for two-object scenes, and wherever a run found
several figures, the sum over figures, marked "+"), B - A, parts A/B, truth parts, truth
E (from A: the true parts' E under A's first figure's encoding; for several figures the
sum of the figures' truth E), figures A/B.  Totals: scenes B shorter / longer than A by
more than tol bits, total bits B - A, part count equal to the truth's (one-object scenes),
scenes where the first figure's E is > 15 bits above the truth's, seconds.
"""

from __future__ import annotations

import argparse
import json


def load(path):
    data = json.load(open(path))
    return {r["name"]: r for r in data["rows"]}


def e_of(r):
    """(E used for comparing, marker)."""
    if r.get("error"):
        return None, "!"
    if r["figures"] > 1 or r["truth_objects"] > 1:
        return r["E_sum"], "+"
    return r["E"], " "


def truth_e(r):
    if r.get("error"):
        return None
    if r["figures"] > 1 or r["truth_objects"] > 1:
        es = [p["E_truth"] for p in r["per_figure"] if p["E_truth"] is not None]
        return sum(es) if es else None
    return r["E_truth"]


def f(x, w=8, p=1):
    return f"{'-':>{w}}" if x is None else f"{x:{w}.{p}f}"


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("a")
    ap.add_argument("b")
    ap.add_argument("--tol", type=float, default=0.5)
    args = ap.parse_args()
    A, B = load(args.a), load(args.b)
    names = list(A) + [n for n in B if n not in A]
    print(
        f"{'scene':22s} {'E_A':>9s} {'E_B':>9s} {'B-A':>8s}  parts A/B truth  {'E_truth':>8s} {'A-tru':>7s} {'B-tru':>7s}  figs A/B"
    )
    shorter = longer = 0
    diff = 0.0
    right = {"A": 0, "B": 0}
    one_obj = 0
    above = {"A": [], "B": []}
    secs = {"A": 0.0, "B": 0.0}
    errors = {"A": [], "B": []}
    for n in names:
        a, b = A.get(n), B.get(n)
        if a is None or b is None:
            print(f"{n:22s} only in {'A' if b is None else 'B'}")
            continue
        (ea, ma), (eb, mb) = e_of(a), e_of(b)
        for k, r in (("A", a), ("B", b)):
            if r.get("error"):
                errors[k].append(n)
            else:
                secs[k] += r["seconds"]
        d = None if ea is None or eb is None else eb - ea
        if d is not None:
            diff += d
            shorter += d < -args.tol
            longer += d > args.tol
        t = truth_e(a) if not a.get("error") else truth_e(b)
        tp = a.get("truth_parts", b.get("truth_parts"))
        if a.get("truth_objects", b.get("truth_objects")) == 1:
            one_obj += 1
            for k, r in (("A", a), ("B", b)):
                if not r.get("error"):
                    right[k] += r["parts"] == tp
                    if r["E_truth"] is not None and r["E"] - r["E_truth"] > 15:
                        above[k].append(n)
        pa = "!" if a.get("error") else a["parts"]
        pb = "!" if b.get("error") else b["parts"]
        fa = "!" if a.get("error") else a["figures"]
        fb = "!" if b.get("error") else b["figures"]
        flag = "" if d is None or abs(d) <= args.tol else (" <" if d < 0 else " >")
        print(
            f"{n:22s} {f(ea)}{ma}{f(eb)}{mb}{f(d)}  {str(pa):>3s}/{str(pb):<3s} {tp:>3d}   {f(t)} "
            f"{f(None if ea is None or t is None else ea - t, 7)} {f(None if eb is None or t is None else eb - t, 7)}  "
            f"{fa}/{fb}{flag}"
        )
    print()
    print(f"B shorter by > {args.tol} bits: {shorter}; longer: {longer}; total B - A: {diff:+.1f} bits")
    print(f"part count = truth's (one-object scenes, {one_obj}): A {right['A']}, B {right['B']}")
    for k in "AB":
        print(f"{k}: first figure's E > truth's + 15 bits: {len(above[k])} {above[k]}")
    print(f"seconds: A {secs['A']:.1f}, B {secs['B']:.1f}")
    if errors["A"] or errors["B"]:
        print(f"errors: A {errors['A']}, B {errors['B']}")


if __name__ == "__main__":
    main()
