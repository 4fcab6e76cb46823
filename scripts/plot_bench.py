#!/usr/bin/python3
"""Plots a benchmark folder: reads plot.json written by the bench tool, a list of
{"csv", "x", "y", "group", "title", "logx", "logy", "points", "annotate", "png"} entries, and draws each CSV's
y against x (one line per group) to the PNG. Speed against error, as DESIGN.md asks."""
import csv
import json
import pathlib
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def plot(folder: pathlib.Path, spec: dict) -> None:
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
