#!/usr/bin/python3
"""Prints one line per procedure report (reports/demo/*/summary.json) and writes
reports/demo/summary.md. Result PASS: the procedure's outcome was met (every seed placed, the
success rate consistent with the prediction, ...); MISSED: it ran to its report but the outcome
was not met (the report says why). Exits 1 if no report was found; scripts/demo itself fails when
a procedure wrote no report or a node it requires died."""
import json
import pathlib
import sys


def main(root: pathlib.Path) -> int:
    rows = []
    for summary in sorted(root.glob("*/summary.json")):
        data = json.loads(summary.read_text())
        success = bool(data.get("success"))
        figures = ", ".join(f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}"
                            for k, v in data.items()
                            if k not in ("procedure", "scene", "success"))
        rows.append((summary.parent.name, data.get("scene", "?"), "PASS" if success else "MISSED",
                     figures))
    if not rows:
        print("no procedure reports found in", root, file=sys.stderr)
        return 1
    header = ("procedure", "scene", "result", "headline figures")
    widths = [max(len(r[i]) for r in rows + [header]) for i in range(3)]
    lines = ["  ".join(h.ljust(w) for h, w in zip(header[:3], widths)) + "  " + header[3]]
    for r in rows:
        lines.append("  ".join(c.ljust(w) for c, w in zip(r[:3], widths)) + "  " + r[3])
    print("\n== needle_guidance demo summary ==")
    print("\n".join(lines))
    md = ["# needle_guidance demo", "", "| procedure | scene | result | headline figures |",
          "| --- | --- | --- | --- |"]
    md += [f"| {r[0]} | {r[1]} | {r[2]} | {r[3]} |" for r in rows]
    (root / "summary.md").write_text("\n".join(md) + "\n")
    missed = [r[0] for r in rows if r[2] != "PASS"]
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
