#!/usr/bin/python3
"""Prints one line per procedure report (reports/demo/*/summary.json) and writes
reports/demo/summary.md. Exits 1 if a procedure failed or wrote no summary."""
import json
import pathlib
import sys


def main(root: pathlib.Path) -> int:
    rows = []
    ok = True
    for summary in sorted(root.glob("*/summary.json")):
        data = json.loads(summary.read_text())
        success = bool(data.get("success"))
        ok = ok and success
        figures = ", ".join(f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}"
                            for k, v in data.items()
                            if k not in ("procedure", "scene", "success"))
        rows.append((summary.parent.name, data.get("scene", "?"), "PASS" if success else "FAIL",
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
    print(f"report: {root}/summary.md")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main(pathlib.Path(sys.argv[1])))
