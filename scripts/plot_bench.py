#!/usr/bin/python3
"""Plots a benchmark folder: reads plot.json written by the bench tool, a list of
{"csv", "x", "y", "group", "filter", "title", "logx", "logy", "points", "annotate", "png"} entries, and draws each CSV's
y against x (one line per group) to the PNG; entries with "kind": "isodose" draw isodose lines,
"kind": "paths" needle paths over obstacles (figure 5.8), "kind": "heatmap" a value over two
columns (figure 5.7). Speed is always plotted against error."""
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


def read_rows(path: pathlib.Path) -> list:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def paths(folder: pathlib.Path, spec: dict) -> None:
    """{"kind": "paths", "paths": trial,x_mm,y_mm, "decisions": trial,x_mm,y_mm,control,
    "contours": structure,contour,x_mm,y_mm, "target": [x_mm, y_mm, r_mm],
    "bounds": [x0, y0, x1, y1], "max_paths", "title", "png"}: needle paths with their decision
    points (small dots insert, large dots flip) over the obstacles and the target."""
    fig, ax = plt.subplots(figsize=(6.0, 6.0), dpi=110)
    outlines = {}
    for r in read_rows(folder / spec["contours"]):
        outlines.setdefault((r["structure"], r["contour"]), []).append((float(r["x_mm"]), float(r["y_mm"])))
    for (structure, _), pts in outlines.items():
        xs = [p[0] for p in pts] + [pts[0][0]]
        ys = [p[1] for p in pts] + [pts[0][1]]
        if structure == "obstacle":
            ax.fill(xs, ys, color="0.55", zorder=1)
        else:
            ax.plot(xs, ys, color="0.55", ls="--", lw=0.7, zorder=1)
    tx, ty, tr = spec["target"]
    ax.add_patch(plt.Circle((tx, ty), tr, fill=False, color="green", lw=1.5, zorder=2))
    trials = {}
    for r in read_rows(folder / spec["paths"]):
        trials.setdefault(r["trial"], []).append((float(r["x_mm"]), float(r["y_mm"])))
    decisions = {}
    for r in read_rows(folder / spec["decisions"]):
        decisions.setdefault(r["trial"], []).append(r)
    shown = list(trials)[: spec.get("max_paths", len(trials))]
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for i, trial in enumerate(shown):
        c = colours[i % len(colours)]
        pts = trials[trial]
        ax.plot([p[0] for p in pts], [p[1] for p in pts], "-", color=c, lw=1.0, zorder=3,
                label=f"trial {trial}")
        for d in decisions.get(trial, []):
            big = d["control"] == "flip"
            ax.plot(float(d["x_mm"]), float(d["y_mm"]), "o", color=c, ms=6 if big else 2.5, zorder=4)
    x0, y0, x1, y1 = spec["bounds"]
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    ax.set_aspect("equal")
    ax.set_xlabel("x_mm")
    ax.set_ylabel("y_mm")
    ax.set_title(spec.get("title", ""), fontsize=9)
    ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    fig.savefig(folder / spec["png"])
    plt.close(fig)


def heatmap(folder: pathlib.Path, spec: dict) -> None:
    """{"kind": "heatmap", "csv", "x", "y", "value", "filter": {column: value}, "title", "png"}."""
    rows = [r for r in read_rows(folder / spec["csv"])
            if all(r.get(k) == v for k, v in spec.get("filter", {}).items())]
    xs = sorted({float(r[spec["x"]]) for r in rows})
    ys = sorted({float(r[spec["y"]]) for r in rows})
    xi = {x: i for i, x in enumerate(xs)}
    yi = {y: j for j, y in enumerate(ys)}
    grid = [[float("nan")] * len(xs) for _ in ys]
    for r in rows:
        grid[yi[float(r[spec["y"]])]][xi[float(r[spec["x"]])]] = float(r[spec["value"]])
    fig, ax = plt.subplots(figsize=(6.4, 4.8), dpi=110)
    mesh = ax.pcolormesh(xs, ys, grid, shading="nearest", cmap="viridis", vmin=0.0,
                         vmax=max(1e-9, max(float(r[spec["value"]]) for r in rows)))
    fig.colorbar(mesh, ax=ax, label=spec["value"])
    ax.set_xlabel(spec["x"])
    ax.set_ylabel(spec["y"])
    ax.set_title(spec.get("title", ""), fontsize=9)
    fig.tight_layout()
    fig.savefig(folder / spec["png"])
    plt.close(fig)


def plot(folder: pathlib.Path, spec: dict) -> None:
    kinds = {"isodose": isodose, "paths": paths, "heatmap": heatmap}
    if spec.get("kind") in kinds:
        kinds[spec["kind"]](folder, spec)
        return
    with open(folder / spec["csv"], newline="") as f:
        rows = [r for r in csv.DictReader(f)
                if all(r.get(k) == v for k, v in spec.get("filter", {}).items())]
    groups = {}
    for row in rows:
        groups.setdefault(row.get(spec.get("group", ""), ""), []).append(row)
    fig, ax = plt.subplots(figsize=(6.4, 4.4), dpi=110)
    for name, members in groups.items():
        # An empty cell is a figure the run could not give (a refused case): it is not drawn.
        members = [r for r in members if r.get(spec["x"], "") != "" and r.get(spec["y"], "") != ""]
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
    if len(sys.argv) != 2 or sys.argv[1] in ("-h", "--help"):
        help_asked = len(sys.argv) == 2
        print(__doc__ + "\nusage: plot_bench.py BENCH_REPORT_DIR", file=sys.stdout if help_asked else sys.stderr)
        sys.exit(0 if help_asked else 2)
    sys.exit(main(pathlib.Path(sys.argv[1])))
