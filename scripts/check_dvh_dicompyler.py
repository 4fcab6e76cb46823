#!/usr/bin/python3
"""Independent check of our dose-volume indices on a DICOM-RT plan's RTDOSE.

Usage: check_dvh_dicompyler.py DICOM_DIR OURS_CSV OUT_CSV [CONVERGENCE_CSV CONVERGENCE_OUT_CSV]

OURS_CSV (written by bench_hdr_dicom) has the columns index, rx_gy, ours, ours_on_dose_grid,
reason: our index from the RTDOSE as reported (trilinear interpolation on our structure-aligned
lattice), empty when we report it undefined (reason says why), and our index code on
dicompyler's default discretisation. CONVERGENCE_CSV (spacing_mm, planes_per_slice, index,
value) holds our index as the lattice is refined.

dicompyler-core (python3-dicompylercore) computes every index from the RTDOSE and RTSTRUCT:
- with its defaults: dose-grid pixels, dose at each contour's plane, each pixel one slice thick;
- with its interpolation as shipped (interpolation_resolution, for the record);
- with its interpolation corrected (corrected_interpolation below), at RESOLUTIONS_MM in plane
  and PLANES_PER_SLICE sample planes per contour slab. As shipped, its interpolated dose sits
  up to 0.6 pixel from the contour points it is paired with, and its planes between contours
  take the nearest dose frame and drop half a slab at each end: refined, it moves away from
  the converged value instead of towards it.
Also read: the cumulative DVHs stored in the RTDOSE (DVHSequence; linear between bin edges).

Writes OUT_CSV (one row per index), CONVERGENCE_OUT_CSV (every calculator at every
discretisation) and prints a JSON summary of the largest differences (Gy for D indices,
percentage points for V indices) over the indices we report defined (an undefined one is never
compared):
- matched: ours against corrected dicompyler at the same discretisation (MATCHED);
- converged: ours at our finest lattice against corrected dicompyler at its finest;
- ours_vs_converged: ours as reported against corrected dicompyler at its finest;
- default, on_grid, as_shipped, stored: ours (on_grid: ours_on_dose_grid) against dicompyler's
  defaults, its shipped interpolation at 0.25 mm, and the stored DVHs.
Exit 0 after a check, 3 when dicompyler-core or pydicom is missing (nothing checked), 2 on bad
input.
"""

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

import collections
import contextlib
import numpy as np
from dicompylercore import dicomparser

# Refined runs: in-plane interpolation resolution [mm] x sample planes per contour slab.
RESOLUTIONS_MM = (0.5, 0.25, 0.125)
PLANES_PER_SLICE = (1, 2, 4)
MATCHED = (0.125, 4)  # the discretisation both sides are compared at (ours: lattice 0.125 mm)


def registered_lut(index_extents, extents, new_pixel_spacing, min_pixel_spacing):
    """Positions of the samples skimage's rescale returns for the dose-grid extract
    d[ymin:ymax, xmin:xmax]: input pixel (k + 1/2)/s - 1/2 for output pixel k, s = scale.
    dicompyler's get_resampled_lut spreads the same number of samples evenly from the first to
    the last extent pixel instead, which pairs each dose value with a contour point up to 0.6
    pixel away from where the dose was interpolated."""
    s = min_pixel_spacing / new_pixel_spacing
    out = []
    for a in (0, 1):
        n = int(round(abs(index_extents[a + 2] - index_extents[a]) * s))
        out.append(extents[a] + ((np.arange(n) + 0.5) / s - 0.5) * min_pixel_spacing)
    return tuple(out)


def slab_planes(planes, n=1):
    """n + 1 sample planes per contour slab, centred in the slab (one slice thick, as the
    default run's volume counts it), each cut through the slab's own contour. dicompyler's
    interpolate_between_planes spreads them from the first to the last contour plane instead,
    dropping half a slab at each end."""
    keys = sorted(planes.keys(), key=float)
    h = min(float(b) - float(a) for a, b in zip(keys, keys[1:])) if len(keys) > 1 else 0.0
    out = collections.OrderedDict()
    for k in keys:
        for m in range(n + 1):
            out[float(k) + ((m + 0.5) / (n + 1) - 0.5) * h] = planes[k]
    return out


@contextlib.contextmanager
def corrected_interpolation():
    """dicompyler-core's interpolation options with three corrections (registration of the
    interpolated dose, slab-centred sub-planes, dose linear between dose frames: GetDoseGrid takes
    the nearest frame within 0.5 mm otherwise) and one more pixel of margin around the structure
    (the dose extract stops one pixel short of the extent)."""
    saved = (dvhcalc.get_resampled_lut, dvhcalc.interpolate_between_planes,
             dvhcalc.dosegrid_extents_indices, dicomparser.DicomParser.GetDoseGrid)
    grid, extents = saved[3], saved[2]
    dvhcalc.get_resampled_lut = registered_lut
    dvhcalc.interpolate_between_planes = slab_planes
    dvhcalc.dosegrid_extents_indices = lambda e, dd, padding=1: extents(e, dd, padding + 1)
    dicomparser.DicomParser.GetDoseGrid = lambda self, z=0, threshold=0.5: grid(self, z, 1e-6)
    try:
        yield
    finally:
        (dvhcalc.get_resampled_lut, dvhcalc.interpolate_between_planes,
         dvhcalc.dosegrid_extents_indices, dicomparser.DicomParser.GetDoseGrid) = saved


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


def dicompyler_runs(rtstruct, rtdose, rois):
    """(calculator, resolution mm or None, planes per slice, roi) -> DVH: dicompyler's defaults,
    its interpolation as shipped, and its interpolation corrected (corrected_interpolation)."""
    runs = {}
    for roi in rois:
        runs[("default", None, 1, roi)] = dvhcalc.get_dvh(rtstruct, rtdose, roi,
                                                          use_structure_extents=True)
        for res in RESOLUTIONS_MM:
            runs[("as_shipped", res, 1, roi)] = dvhcalc.get_dvh(
                rtstruct, rtdose, roi, interpolation_resolution=res, use_structure_extents=True)
        with corrected_interpolation():
            for res in RESOLUTIONS_MM:
                for n in PLANES_PER_SLICE:
                    runs[("corrected", res, n, roi)] = dvhcalc.get_dvh(
                        rtstruct, rtdose, roi, interpolation_resolution=res,
                        interpolation_segments_between_planes=n - 1, use_structure_extents=True)
    return runs


def read_convergence(path):
    """(spacing_mm, planes_per_slice) -> {index: value or None} from bench_hdr_dicom's CSV."""
    out = collections.defaultdict(dict)
    with open(path) as f:
        for r in csv.DictReader(f):
            key = (float(r["spacing_mm"]), int(r["planes_per_slice"]))
            out[key][r["index"]] = float(r["value"]) if r["value"] != "" else None
    return out


class Worst:
    """Largest |a - b| per unit (pp for V indices, Gy for D indices) and where."""

    def __init__(self):
        self.value = {"pp": 0.0, "gy": 0.0}
        self.index = {"pp": "", "gy": ""}

    def add(self, index, a, b):
        if a is None or b is None or a == "" or b == "":
            return
        unit = "gy" if index.split("_", 1)[1].startswith("D") else "pp"
        if abs(a - b) > self.value[unit]:
            self.value[unit] = abs(a - b)
            self.index[unit] = index

    def into(self, summary, name):
        for unit in ("pp", "gy"):
            summary["max_diff_%s_%s" % (name, unit)] = round(self.value[unit], 4)
        summary["worst_%s" % name] = [self.index["pp"], self.index["gy"]]


def main():
    if len(sys.argv) not in (4, 6):
        sys.exit(__doc__)
    folder, ours_csv, out_csv = sys.argv[1:4]
    rtstruct, rtdose = find_files(folder)
    rois = roi_numbers(rtstruct)
    stored = stored_curves(rtdose)
    with open(ours_csv) as f:
        ours = list(csv.DictReader(f))
    used = sorted({rois[r["index"].split("_", 1)[0]] for r in ours
                   if r["index"].split("_", 1)[0] in rois})
    runs = dicompyler_runs(rtstruct, rtdose, used)
    convergence = read_convergence(sys.argv[4]) if len(sys.argv) == 6 else {}
    m_res, m_planes = MATCHED
    worst = {k: Worst() for k in ("matched", "default", "on_grid", "as_shipped", "stored",
                                  "ours_vs_converged", "converged")}
    rows, conv_rows = [], []
    finest_ours = (min(k[0] for k in convergence), max(k[1] for k in convergence)) \
        if convergence else None
    converged_key = ("corrected", min(RESOLUTIONS_MM), max(PLANES_PER_SLICE))
    for r in ours:
        structure, spec = r["index"].split("_", 1)
        rx = float(r["rx_gy"])
        roi = rois.get(structure)
        if roi is None:
            continue
        value = {k[:3]: from_dicompyler(dvh, spec, rx) for k, dvh in runs.items() if k[3] == roi}
        o = float(r["ours"]) if r["ours"] != "" else None
        on_grid = float(r["ours_on_dose_grid"]) if r.get("ours_on_dose_grid", "") != "" else None
        s = from_stored(stored[roi], spec, rx) if roi in stored else None
        matched = convergence.get((m_res, m_planes), {}).get(r["index"])
        finest = convergence[finest_ours].get(r["index"]) if finest_ours else None
        row = {"index": r["index"], "ours": r["ours"], "reason": r.get("reason", ""),
               "ours_on_dose_grid": "" if on_grid is None else on_grid,
               "ours_matched": "" if matched is None else matched,
               "dicompyler_matched": value[("corrected", m_res, m_planes)],
               "ours_converged": "" if finest is None else finest,
               "dicompyler_converged": value[converged_key],
               "dicompyler_default": value[("default", None, 1)],
               "dicompyler_0.25mm_as_shipped": value[("as_shipped", 0.25, 1)],
               "stored_dvh": "" if s is None else s}
        if o is not None:  # an index ours reports undefined is never compared
            worst["matched"].add(r["index"], matched, row["dicompyler_matched"])
            worst["default"].add(r["index"], o, row["dicompyler_default"])
            worst["on_grid"].add(r["index"], on_grid, row["dicompyler_default"])
            worst["as_shipped"].add(r["index"], o, row["dicompyler_0.25mm_as_shipped"])
            worst["stored"].add(r["index"], o, s)
            worst["ours_vs_converged"].add(r["index"], o, row["dicompyler_converged"])
            worst["converged"].add(r["index"], finest, row["dicompyler_converged"])
        rows.append(row)
        for (calc, res, n), v in sorted(value.items(), key=str):
            conv_rows.append({"calculator": "dicompyler_" + calc, "spacing_mm": res or "",
                              "planes_per_slice": n, "index": r["index"], "value": v})
        for (res, n), values in sorted(convergence.items()):
            v = values.get(r["index"])
            conv_rows.append({"calculator": "ours", "spacing_mm": res, "planes_per_slice": n,
                              "index": r["index"], "value": "" if v is None else v})
    with open(out_csv, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0].keys()) if rows else ["index"])
        w.writeheader()
        w.writerows(rows)
    if len(sys.argv) == 6:
        with open(sys.argv[5], "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=["calculator", "spacing_mm", "planes_per_slice",
                                              "index", "value"])
            w.writeheader()
            w.writerows(conv_rows)
    summary = {"dicompyler_available": True, "indices": len(rows),
               "matched_spacing_mm": m_res, "matched_planes_per_slice": m_planes,
               "converged_dicompyler": list(converged_key[1:]),
               "converged_ours": list(finest_ours) if finest_ours else None}
    for name, wst in worst.items():
        wst.into(summary, name)
    print(json.dumps(summary))


if __name__ == "__main__":
    if any(a in ("-h", "--help") for a in sys.argv[1:]):
        print(__doc__ + "\nusage: check_dvh_dicompyler.py CASE_DIR OURS_CSV OUT_CSV "
              "[CONVERGENCE_CSV CONVERGENCE_OUT_CSV]")
        sys.exit(0)
    main()
