#!/usr/bin/python3
"""Reads an exported DICOM-RT folder (RS.dcm, RP.dcm, RD.dcm optional) with pydicom, an
independent reader, and checks what the export promises: modalities and SOP classes, the
RTPLAN -> RTSTRUCT and RTDOSE -> RTPLAN references, Brachy HDR with standard (monotonic)
cumulative time weights ending at FinalCumulativeTimeWeight = ChannelTotalTime, and the channels
referencing BRACHY_CHANNEL ROIs. Prints the total dwell time; exit 0 if every check passes.
Usage: check_rt_export.py DIR"""
import pathlib
import sys

import pydicom


def main(folder: pathlib.Path) -> int:
    errors = []
    rs = pydicom.dcmread(folder / "RS.dcm")
    rp = pydicom.dcmread(folder / "RP.dcm")
    if rs.Modality != "RTSTRUCT" or rs.SOPClassUID != "1.2.840.10008.5.1.4.1.1.481.3":
        errors.append("RS.dcm is not an RT Structure Set")
    if rp.Modality != "RTPLAN" or rp.SOPClassUID != "1.2.840.10008.5.1.4.1.1.481.5":
        errors.append("RP.dcm is not an RT Plan")
    if rp.BrachyTreatmentType != "HDR":
        errors.append("RP.dcm BrachyTreatmentType is not HDR")
    if rp.ReferencedStructureSetSequence[0].ReferencedSOPInstanceUID != rs.SOPInstanceUID:
        errors.append("RP.dcm does not reference RS.dcm")
    channel_rois = {o.ReferencedROINumber for o in rs.RTROIObservationsSequence
                    if o.RTROIInterpretedType == "BRACHY_CHANNEL"}
    total = 0.0
    for ch in rp.ApplicationSetupSequence[0].ChannelSequence:
        w = [float(cp.CumulativeTimeWeight) for cp in ch.BrachyControlPointSequence]
        if any(b < a - 1e-9 for a, b in zip(w, w[1:])):
            errors.append(f"channel {ch.ChannelNumber}: cumulative time weights not monotonic")
        if abs(w[-1] - float(ch.FinalCumulativeTimeWeight)) > 1e-6:
            errors.append(f"channel {ch.ChannelNumber}: last weight != FinalCumulativeTimeWeight")
        if ch.ReferencedROINumber not in channel_rois:
            errors.append(f"channel {ch.ChannelNumber}: ROI {ch.ReferencedROINumber} is no BRACHY_CHANNEL")
        total += float(ch.ChannelTotalTime)
    rd_path = folder / "RD.dcm"
    if rd_path.exists():
        rd = pydicom.dcmread(rd_path)
        if rd.Modality != "RTDOSE" or rd.DoseUnits != "GY":
            errors.append("RD.dcm is not an RTDOSE in Gy")
        if rd.ReferencedRTPlanSequence[0].ReferencedSOPInstanceUID != rp.SOPInstanceUID:
            errors.append("RD.dcm does not reference RP.dcm")
        pixels = rd.pixel_array
        if pixels.shape != (int(rd.NumberOfFrames), int(rd.Rows), int(rd.Columns)):
            errors.append(f"RD.dcm pixel array shape {pixels.shape}")
    for e in errors:
        print("error:", e)
    print(f"pydicom: total dwell time {total:.3f} s, {len(errors)} errors")
    return 1 if errors else 0


if __name__ == "__main__":
    if len(sys.argv) != 2 or sys.argv[1] in ("-h", "--help"):
        help_asked = len(sys.argv) == 2
        print(__doc__ + "\nusage: check_rt_export.py DIR", file=sys.stdout if help_asked else sys.stderr)
        sys.exit(0 if help_asked else 2)
    sys.exit(main(pathlib.Path(sys.argv[1])))
