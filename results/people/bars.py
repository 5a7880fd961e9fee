#!/usr/bin/env python3
"""Issue 49's bar, person by person, from the grids' own tables.

    python3 results/people/bars.py \
        --references REFS/summary.csv \     # pbrl exp plot of grid-references (SAC on each truth)
        --task TASK.csv [--task TASK2.csv] \  # pbrl eval RUN --people DIR --csv, one per r_task seed
        --runs DEFAULT/summary.csv \        # pbrl exp plot of the grid judged (the default)
        --at 500000 [--prefix sac-decoupled-] > bars.md

For each person: the truth policy's success and preference return (mean of the last 100k env
steps, mean over its seeds), the r_task policies' preference return for that person (pbrl
eval, mean over seeds), and the judged runs' success and preference return (last 100k, mean
over seeds, with the t interval over seeds). A person meets the bar when the runs' success is
at least 0.9x the truth policy's and their preference return closes at least half of the gap
between r_task's and the truth's. The last line is the share of people who meet both.
"""
import argparse
import csv
import sys
from collections import defaultdict


def rows(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def at_mark(path, at, prefix):
    """person -> the summary row of method `prefix + person` at env steps `at`."""
    out = {}
    for r in rows(path):
        if int(r["env_steps"]) != at or not r["method"].startswith(prefix):
            continue
        out[r["method"][len(prefix):]] = r
    return out


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--references", required=True)
    p.add_argument("--task", action="append", required=True)
    p.add_argument("--runs", required=True)
    p.add_argument("--at", type=int, default=500000)
    p.add_argument("--ref-prefix", default="sac-true-")
    p.add_argument("--prefix", default="sac-decoupled-")
    a = p.parse_args()
    refs = at_mark(a.references, a.at, a.ref_prefix)
    runs = at_mark(a.runs, a.at, a.prefix)
    task = defaultdict(list)
    for path in a.task:
        for r in rows(path):
            task[r["person"]].append(float(r["return_human"]))
    people = sorted(set(refs) & set(runs) & set(task))
    missing = sorted((set(refs) | set(runs) | set(task)) - set(people))
    print(
        "| person | truth: success | truth: pref. return | r_task: pref. return | "
        "runs: seeds | runs: success [95%] | x truth | runs: pref. return [95%] | "
        "gap closed | meets both |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    met = 0
    for person in people:
        ref, run = refs[person], runs[person]
        s_ref = float(ref["success_rate_mean"])
        h_ref = float(ref["return_human_mean"])
        h_task = sum(task[person]) / len(task[person])
        s = float(run["success_rate_mean"])
        h = float(run["return_human_mean"])
        ratio = s / s_ref if s_ref > 0 else float("inf")
        gap = h_ref - h_task
        closed = (h - h_task) / gap if gap != 0 else float("nan")
        success_ok = s >= 0.9 * s_ref
        taste_ok = h >= h_task + 0.5 * gap
        both = success_ok and taste_ok
        met += both
        print(
            f"| {person} | {s_ref:.2f} | {h_ref:.1f} | {h_task:.1f} | {run['seeds']} | "
            f"{s:.2f} [{max(0.0, float(run['success_rate_lo'])):.2f}, "
            f"{min(1.0, float(run['success_rate_hi'])):.2f}] | "
            f"{ratio:.2f} | {h:.1f} [{float(run['return_human_lo']):.1f}, "
            f"{float(run['return_human_hi']):.1f}] | {closed:.2f} | "
            f"{'yes' if both else 'no (' + ', '.join(w for w, ok in (('success', success_ok), ('taste', taste_ok)) if not ok) + ')'} |"
        )
    print(f"\nPeople who meet both: {met} of {len(people)}.")
    if missing:
        print(f"Not judged (a table lacks them): {', '.join(missing)}.")
    return 0


if __name__ == "__main__":
    sys.exit(main())
