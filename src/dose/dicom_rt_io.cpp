// DICOM-RT element reading, loading, geometry and writing (dicom_rt_io.h).
#include "dicom_rt_io.h"

namespace needle_guidance::dose::dicom_io {

[[noreturn]] void fail(const std::string& file, const std::string& where,
                       const std::string& reason) {
  std::string msg = "DICOM-RT: " + file + ": ";
  if (!where.empty()) {
    msg += where + ": ";
  }
  throw std::invalid_argument(msg + reason);
}

std::string tagName(const DcmTagKey& key) {
  DcmTag tag(key);
  return std::string(tag.getTagName()) + " " + key.toString().c_str();
}

std::string join(const std::string& a, const std::string& b) {
  if (a.empty()) {
    return b;
  }
  return a + " > " + b;
}

std::string itemContext(const std::string& parent, const DcmTagKey& seq, unsigned long index) {
  return join(parent, std::string(DcmTag(seq).getTagName()) + "[" + std::to_string(index) + "]");
}

std::string lower(std::string s) {
  std::transform(s.begin(), s.end(), s.begin(),
                 [](unsigned char ch) { return static_cast<char>(std::tolower(ch)); });
  return s;
}

std::string trim(const std::string& s) {
  const auto b = s.find_first_not_of(" \t\r\n");
  if (b == std::string::npos) {
    return {};
  }
  const auto e = s.find_last_not_of(" \t\r\n");
  return s.substr(b, e - b + 1);
}

std::string formatNumber(double v) {
  // DS values may hold at most 16 characters: 10 significant digits always fit.
  char buf[32];
  std::snprintf(buf, sizeof(buf), "%.10g", v == 0.0 ? 0.0 : v);
  return buf;
}

std::string formatNumbers(const std::vector<double>& values) {
  std::string s;
  for (std::size_t i = 0; i < values.size(); ++i) {
    if (i > 0) {
      s += '\\';
    }
    s += formatNumber(values[i]);
  }
  return s;
}

DcmElement* findElement(DcmItem* item, const DcmTagKey& key) {
  DcmElement* e = nullptr;
  if (item->findAndGetElement(key, e).bad() || e == nullptr) {
    return nullptr;
  }
  return e;
}

double elementNumber(DcmElement* e, unsigned long pos, const std::string& file,
                     const std::string& where) {
  double v = 0.0;
  bool ok = false;
  switch (e->ident()) {
    case EVR_FL: {
      Float32 f = 0;
      ok = e->getFloat32(f, pos).good();
      v = f;
      break;
    }
    case EVR_FD: {
      Float64 f = 0;
      ok = e->getFloat64(f, pos).good();
      v = f;
      break;
    }
    case EVR_US: {
      Uint16 u = 0;
      ok = e->getUint16(u, pos).good();
      v = u;
      break;
    }
    case EVR_UL: {
      Uint32 u = 0;
      ok = e->getUint32(u, pos).good();
      v = u;
      break;
    }
    case EVR_SS: {
      Sint16 s = 0;
      ok = e->getSint16(s, pos).good();
      v = s;
      break;
    }
    case EVR_SL: {
      Sint32 s = 0;
      ok = e->getSint32(s, pos).good();
      v = s;
      break;
    }
    default: {  // DS, IS and anything stored as text
      OFString text;
      if (e->getOFString(text, pos, OFTrue).good()) {
        const std::string t = trim(text.c_str());
        char* end = nullptr;
        v = std::strtod(t.c_str(), &end);
        ok = !t.empty() && end != nullptr && *end == '\0';
      }
      break;
    }
  }
  if (!ok || !std::isfinite(v)) {
    fail(file, where,
         tagName(e->getTag()) + " value " + std::to_string(pos + 1) + " is not a finite number");
  }
  return v;
}

std::vector<double> getNumbers(DcmItem* item, const DcmTagKey& key, const std::string& file,
                               const std::string& where) {
  std::vector<double> values;
  DcmElement* e = findElement(item, key);
  if (e == nullptr || e->getLength() == 0) {
    return values;
  }
  const unsigned long vm = e->getVM();
  values.reserve(vm);
  for (unsigned long pos = 0; pos < vm; ++pos) {
    values.push_back(elementNumber(e, pos, file, where));
  }
  return values;
}

std::optional<double> getNumber(DcmItem* item, const DcmTagKey& key, const std::string& file,
                                const std::string& where) {
  DcmElement* e = findElement(item, key);
  if (e == nullptr || e->getLength() == 0) {
    return std::nullopt;
  }
  return elementNumber(e, 0, file, where);
}

double requireNumber(DcmItem* item, const DcmTagKey& key, const std::string& file,
                     const std::string& where) {
  const std::optional<double> v = getNumber(item, key, file, where);
  if (!v) {
    fail(file, where, tagName(key) + " is missing or empty");
  }
  return *v;
}

std::vector<double> requireNumbers(DcmItem* item, const DcmTagKey& key, std::size_t count,
                                   const std::string& file, const std::string& where) {
  std::vector<double> v = getNumbers(item, key, file, where);
  if (v.empty()) {
    fail(file, where, tagName(key) + " is missing or empty");
  }
  if (count > 0 && v.size() != count) {
    fail(file, where,
         tagName(key) + " has " + std::to_string(v.size()) + " values, expected " +
             std::to_string(count));
  }
  return v;
}

int requireInt(DcmItem* item, const DcmTagKey& key, const std::string& file,
               const std::string& where) {
  const double v = requireNumber(item, key, file, where);
  if (v != std::floor(v) || std::abs(v) > 2e9) {
    fail(file, where, tagName(key) + " = " + formatNumber(v) + " is not an integer");
  }
  return static_cast<int>(v);
}

std::optional<int> getInt(DcmItem* item, const DcmTagKey& key, const std::string& file,
                          const std::string& where) {
  if (!getNumber(item, key, file, where)) {
    return std::nullopt;
  }
  return requireInt(item, key, file, where);
}

std::string getString(DcmItem* item, const DcmTagKey& key) {
  OFString value;
  if (item->findAndGetOFStringArray(key, value).bad()) {
    return {};
  }
  return trim(value.c_str());
}

std::vector<DcmItem*> getItems(DcmItem* item, const DcmTagKey& key) {
  std::vector<DcmItem*> items;
  DcmSequenceOfItems* seq = nullptr;
  if (item->findAndGetSequence(key, seq).bad() || seq == nullptr) {
    return items;
  }
  for (unsigned long i = 0; i < seq->card(); ++i) {
    items.push_back(seq->getItem(i));
  }
  return items;
}

std::vector<DcmItem*> requireItems(DcmItem* item, const DcmTagKey& key, const std::string& file,
                                   const std::string& where) {
  std::vector<DcmItem*> items = getItems(item, key);
  if (items.empty()) {
    fail(file, where, tagName(key) + " is missing or has no items");
  }
  return items;
}

std::string sopClassName(const std::string& uid) {
  const char* name = dcmFindNameOfUID(uid.c_str());
  return name != nullptr ? name : uid;
}

Loaded load(const std::string& path, const std::string& modality, const char* sop_class_uid) {
  std::error_code ec;
  if (!std::filesystem::is_regular_file(path, ec)) {
    fail(path, "", "no such file (expected a " + modality + " object)");
  }
  Loaded l;
  l.path = path;
  l.file = std::make_unique<DcmFileFormat>();
  const OFCondition status = l.file->loadFile(path.c_str());
  if (status.bad()) {
    fail(path, "", std::string("not a readable DICOM file (") + status.text() + ")");
  }
  l.data = l.file->getDataset();
  const std::string sop = getString(l.data, DCM_SOPClassUID);
  const std::string found_modality = getString(l.data, DCM_Modality);
  if (sop.empty() && found_modality.empty()) {
    fail(path, "",
         "not a DICOM object: no " + tagName(DCM_SOPClassUID) + " and no " + tagName(DCM_Modality) +
             " (expected " + modality + ")");
  }
  if (!sop.empty() && sop != sop_class_uid) {
    fail(path, "",
         tagName(DCM_SOPClassUID) + " is " + sopClassName(sop) + ", expected " +
             sopClassName(sop_class_uid) + " (" + modality + ")");
  }
  if (!found_modality.empty() && found_modality != modality) {
    fail(path, "", tagName(DCM_Modality) + " is " + found_modality + ", expected " + modality);
  }
  return l;
}

Projection projectOntoPolyline(const std::vector<Point3>& line, const Point3& p) {
  Projection best;
  if (line.size() < 2) {
    if (!line.empty()) {
      best.distance_m = (p - line.front()).norm();
    }
    return best;
  }
  double arc = 0.0;
  for (std::size_t s = 0; s + 1 < line.size(); ++s) {
    const Point3& a = line[s];
    const Point3 ab = line[s + 1] - a;
    const double len2 = ab.squaredNorm();
    const double t = len2 > 0.0 ? std::clamp((p - a).dot(ab) / len2, 0.0, 1.0) : 0.0;
    const double d = (a + t * ab - p).norm();
    if (d < best.distance_m) {
      best.distance_m = d;
      best.arc_m = arc + t * std::sqrt(len2);
      best.segment = s;
    }
    arc += std::sqrt(len2);
  }
  return best;
}

double polylineLength(const std::vector<Point3>& line) {
  double len = 0.0;
  for (std::size_t s = 0; s + 1 < line.size(); ++s) {
    len += (line[s + 1] - line[s]).norm();
  }
  return len;
}

Point3 tipDirection(const std::vector<Point3>& line, const Point3& p) {
  if (line.size() < 2) {
    return Point3::Zero();
  }
  const Projection proj = projectOntoPolyline(line, p);
  // Skip zero-length segments towards the tip end.
  for (std::size_t s = proj.segment + 1; s-- > 0;) {
    const Point3 d = line[s] - line[s + 1];
    if (d.norm() > 1e-12) {
      return d.normalized();
    }
  }
  for (std::size_t s = proj.segment + 1; s + 1 < line.size(); ++s) {
    const Point3 d = line[s] - line[s + 1];
    if (d.norm() > 1e-12) {
      return d.normalized();
    }
  }
  return Point3::Zero();
}

std::string newUid() {
  char uid[100];
  dcmGenerateUniqueIdentifier(uid, SITE_INSTANCE_UID_ROOT);
  return uid;
}

void put(DcmItem* item, const DcmTagKey& key, const std::string& value, const std::string& path) {
  const OFCondition st = item->putAndInsertString(DcmTag(key), value.c_str());
  if (st.bad()) {
    throw std::runtime_error("DICOM-RT: " + path + ": cannot set " + tagName(key) + ": " +
                             st.text());
  }
}

void put(DcmItem* item, const DcmTagKey& key, double value, const std::string& path) {
  put(item, key, formatNumber(value), path);
}

void putInt(DcmItem* item, const DcmTagKey& key, long value, const std::string& path) {
  put(item, key, std::to_string(value), path);
}

DcmItem* appendItem(DcmItem* parent, const DcmTagKey& seq, const std::string& path) {
  DcmItem* item = nullptr;
  const OFCondition st = parent->findOrCreateSequenceItem(DcmTag(seq), item, -2);
  if (st.bad() || item == nullptr) {
    throw std::runtime_error("DICOM-RT: " + path + ": cannot append to " + tagName(seq) + ": " +
                             st.text());
  }
  return item;
}

std::string putCommon(DcmDataset* ds, const char* sop_class, const std::string& modality,
                      const std::string& path, const DicomExportContext& ctx) {
  const std::string instance = ctx.sop_instance_uid.empty() ? newUid() : ctx.sop_instance_uid;
  put(ds, DCM_SpecificCharacterSet, "ISO_IR 100", path);
  put(ds, DCM_SOPClassUID, sop_class, path);
  put(ds, DCM_SOPInstanceUID, instance, path);
  put(ds, DCM_Modality, modality, path);
  put(ds, DCM_StudyInstanceUID, ctx.study_uid.empty() ? newUid() : ctx.study_uid, path);
  put(ds, DCM_SeriesInstanceUID, newUid(), path);
  putInt(ds, DCM_SeriesNumber, ctx.series_number, path);
  put(ds, DCM_StudyID, ctx.study_id, path);
  put(ds, DCM_StudyDate, ctx.study_date, path);
  put(ds, DCM_StudyTime, ctx.study_time, path);
  put(ds, DCM_ReferringPhysicianName, "", path);
  put(ds, DCM_AccessionNumber, "", path);
  put(ds, DCM_PatientName, ctx.patient_name, path);
  put(ds, DCM_PatientID, ctx.patient_id, path);
  put(ds, DCM_PatientBirthDate, ctx.patient_birth_date, path);
  put(ds, DCM_PatientSex, ctx.patient_sex, path);
  put(ds, DCM_Manufacturer, "needle_guidance", path);
  put(ds, DCM_OperatorsName, "", path);
  put(ds, DCM_InstanceCreationDate, ctx.study_date, path);
  put(ds, DCM_InstanceCreationTime, ctx.study_time, path);
  return instance;
}

void save(DcmFileFormat& ff, const std::string& path) {
  const OFCondition st = ff.saveFile(path.c_str(), EXS_LittleEndianExplicit);
  if (st.bad()) {
    throw std::runtime_error("DICOM-RT: " + path + ": cannot write: " + st.text());
  }
}

}  // namespace needle_guidance::dose::dicom_io
