// DICOM-RT export: RTSTRUCT, Brachy HDR RTPLAN (standard cumulative time weights) and RTDOSE,
// referencing each other (patient, study and frame of reference from a context).
#include "dicom_rt_io.h"

#include <algorithm>
#include <cctype>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <limits>
#include <map>
#include <memory>
#include <random>
#include <sstream>
#include <stdexcept>

namespace needle_guidance::dose {
using namespace dicom_io;  // NOLINT: the shared DICOM element readers and writers

DicomExportContext newExportContext() {
  DicomExportContext ctx;
  ctx.study_uid = newUid();
  ctx.frame_uid = newUid();
  return ctx;
}

DicomExportContext exportContextFrom(const std::string& path) {
  DcmFileFormat ff;
  const OFCondition st = ff.loadFile(path.c_str());
  if (st.bad()) {
    throw std::invalid_argument("DICOM-RT: " + path + ": cannot read: " + st.text());
  }
  DcmDataset* ds = ff.getDataset();
  DicomExportContext ctx = newExportContext();
  auto copy = [&](const DcmTagKey& key, std::string& into) {
    const std::string v = getString(ds, key);
    if (!v.empty())
      into = v;
  };
  copy(DCM_PatientName, ctx.patient_name);
  copy(DCM_PatientID, ctx.patient_id);
  copy(DCM_PatientBirthDate, ctx.patient_birth_date);
  copy(DCM_PatientSex, ctx.patient_sex);
  copy(DCM_StudyInstanceUID, ctx.study_uid);
  copy(DCM_StudyID, ctx.study_id);
  copy(DCM_StudyDate, ctx.study_date);
  copy(DCM_StudyTime, ctx.study_time);
  // RTSTRUCT: (3006,0010)[0] FrameOfReferenceUID; images: (0020,0052).
  copy(DCM_FrameOfReferenceUID, ctx.frame_uid);
  const auto refs = getItems(ds, DCM_ReferencedFrameOfReferenceSequence);
  if (!refs.empty()) {
    const std::string v = getString(refs[0], DCM_FrameOfReferenceUID);
    if (!v.empty())
      ctx.frame_uid = v;
  }
  return ctx;
}

void writeRtDose(const DoseGrid& grid, const std::string& path) {
  writeRtDose(grid, path, newExportContext());
}

void writeRtDose(const DoseGrid& grid, const std::string& path, const DicomExportContext& ctx) {
  grid.validate("writeRtDose(" + path + ")");
  DcmFileFormat ff;
  DcmDataset* ds = ff.getDataset();
  putCommon(ds, UID_RTDoseStorage, "RTDOSE", path, ctx);
  put(ds, DCM_FrameOfReferenceUID, ctx.frame_uid.empty() ? newUid() : ctx.frame_uid, path);
  put(ds, DCM_PositionReferenceIndicator, "", path);
  if (!ctx.plan_uid.empty()) {
    DcmItem* ref = appendItem(ds, DCM_ReferencedRTPlanSequence, path);
    put(ref, DCM_ReferencedSOPClassUID, UID_RTPlanStorage, path);
    put(ref, DCM_ReferencedSOPInstanceUID, ctx.plan_uid, path);
  }
  put(ds, DCM_ImagePositionPatient,
      formatNumbers(
          {grid.origin_m.x() * kMToMm, grid.origin_m.y() * kMToMm, grid.origin_m.z() * kMToMm}),
      path);
  put(ds, DCM_ImageOrientationPatient, "1\\0\\0\\0\\1\\0", path);
  put(ds, DCM_PixelSpacing,
      formatNumbers({grid.spacing_m.y() * kMToMm, grid.spacing_m.x() * kMToMm}), path);
  ds->putAndInsertUint16(DCM_Rows, static_cast<Uint16>(grid.sizes[1]));
  ds->putAndInsertUint16(DCM_Columns, static_cast<Uint16>(grid.sizes[0]));
  putInt(ds, DCM_NumberOfFrames, grid.sizes[2], path);
  ds->putAndInsertTagKey(DCM_FrameIncrementPointer, DCM_GridFrameOffsetVector);
  ds->putAndInsertUint16(DCM_SamplesPerPixel, 1);
  put(ds, DCM_PhotometricInterpretation, "MONOCHROME2", path);
  ds->putAndInsertUint16(DCM_BitsAllocated, 32);
  ds->putAndInsertUint16(DCM_BitsStored, 32);
  ds->putAndInsertUint16(DCM_HighBit, 31);
  ds->putAndInsertUint16(DCM_PixelRepresentation, 0);
  put(ds, DCM_DoseUnits, "GY", path);
  put(ds, DCM_DoseType, "PHYSICAL", path);
  put(ds, DCM_DoseSummationType, grid.summation_type.empty() ? "PLAN" : grid.summation_type, path);
  std::vector<double> offsets_mm;
  for (const double o : grid.z_offsets_m) {
    offsets_mm.push_back(o * kMToMm);
  }
  put(ds, DCM_GridFrameOffsetVector, formatNumbers(offsets_mm), path);
  const double max = grid.maxDose();
  // Quantise with the scaling exactly as written (DS text), so that reading back reproduces it.
  const std::string scaling_text = formatNumber(max > 0.0 ? max / 4294967295.0 : 1.0);
  const double scaling = std::strtod(scaling_text.c_str(), nullptr);
  put(ds, DCM_DoseGridScaling, scaling_text, path);
  std::vector<Uint16> words(2 * grid.dose_Gy.size());
  for (std::size_t v = 0; v < grid.dose_Gy.size(); ++v) {
    const double q = std::clamp(std::round(grid.dose_Gy[v] / scaling), 0.0, 4294967295.0);
    const Uint32 value = static_cast<Uint32>(q);
    words[2 * v] = static_cast<Uint16>(value & 0xFFFFu);
    words[2 * v + 1] = static_cast<Uint16>(value >> 16);
  }
  const OFCondition st = ds->putAndInsertUint16Array(DCM_PixelData, words.data(),
                                                     static_cast<unsigned long>(words.size()));
  if (st.bad()) {
    throw std::runtime_error("DICOM-RT: " + path + ": cannot set " + tagName(DCM_PixelData) + ": " +
                             st.text());
  }
  save(ff, path);
}

void writeRtStruct(const HdrCase& c, const std::string& path) {
  writeRtStruct(c, path, newExportContext());
}

void writeRtStruct(const HdrCase& c, const std::string& path, const DicomExportContext& ctx) {
  DcmFileFormat ff;
  DcmDataset* ds = ff.getDataset();
  putCommon(ds, UID_RTStructureSetStorage, "RTSTRUCT", path, ctx);
  put(ds, DCM_StructureSetLabel, c.name.empty() ? "needle_guidance" : c.name.substr(0, 16), path);
  put(ds, DCM_StructureSetDate, ctx.study_date, path);
  put(ds, DCM_StructureSetTime, ctx.study_time, path);
  const std::string frame = ctx.frame_uid.empty() ? newUid() : ctx.frame_uid;
  put(ds, DCM_FrameOfReferenceUID, frame, path);
  put(ds, DCM_PositionReferenceIndicator, "", path);
  DcmItem* for_item = appendItem(ds, DCM_ReferencedFrameOfReferenceSequence, path);
  put(for_item, DCM_FrameOfReferenceUID, frame, path);
  const int n_structures = static_cast<int>(c.structures.size());
  auto add_roi = [&](int number, const std::string& name, const std::string& type) {
    DcmItem* roi = appendItem(ds, DCM_StructureSetROISequence, path);
    putInt(roi, DCM_ROINumber, number, path);
    put(roi, DCM_ReferencedFrameOfReferenceUID, frame, path);
    put(roi, DCM_ROIName, name, path);
    put(roi, DCM_ROIGenerationAlgorithm, "", path);
    DcmItem* obs = appendItem(ds, DCM_RTROIObservationsSequence, path);
    putInt(obs, DCM_ObservationNumber, number, path);
    putInt(obs, DCM_ReferencedROINumber, number, path);
    put(obs, DCM_RTROIInterpretedType, type, path);
    put(obs, DCM_ROIInterpreter, "", path);
    DcmItem* rc = appendItem(ds, DCM_ROIContourSequence, path);
    putInt(rc, DCM_ReferencedROINumber, number, path);
    return rc;
  };
  for (int s = 0; s < n_structures; ++s) {
    const Structure& st = c.structures[static_cast<std::size_t>(s)];
    DcmItem* rc = add_roi(s + 1, st.name, st.role == StructureRole::kTarget ? "PTV" : "ORGAN");
    for (const Contour& contour : st.contours) {
      DcmItem* item = appendItem(rc, DCM_ContourSequence, path);
      put(item, DCM_ContourGeometricType, "CLOSED_PLANAR", path);
      putInt(item, DCM_NumberOfContourPoints, static_cast<long>(contour.xy_m.size()), path);
      std::vector<double> data;
      for (const Point2d& p : contour.xy_m) {
        data.insert(data.end(), {p.x() * kMToMm, p.y() * kMToMm, contour.z_m * kMToMm});
      }
      put(item, DCM_ContourData, formatNumbers(data), path);
    }
  }
  for (std::size_t k = 0; k < c.catheters.size(); ++k) {
    const Catheter& cat = c.catheters[k];
    DcmItem* rc = add_roi(n_structures + 1 + static_cast<int>(k), cat.name, "BRACHY_CHANNEL");
    DcmItem* item = appendItem(rc, DCM_ContourSequence, path);
    put(item, DCM_ContourGeometricType, "OPEN_NONPLANAR", path);
    putInt(item, DCM_NumberOfContourPoints, static_cast<long>(cat.points_m.size()), path);
    std::vector<double> data;
    for (const Point3& p : cat.points_m) {
      data.insert(data.end(), {p.x() * kMToMm, p.y() * kMToMm, p.z() * kMToMm});
    }
    put(item, DCM_ContourData, formatNumbers(data), path);
  }
  save(ff, path);
}

namespace {

/// Median spacing of a channel's consecutive dwell positions [mm] (5 mm if it has one).
double channelStepMm(const HdrCase& c, const std::vector<std::size_t>& dwells) {
  std::vector<double> gaps;
  for (std::size_t i = 0; i + 1 < dwells.size(); ++i) {
    const double gap = (c.dwells[dwells[i + 1]].position_m - c.dwells[dwells[i]].position_m).norm();
    if (gap > 1e-6)
      gaps.push_back(gap);
  }
  if (gaps.empty())
    return 5.0;
  std::nth_element(gaps.begin(), gaps.begin() + gaps.size() / 2, gaps.end());
  return std::round(gaps[gaps.size() / 2] * kMToMm * 100.0) / 100.0;
}

}  // namespace

void writeRtPlan(const HdrCase& c, const std::string& path, DwellTimeEncoding encoding) {
  writeRtPlan(c, path, encoding, newExportContext());
}

void writeRtPlan(const HdrCase& c, const std::string& path, DwellTimeEncoding encoding,
                 const DicomExportContext& ctx) {
  const std::string what = "writeRtPlan(" + path + ")";
  if (encoding != DwellTimeEncoding::kStandardCumulative &&
      encoding != DwellTimeEncoding::kPerPairNonCumulative) {
    throw std::invalid_argument(
        what + ": encoding must be standard_cumulative or per_pair_non_cumulative, not " +
        toString(encoding));
  }
  if (!c.dwell_times_s.empty() && c.dwell_times_s.size() != c.dwells.size()) {
    throw std::invalid_argument(what + ": " + std::to_string(c.dwell_times_s.size()) +
                                " dwell times for " + std::to_string(c.dwells.size()) +
                                " dwell positions");
  }
  for (const double t : c.dwell_times_s) {
    if (!std::isfinite(t) || t < 0.0) {
      throw std::invalid_argument(what + ": dwell times must be finite and >= 0");
    }
  }
  if (!(c.air_kerma_strength_U > 0.0) || !(c.prescription_Gy > 0.0)) {
    throw std::invalid_argument(what + ": air-kerma strength and prescription must be > 0");
  }
  std::vector<std::vector<std::size_t>> by_catheter(c.catheters.size());
  for (std::size_t d = 0; d < c.dwells.size(); ++d) {
    const int cat = c.dwells[d].catheter;
    if (cat < 0 || static_cast<std::size_t>(cat) >= c.catheters.size()) {
      throw std::invalid_argument(what + ": dwell " + std::to_string(d) + " refers to catheter " +
                                  std::to_string(cat));
    }
    by_catheter[static_cast<std::size_t>(cat)].push_back(d);
  }
  double total_s = 0.0;
  for (const double t : c.dwell_times_s) {
    total_s += t;
  }

  DcmFileFormat ff;
  DcmDataset* ds = ff.getDataset();
  putCommon(ds, UID_RTPlanStorage, "RTPLAN", path, ctx);
  put(ds, DCM_FrameOfReferenceUID, ctx.frame_uid.empty() ? newUid() : ctx.frame_uid, path);
  put(ds, DCM_PositionReferenceIndicator, "", path);
  put(ds, DCM_RTPlanLabel, c.name.empty() ? "needle_guidance" : c.name.substr(0, 16), path);
  put(ds, DCM_RTPlanDate, ctx.study_date, path);
  put(ds, DCM_RTPlanTime, ctx.study_time, path);
  put(ds, DCM_RTPlanGeometry, "PATIENT", path);
  if (!ctx.structure_set_uid.empty()) {
    DcmItem* ref = appendItem(ds, DCM_ReferencedStructureSetSequence, path);
    put(ref, DCM_ReferencedSOPClassUID, UID_RTStructureSetStorage, path);
    put(ref, DCM_ReferencedSOPInstanceUID, ctx.structure_set_uid, path);
  }
  put(ds, DCM_BrachyTreatmentTechnique, "INTERSTITIAL", path);
  put(ds, DCM_BrachyTreatmentType, "HDR", path);
  DcmItem* dref = appendItem(ds, DCM_DoseReferenceSequence, path);
  putInt(dref, DCM_DoseReferenceNumber, 1, path);
  put(dref, DCM_DoseReferenceStructureType, "SITE", path);
  put(dref, DCM_DoseReferenceType, "TARGET", path);
  put(dref, DCM_TargetPrescriptionDose, c.prescription_Gy, path);
  DcmItem* fg = appendItem(ds, DCM_FractionGroupSequence, path);
  putInt(fg, DCM_FractionGroupNumber, 1, path);
  putInt(fg, DCM_NumberOfFractionsPlanned, 1, path);
  putInt(fg, DCM_NumberOfBeams, 0, path);
  putInt(fg, DCM_NumberOfBrachyApplicationSetups, 1, path);
  DcmItem* rbs = appendItem(fg, DCM_ReferencedBrachyApplicationSetupSequence, path);
  put(rbs, DCM_BrachyApplicationSetupDose, c.prescription_Gy, path);
  putInt(rbs, DCM_ReferencedBrachyApplicationSetupNumber, 1, path);
  DcmItem* src = appendItem(ds, DCM_SourceSequence, path);
  putInt(src, DCM_SourceNumber, 1, path);
  put(src, DCM_SourceType, "LINE", path);
  put(src, DCM_SourceIsotopeName, "Ir-192", path);  // every source in config/sources/ is Ir-192
  put(src, DCM_ReferenceAirKermaRate, c.air_kerma_strength_U, path);
  put(src, DCM_SourceManufacturer, c.source, path);
  put(src, DCM_SourceIsotopeHalfLife, 73.83, path);  // Ir-192 [days]
  put(src, DCM_SourceStrengthReferenceDate, ctx.study_date, path);
  put(src, DCM_SourceStrengthReferenceTime, ctx.study_time, path);
  DcmItem* machine = appendItem(ds, DCM_TreatmentMachineSequence, path);
  put(machine, DCM_TreatmentMachineName, "afterloader", path);
  put(machine, DCM_Manufacturer, "needle_guidance", path);
  DcmItem* setup = appendItem(ds, DCM_ApplicationSetupSequence, path);
  put(setup, DCM_ApplicationSetupType, "PERINEAL", path);  // prostate interstitial HDR
  putInt(setup, DCM_ApplicationSetupNumber, 1, path);
  put(setup, DCM_TotalReferenceAirKerma, c.air_kerma_strength_U * total_s / 3600.0, path);
  const int n_structures = static_cast<int>(c.structures.size());
  int channel_number = 0;
  for (std::size_t k = 0; k < c.catheters.size(); ++k) {
    std::vector<std::size_t>& dwells = by_catheter[k];
    if (dwells.empty()) {
      continue;  // a channel needs control points
    }
    std::stable_sort(dwells.begin(), dwells.end(), [&](std::size_t a, std::size_t b) {
      return c.dwells[a].index < c.dwells[b].index;
    });
    const Catheter& cat = c.catheters[k];
    double channel_s = 0.0;
    for (const std::size_t d : dwells) {
      channel_s += c.dwell_times_s.empty() ? 0.0 : c.dwell_times_s[d];
    }
    DcmItem* ch = appendItem(setup, DCM_ChannelSequence, path);
    putInt(ch, DCM_ChannelNumber, ++channel_number, path);
    put(ch, DCM_ChannelLength, polylineLength(cat.points_m) * kMToMm, path);
    put(ch, DCM_ChannelTotalTime, channel_s, path);
    put(ch, DCM_SourceMovementType, "STEPWISE", path);
    putInt(ch, DCM_ReferencedROINumber, n_structures + 1 + static_cast<long>(k), path);
    putInt(ch, DCM_SourceApplicatorNumber, channel_number, path);
    put(ch, DCM_SourceApplicatorID, cat.name.substr(0, 16), path);
    put(ch, DCM_SourceApplicatorType, "FLEXIBLE", path);
    put(ch, DCM_SourceApplicatorLength, polylineLength(cat.points_m) * kMToMm, path);
    put(ch, DCM_SourceApplicatorStepSize, channelStepMm(c, dwells), path);
    put(ch, DCM_TransferTubeNumber, "", path);
    putInt(ch, DCM_NumberOfControlPoints, static_cast<long>(2 * dwells.size()), path);
    putInt(ch, DCM_ReferencedSourceNumber, 1, path);
    put(ch, DCM_FinalCumulativeTimeWeight, channel_s, path);
    double cumulative = 0.0;
    int cp_index = 0;
    for (const std::size_t d : dwells) {
      const DwellPosition& dw = c.dwells[d];
      const double t = c.dwell_times_s.empty() ? 0.0 : c.dwell_times_s[d];
      const double rel_mm = projectOntoPolyline(cat.points_m, dw.position_m).arc_m * kMToMm;
      const double w0 = encoding == DwellTimeEncoding::kStandardCumulative ? cumulative : 0.0;
      const double w1 = encoding == DwellTimeEncoding::kStandardCumulative ? cumulative + t : t;
      cumulative += t;
      for (const double w : {w0, w1}) {
        DcmItem* cp = appendItem(ch, DCM_BrachyControlPointSequence, path);
        putInt(cp, DCM_ControlPointIndex, cp_index++, path);
        put(cp, DCM_ControlPointRelativePosition, rel_mm, path);
        put(cp, DCM_ControlPoint3DPosition,
            formatNumbers({dw.position_m.x() * kMToMm, dw.position_m.y() * kMToMm,
                           dw.position_m.z() * kMToMm}),
            path);
        put(cp, DCM_CumulativeTimeWeight, w, path);
        const Float32 axis[3] = {static_cast<Float32>(dw.axis.x()),
                                 static_cast<Float32>(dw.axis.y()),
                                 static_cast<Float32>(dw.axis.z())};
        cp->putAndInsertFloat32Array(DCM_ControlPointOrientation, axis, 3);
      }
    }
  }
  save(ff, path);
}

}  // namespace needle_guidance::dose
