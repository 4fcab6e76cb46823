#!/usr/bin/python3
"""Prints one line per procedure report (reports/demo/*/summary.json) and writes
reports/demo/summary.md: procedure, result, three headline figures and the report folder; every
other figure stays in the report. Result PASS: the procedure's outcome was met (every seed placed,
the success rate consistent with the prediction, ...); MISSED: it ran to its report but the
outcome was not met (the report says why). Exits 1 if no report was found; scripts/demo itself
fails when a procedure wrote no report or a node it requires died."""
import json
import math
import os
import pathlib
import sys

# The figures a reader looks at first, in order of preference; a report shows the first three
# it has (the rest of its numbers in file order fill in when it has fewer).
HEADLINE_KEYS = [
    "placed", "targets_tried", "seed_error_mm_max",
    "success_rate", "success_ci_low", "predicted_ps", "predicted_p_success_mean",
    "target_error_mm_median", "tip_error_mm_median",
    "max_dwell_error_s", "interruptions",
    "dice_mean", "point_error_mm_mean", "rigid_point_error_mm_mean",
]
SKIPPED = {"procedure", "scene", "success", "status", "detected_unix_s", "seed"}
FIGURES = 3


def shown(value):
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        return "undefined" if math.isnan(value) else f"{value:.3g}"
    return str(value)


def headline(data):
    numbers = {k: v for k, v in data.items()
               if k not in SKIPPED and isinstance(v, (int, float)) and not isinstance(v, bool)}
    keys = [k for k in HEADLINE_KEYS if k in numbers]
    keys += [k for k in numbers if k not in keys]
    return [f"{k} {shown(numbers[k])}" for k in keys[:FIGURES]]


def main(root: pathlib.Path) -> int:
    rows = []
    for summary in sorted(root.glob("*/summary.json")):
        data = json.loads(summary.read_text())
        figures = headline(data) + [""] * FIGURES
        rows.append((summary.parent.name, "PASS" if data.get("success") else "MISSED",
                     *figures[:FIGURES], os.path.relpath(summary.parent)))
    if not rows:
        print("no procedure reports found in", root, file=sys.stderr)
        return 1
    header = ("procedure", "result", "figure 1", "figure 2", "figure 3", "report")
    widths = [max(len(r[i]) for r in rows + [header]) for i in range(len(header))]
    print("\n== needle_guidance demo summary ==")
    for r in [header] + rows:
        print("  ".join(c.ljust(w) for c, w in zip(r, widths)).rstrip())
    md = ["# needle_guidance demo", "", "| " + " | ".join(header) + " |",
          "| " + " | ".join("---" for _ in header) + " |"]
    md += ["| " + " | ".join(r) + " |" for r in rows]
    (root / "summary.md").write_text("\n".join(md) + "\n")
    missed = [r[0] for r in rows if r[1] != "PASS"]
    if missed:
        print("outcome not met (see each report): " + ", ".join(missed))
    print(f"report: {root}/summary.md")
    return 0


if __name__ == "__main__":
    if len(sys.argv) != 2 or sys.argv[1] in ("-h", "--help"):
        help_asked = len(sys.argv) == 2
        print(__doc__ + "\nusage: summarize_reports.py REPORTS_DIR", file=sys.stdout if help_asked else sys.stderr)
        sys.exit(0 if help_asked else 2)
    sys.exit(main(pathlib.Path(sys.argv[1])))
