#!/usr/bin/python3
"""Plots a benchmark folder: reads plot.json written by the bench tool, a list of
{"csv", "x", "y", "group", "title", "logx", "logy", "points", "annotate", "png"} entries, and draws each CSV's
y against x (one line per group) to the PNG; entries with "kind": "isodose" draw isodose lines. Speed against error, as DESIGN.md asks."""
import csv
import json
import pathlib
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def isodose(folder: pathlib.Path, spec: dict) -> None:
    """{"kind": "isodose", "csv": grid x_mm,y_mm,dose_pct, "contours": structure,contour,x_mm,y_mm,
    "levels": [..], "title", "png"}: isodose lines over the slice's structure outlines."""
    with open(folder / spec["csv"], newline="") as f:
        rows = list(csv.DictReader(f))
    xs = sorted({float(r["x_mm"]) for r in rows})
    ys = sorted({float(r["y_mm"]) for r in rows})
    grid = [[0.0] * len(xs) for _ in ys]
    xi = {x: i for i, x in enumerate(xs)}
    yi = {y: j for j, y in enumerate(ys)}
    for r in rows:
        grid[yi[float(r["y_mm"])]][xi[float(r["x_mm"])]] = float(r["dose_pct"])
    fig, ax = plt.subplots(figsize=(6.0, 5.4), dpi=110)
    lines = ax.contour(xs, ys, grid, levels=spec.get("levels", [50, 100, 150, 200]), cmap="plasma")
    ax.clabel(lines, fmt="%d %%", fontsize=7)
    with open(folder / spec["contours"], newline="") as f:
        outlines = {}
        for r in csv.DictReader(f):
            outlines.setdefault((r["structure"], r["contour"]), []).append((float(r["x_mm"]), float(r["y_mm"])))
    drawn = set()
    for (name, _), pts in outlines.items():
        pts = pts + pts[:1]
        ax.plot([p[0] for p in pts], [p[1] for p in pts], "k-" if name == "prostate" else "k--", lw=0.8,
                label=None if name in drawn else name)
        drawn.add(name)
    if spec.get("points_csv"):
        with open(folder / spec["points_csv"], newline="") as f:
            pts = list(csv.DictReader(f))
        ax.plot([float(p["x_mm"]) for p in pts], [float(p["y_mm"]) for p in pts], "k.", ms=3, label="catheters")
    ax.set_aspect("equal")
    if spec.get("invert_y"):
        ax.invert_yaxis()  # DICOM patient frame: +y is posterior; anterior up as on a CT slice
    ax.set_xlabel("x_mm")
    ax.set_ylabel("y_mm")
    ax.set_title(spec.get("title", ""))
    ax.legend(fontsize=7, loc="upper right")
    fig.tight_layout()
    fig.savefig(folder / spec["png"])
    plt.close(fig)


def plot(folder: pathlib.Path, spec: dict) -> None:
    if spec.get("kind") == "isodose":
        isodose(folder, spec)
        return
    with open(folder / spec["csv"], newline="") as f:
        rows = list(csv.DictReader(f))
    groups = {}
    for row in rows:
        groups.setdefault(row.get(spec.get("group", ""), ""), []).append(row)
    fig, ax = plt.subplots(figsize=(6.4, 4.4), dpi=110)
    for name, members in groups.items():
        xs = [float(r[spec["x"]]) for r in members]
        ys = [float(r[spec["y"]]) for r in members]
        order = sorted(range(len(xs)), key=xs.__getitem__)
        style = "o" if spec.get("points") else "o-"
        ax.plot([xs[i] for i in order], [ys[i] for i in order], style, label=name or None)
        for i in order:
            if spec.get("annotate"):
                ax.annotate(members[i][spec["annotate"]], (xs[i], ys[i]), fontsize=7,
                            xytext=(3, 3), textcoords="offset points")
    ax.set_xlabel(spec["x"])
    ax.set_ylabel(spec["y"])
    ax.set_title(spec.get("title", ""))
    if spec.get("logx"):
        ax.set_xscale("log")
    if spec.get("logy"):
        ax.set_yscale("log")
    ax.grid(True, which="both", alpha=0.3)
    if len(groups) > 1:
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(folder / spec["png"])
    plt.close(fig)


def main(folder: pathlib.Path) -> int:
    specs = json.loads((folder / "plot.json").read_text())
    for spec in specs:
        plot(folder, spec)
        print(f"[plot] {folder / spec['png']}")
    return 0


if __name__ == "__main__":
    sys.exit(main(pathlib.Path(sys.argv[1])))
