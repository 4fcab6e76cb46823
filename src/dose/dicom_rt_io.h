// DICOM-RT element reading, loading, geometry and writing functions shared by the importer
// (dicom_rt_import.cpp), the exporter (dicom_rt_export.cpp) and the validation
// (dicom_rt_validation.cpp). Private to src/dose/.
#pragma once

#include "needle_guidance/dose/dicom_rt.h"

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
#include <optional>
#include <random>
#include <sstream>
#include <stdexcept>

// DCMTK is a private dependency of the core (CMakeLists.txt); its headers are system headers
// there, the pragmas keep -Werror quiet should they not be.
#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Wall"
#pragma GCC diagnostic ignored "-Wextra"
#include <dcmtk/config/osconfig.h>
#include <dcmtk/dcmdata/dctk.h>
#pragma GCC diagnostic pop

namespace needle_guidance::dose::dicom_io {

constexpr double kMmToM = 1e-3;
constexpr double kMToMm = 1e3;
/// Two control points within this distance are at the same dwell position [mm].
constexpr double kSamePositionTol_mm = 1e-2;
/// Contour vertices this far from their contour's first z make it non-axial [mm].
constexpr double kPlanarTol_mm = 5e-2;
/// ImageOrientationPatient components may differ this much from 1\0\0\0\1\0.
constexpr double kOrientationTol = 1e-4;
/// Above this angle between ControlPointOrientation and the catheter direction, warn [rad].
constexpr double kAxisWarnAngle_rad = 10.0 * M_PI / 180.0;

// ---- errors ----------------------------------------------------------------------------------

/// Throws std::invalid_argument "DICOM-RT: FILE: WHERE: REASON" (WHERE omitted when empty).
[[noreturn]] void fail(const std::string& file, const std::string& where,
                       const std::string& reason);

/// "CumulativeTimeWeight (300a,02d6)".
std::string tagName(const DcmTagKey& key);

/// "a > b", or b alone when a is empty: the path to an element in errors.
std::string join(const std::string& a, const std::string& b);

/// join(parent, "SequenceName[index]").
std::string itemContext(const std::string& parent, const DcmTagKey& seq, unsigned long index);

/// s in lower case (ASCII).
std::string lower(std::string s);

/// s without leading and trailing blanks.
std::string trim(const std::string& s);

/// A DS value: at most 10 significant digits (fits the 16 characters of DS).
std::string formatNumber(double v);

/// Values as one multi-valued DS string, separated by backslashes.
std::string formatNumbers(const std::vector<double>& values);

// ---- reading elements ------------------------------------------------------------------------

/// A loaded DICOM file and where it came from.
struct Loaded {
  std::string path;
  std::unique_ptr<DcmFileFormat> file;
  DcmDataset* data = nullptr;
};

/// The element `key` of `item`, or nullptr when absent.
DcmElement* findElement(DcmItem* item, const DcmTagKey& key);

/// Value `pos` of a numeric element of any numeric VR (DS, IS, FL, FD, US, UL, SS, SL, or a
/// string that parses). Throws for a value that is present but not a finite number.
double elementNumber(DcmElement* e, unsigned long pos, const std::string& file,
                     const std::string& where);

/// All values of a numeric element, empty if it is absent or has no value.
std::vector<double> getNumbers(DcmItem* item, const DcmTagKey& key, const std::string& file,
                               const std::string& where);

/// The first value of a numeric element; nullopt if absent or empty.
std::optional<double> getNumber(DcmItem* item, const DcmTagKey& key, const std::string& file,
                                const std::string& where);

/// The first value of a numeric element; throws (fail) if absent.
double requireNumber(DcmItem* item, const DcmTagKey& key, const std::string& file,
                     const std::string& where);

/// Exactly `count` values of a numeric element; throws (fail) otherwise.
std::vector<double> requireNumbers(DcmItem* item, const DcmTagKey& key, std::size_t count,
                                   const std::string& file, const std::string& where);

/// An integer element; throws (fail) if absent or not an integer.
int requireInt(DcmItem* item, const DcmTagKey& key, const std::string& file,
               const std::string& where);

/// An integer element; nullopt if absent, throws (fail) if not an integer.
std::optional<int> getInt(DcmItem* item, const DcmTagKey& key, const std::string& file,
                          const std::string& where);

/// A string element, trimmed; empty if absent.
std::string getString(DcmItem* item, const DcmTagKey& key);

/// Items of a sequence (empty vector if absent).
std::vector<DcmItem*> getItems(DcmItem* item, const DcmTagKey& key);

/// Items of a sequence; throws (fail) if it is absent or empty.
std::vector<DcmItem*> requireItems(DcmItem* item, const DcmTagKey& key, const std::string& file,
                                   const std::string& where);

/// A readable name of a SOP class UID (the UID itself when unknown).
std::string sopClassName(const std::string& uid);

/// Loads `path` and checks it is a DICOM object of the expected modality.
Loaded load(const std::string& path, const std::string& modality, const char* sop_class_uid);

// ---- geometry ---------------------------------------------------------------------------------

/// Closest point of a polyline to p: arc length from the first point and the segment index.
struct Projection {
  double arc_m = 0.0;
  std::size_t segment = 0;
  double distance_m = std::numeric_limits<double>::infinity();
};

Projection projectOntoPolyline(const std::vector<Point3>& line, const Point3& p);

double polylineLength(const std::vector<Point3>& line);

/// Unit direction towards the first point of the polyline at the point closest to p, or zero
/// if the polyline has no extent.
Point3 tipDirection(const std::vector<Point3>& line, const Point3& p);

// ---- writing -----------------------------------------------------------------------------------

std::string newUid();

void put(DcmItem* item, const DcmTagKey& key, const std::string& value, const std::string& path);

void put(DcmItem* item, const DcmTagKey& key, double value, const std::string& path);

void putInt(DcmItem* item, const DcmTagKey& key, long value, const std::string& path);

DcmItem* appendItem(DcmItem* parent, const DcmTagKey& seq, const std::string& path);

/// Patient, General Study, series, Frame of Reference (if any), General Equipment and SOP Common
/// modules from the context; returns the SOP Instance UID written.
std::string putCommon(DcmDataset* ds, const char* sop_class, const std::string& modality,
                      const std::string& path, const DicomExportContext& ctx);

void save(DcmFileFormat& ff, const std::string& path);

}  // namespace needle_guidance::dose::dicom_io
