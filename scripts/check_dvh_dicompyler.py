#!/usr/bin/python3
"""Independent check of our dose-volume indices on a DICOM-RT plan's RTDOSE.

Usage: check_dvh_dicompyler.py DICOM_DIR OURS_CSV OUT_CSV

OURS_CSV (written by bench_hdr_dicom) has the columns index, rx_gy, ours, reason: our index
from the RTDOSE (trilinear interpolation on our structure-aligned lattice), empty when our
method reports it undefined (reason says why). For every index this script computes the same
index with dicompyler-core (python3-dicompylercore) from the RTDOSE and RTSTRUCT, twice: with
its defaults (dose-grid pixels, 1 mm here) and with in-plane interpolation to 0.25 mm, and from
the cumulative DVHs stored in the RTDOSE (DVHSequence; linear between bin edges). Writes
OUT_CSV and prints a JSON summary: the largest |ours - dicompyler| over the indices defined by
ours (Gy for D indices, percentage points for V indices). Exit 0 after a check, 3 when
dicompyler-core or pydicom is missing (nothing checked), 2 on bad input.

Telling a discretisation difference from an error: OURS_CSV may also have the column
ours_on_dose_grid, our index code run on dicompyler's own discretisation (the dose grid's
in-plane voxel centres inside each contour, at the contour's plane, each voxel area x slice
thickness). An index whose |ours - dicompyler default| exceeds the tolerance (0.3 Gy, 1 pp)
while ours_on_dose_grid agrees with dicompyler within it is "not comparable": the difference
comes from the two discretisations, not from the index. It is listed with the figures in
not_comparable and left out of max_diff_comparable_*. Every other index counts there, so a
real error is never hidden. max_diff_on_grid_* is the largest |ours_on_dose_grid -
dicompyler default| over all indices.
"""

TOLERANCE = {"gy": 0.3, "pp": 1.0}
import csv
import glob
import json
import os
import re
import sys
import warnings

warnings.filterwarnings("ignore")
try:
    import pydicom
    from dicompylercore import dvhcalc
except ImportError as e:  # the check is optional: say so, do not fail the benchmark
    print(json.dumps({"dicompyler_available": False, "reason": str(e)}))
    sys.exit(3)

CANONICAL = {"prostate": ["prostate", "ctv", "ptv"], "urethra": ["urethra"],
             "rectum": ["rectum"], "bladder": ["bladder"]}


def find_files(folder):
    """RTSTRUCT and RTDOSE paths of the folder, by SOP class."""
    found = {}
    for path in sorted(glob.glob(os.path.join(folder, "*"))):
        try:
            ds = pydicom.dcmread(path, stop_before_pixels=True)
        except Exception:  # not DICOM
            continue
        modality = str(ds.get("Modality", ""))
        if modality in ("RTSTRUCT", "RTDOSE") and modality not in found:
            found[modality] = path
    if "RTSTRUCT" not in found or "RTDOSE" not in found:
        sys.exit("check_dvh_dicompyler: %s: needs an RTSTRUCT and an RTDOSE" % folder)
    return found["RTSTRUCT"], found["RTDOSE"]


def roi_numbers(rtstruct):
    """canonical name -> ROI number (first name of CANONICAL that matches, case-insensitive)."""
    ds = pydicom.dcmread(rtstruct)
    by_name = {str(r.ROIName).strip().lower(): int(r.ROINumber)
               for r in ds.StructureSetROISequence}
    return {c: by_name[n] for c, names in CANONICAL.items() for n in names if n in by_name}


def parse(spec):
    """'V125' -> ('V', 125, False); 'D10' -> ('D', 10, False); 'D0.1cc' -> ('D', 0.1, True)."""
    m = re.fullmatch(r"([VD])([0-9.]+)(cc)?", spec)
    if not m:
        raise ValueError("index spec %r" % spec)
    return m.group(1), float(m.group(2)), bool(m.group(3))


def from_dicompyler(dvh, spec, rx):
    kind, x, cc = parse(spec)
    if kind == "V":
        return float(dvh.relative_volume.statistic("V%gGy" % (x / 100.0 * rx)).value)
    return float(dvh.statistic("D%gcc" % x if cc else "D%g" % x).value)


def stored_curves(rtdose):
    """ROI number -> (dose bin edges [Gy], cumulative volume [cm3]) from DVHSequence."""
    ds = pydicom.dcmread(rtdose, stop_before_pixels=True)
    out = {}
    for d in ds.get("DVHSequence", []):
        if str(d.DVHType) != "CUMULATIVE" or str(d.DoseUnits) != "GY":
            continue
        data = [float(v) for v in d.DVHData]
        scale = float(d.get("DVHDoseScaling", 1.0))
        edges, volumes, dose = [], [], 0.0
        for width, volume in zip(data[0::2], data[1::2]):
            edges.append(dose)
            volumes.append(volume)
            dose += width * scale
        edges.append(dose)
        volumes.append(0.0)
        out[int(d.DVHReferencedROISequence[0].ReferencedROINumber)] = (edges, volumes)
    return out


def from_stored(curve, spec, rx):
    """The index from a stored cumulative DVH, or None past the curve's dose range."""
    edges, volumes = curve
    total = volumes[0]
    kind, x, cc = parse(spec)
    if kind == "V":
        level = x / 100.0 * rx
        if level >= edges[-1]:
            return 0.0
        for i in range(len(edges) - 1):
            if edges[i] <= level <= edges[i + 1]:
                f = (level - edges[i]) / (edges[i + 1] - edges[i])
                return 100.0 * (volumes[i] + f * (volumes[i + 1] - volumes[i])) / total
    want = x if cc else x / 100.0 * total
    if want > total:
        return None
    for i in range(len(edges) - 1):
        if volumes[i] >= want >= volumes[i + 1]:
            if volumes[i + 1] == 0.0 and i + 1 == len(edges) - 1:
                return None  # the curve ends there: the dose lies beyond its range
            f = (volumes[i] - want) / max(volumes[i] - volumes[i + 1], 1e-12)
            return edges[i] + f * (edges[i + 1] - edges[i])
    return None


def judge(index, ours, on_grid, reference, unit, comparable, row):
    """Counts |ours - reference| as comparable unless ours on the reference's discretisation
    (on_grid) agrees with it while ours does not; records the reason in row and comparable."""
    tol = TOLERANCE["gy" if unit else "pp"]
    diff = abs(ours - reference)
    row["comparable"] = 1
    if on_grid == "":
        comparable["comparable"][0][unit].append(diff)
        return
    grid_diff = abs(float(on_grid) - reference)
    comparable["on_grid"][0][unit].append(grid_diff)
    if diff > tol and grid_diff <= tol:
        row["comparable"] = 0
        comparable["comparable"][1][index] = (
            "discretisation: ours %.3f on our lattice, %.3f on dicompyler's grid, dicompyler "
            "%.3f (%s)" % (ours, float(on_grid), reference, "Gy" if unit else "%"))
    else:
        comparable["comparable"][0][unit].append(diff)


def main():
    if len(sys.argv) != 4:
        sys.exit(__doc__)
    folder, ours_csv, out_csv = sys.argv[1:]
    rtstruct, rtdose = find_files(folder)
    rois = roi_numbers(rtstruct)
    stored = stored_curves(rtdose)
    with open(ours_csv) as f:
        ours = list(csv.DictReader(f))
    dvhs = {}
    # name -> ([diffs in pp], [diffs in Gy]), and for "comparable" the excluded indices.
    comparable = {"comparable": ([[], []], {}), "on_grid": ([[], []], {})}
    rows, worst = [], {"default": [0.0, 0.0], "interpolated": [0.0, 0.0], "stored": [0.0, 0.0]}
    worst_key = {k: ["", ""] for k in worst}
    for r in ours:
        structure, spec = r["index"].split("_", 1)
        rx = float(r["rx_gy"])
        roi = rois.get(structure)
        if roi is None:
            continue
        for mode, res in (("default", None), ("interpolated", 0.25)):
            if (roi, mode) not in dvhs:
                dvhs[(roi, mode)] = dvhcalc.get_dvh(rtstruct, rtdose, roi,
                                                    interpolation_resolution=res,
                                                    use_structure_extents=True)
        row = {"index": r["index"], "ours": r["ours"], "reason": r.get("reason", ""),
               "ours_on_dose_grid": r.get("ours_on_dose_grid", ""), "comparable": ""}
        row["dicompyler_default"] = from_dicompyler(dvhs[(roi, "default")], spec, rx)
        row["dicompyler_0.25mm"] = from_dicompyler(dvhs[(roi, "interpolated")], spec, rx)
        s = from_stored(stored[roi], spec, rx) if roi in stored else None
        row["stored_dvh"] = "" if s is None else s
        unit = 1 if spec.startswith("D") else 0  # [pp, Gy] slot
        if r["ours"] != "":
            o = float(r["ours"])
            for mode, ref in (("default", row["dicompyler_default"]),
                              ("interpolated", row["dicompyler_0.25mm"]),
                              ("stored", s)):
                if ref is None or ref == "":
                    continue
                diff = abs(o - ref)
                if diff > worst[mode][unit]:
                    worst[mode][unit] = diff
                    worst_key[mode][unit] = r["index"]
            judge(r["index"], o, r.get("ours_on_dose_grid", ""), row["dicompyler_default"],
                  unit, comparable, row)
        rows.append(row)
    with open(out_csv, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=["index", "ours", "ours_on_dose_grid",
                                          "dicompyler_default", "dicompyler_0.25mm",
                                          "stored_dvh", "comparable", "reason"])
        w.writeheader()
        w.writerows(rows)
    summary = {"dicompyler_available": True, "indices": len(rows)}
    for name, (values, _) in comparable.items():
        for unit, slot in (("pp", 0), ("gy", 1)):
            summary["max_diff_%s_%s" % (name, unit)] = round(max(values[slot], default=0.0), 4)
    summary["not_comparable"] = comparable["comparable"][1]
    for mode in worst:
        summary["max_diff_%s_pp" % mode] = round(worst[mode][0], 4)
        summary["max_diff_%s_gy" % mode] = round(worst[mode][1], 4)
        summary["worst_%s" % mode] = worst_key[mode]
    print(json.dumps(summary))


if __name__ == "__main__":
    if any(a in ("-h", "--help") for a in sys.argv[1:]):
        print(__doc__ + "\nusage: check_dvh_dicompyler.py CASE_DIR OURS_CSV OUT_CSV")
        sys.exit(0)
    main()
