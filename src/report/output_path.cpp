#include "needle_guidance/report/output_path.h"

#include <filesystem>
#include <fstream>
#include <stdexcept>
#include <system_error>

namespace needle_guidance::report {
namespace fs = std::filesystem;

namespace {

fs::path normalised(const std::string& path) {
  std::error_code ec;
  fs::path p = fs::absolute(fs::path(path), ec);
  if (ec) {
    p = fs::path(path);
  }
  return p.lexically_normal();
}

bool under(const fs::path& p, const fs::path& dir) {
  auto d = dir.begin();
  for (auto it = p.begin(); d != dir.end(); ++it, ++d) {
    if (it == p.end() || *it != *d) {
      return false;
    }
  }
  return true;
}

// True when `p` holds no file at any depth: only (possibly nested) empty folders. A procedure's
// report folder can hold such a folder before the procedure starts, when a node launched with
// it (the afterloader's journal folder inside the report) creates its own folder first.
bool holdsNoFile(const fs::path& p) {
  std::error_code ec;
  for (fs::recursive_directory_iterator it(p, ec), end; !ec && it != end; it.increment(ec)) {
    if (!it->is_directory(ec)) {
      return false;
    }
  }
  return !ec;
}

}  // namespace

std::string systemLocation(const std::string& path) {
  const fs::path p = normalised(path);
  if (p == p.root_path()) {
    return "'" + p.string() + "' is the root directory";
  }
  if (under(p, "/var/tmp")) {
    return "";
  }
  for (const char* system : {"/bin", "/boot", "/dev", "/etc", "/lib", "/lib32", "/lib64", "/libx32",
                             "/opt", "/proc", "/run", "/sbin", "/srv", "/sys", "/usr", "/var"}) {
    if (under(p, system)) {
      return "'" + p.string() + "' is in the system directory " + system;
    }
  }
  return "";
}

void prepareReportDir(const std::string& dir, const std::string& what, bool allow_system) {
  if (dir.empty()) {
    throw std::runtime_error(what + ": no report folder given");
  }
  if (const std::string why = systemLocation(dir); !why.empty() && !allow_system) {
    throw std::runtime_error(what + ": refused: " + why +
                             " (allow_system_paths:=true to write there)");
  }
  const fs::path p = normalised(dir);
  std::error_code ec;
  if (fs::exists(p, ec)) {
    if (!fs::is_directory(p, ec)) {
      throw std::runtime_error(what + ": '" + p.string() + "' is a file, not a folder");
    }
    if (!holdsNoFile(p) && !fs::exists(p / kReportMarker, ec)) {
      throw std::runtime_error(what + ": refused: '" + p.string() +
                               "' is a non-empty folder the suite did not create (no " +
                               kReportMarker + "); give a new or empty folder");
    }
  }
  fs::create_directories(p, ec);
  if (ec) {
    throw std::runtime_error(what + ": cannot create '" + p.string() + "': " + ec.message());
  }
  std::ofstream marker(p / kReportMarker, std::ios::app);
  if (!marker) {
    throw std::runtime_error(what + ": cannot write in '" + p.string() + "'");
  }
}

void checkAppendFile(const std::string& path, const std::vector<std::string>& first_lines,
                     const std::string& what, bool allow_system) {
  if (const std::string why = systemLocation(path); !why.empty() && !allow_system) {
    throw std::runtime_error(what + ": refused: " + why +
                             " (allow_system_paths:=true to write there)");
  }
  const fs::path p = normalised(path);
  std::error_code ec;
  if (!fs::exists(p, ec)) {
    return;
  }
  if (fs::is_directory(p, ec)) {
    throw std::runtime_error(what + ": '" + p.string() + "' is a folder, not a file");
  }
  if (fs::file_size(p, ec) == 0) {
    return;
  }
  std::ifstream in(p);
  std::string first;
  std::getline(in, first);
  for (const std::string& ok : first_lines) {
    if (first == ok) {
      return;
    }
  }
  throw std::runtime_error(what + ": refused: '" + p.string() +
                           "' exists and is not a journal the suite wrote (its first line is '" +
                           first.substr(0, 60) + "')");
}

}  // namespace needle_guidance::report
