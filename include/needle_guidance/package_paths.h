// Where the package's files (config/, scripts/) are at run time: found through the package path,
// never a source path compiled in, so an installed package reads its installed files.
#pragma once

#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <stdexcept>
#include <string>
#include <system_error>

namespace needle_guidance {

namespace package_paths_detail {

/// True if `dir` holds this package's package.xml.
inline bool isPackageDir(const std::filesystem::path& dir) {
  std::ifstream in(dir / "package.xml");
  std::stringstream text;
  text << in.rdbuf();
  return in && text.str().find("<name>needle_guidance</name>") != std::string::npos;
}

}  // namespace package_paths_detail

/// The package's root at run time: the folder holding its package.xml and config/. Searched in
/// order: $NG_PACKAGE_DIR; every entry of $ROS_PACKAGE_PATH (the entry itself, as catkin's devel
/// space sets it, or ENTRY/needle_guidance, as an install space's share/ does); then relative to
/// the running executable, PREFIX/lib/needle_guidance/EXE -> PREFIX/share/needle_guidance.
/// Throws std::runtime_error saying what to source or set when none holds the package.
inline std::filesystem::path packageDir() {
  namespace fs = std::filesystem;
  using package_paths_detail::isPackageDir;
  if (const char* dir = std::getenv("NG_PACKAGE_DIR"); dir && *dir) {
    if (!isPackageDir(dir)) {
      throw std::runtime_error(std::string("NG_PACKAGE_DIR='") + dir +
                               "' holds no needle_guidance package.xml");
    }
    return dir;
  }
  if (const char* path = std::getenv("ROS_PACKAGE_PATH"); path && *path) {
    std::stringstream entries(path);
    std::string entry;
    while (std::getline(entries, entry, ':')) {
      if (!entry.empty() && isPackageDir(entry)) {
        return entry;
      }
      if (!entry.empty() && isPackageDir(fs::path(entry) / "needle_guidance")) {
        return fs::path(entry) / "needle_guidance";
      }
    }
  }
  std::error_code error;
  const fs::path exe = fs::read_symlink("/proc/self/exe", error);
  if (!error) {
    const fs::path share =
        exe.parent_path().parent_path().parent_path() / "share" / "needle_guidance";
    if (isPackageDir(share)) {
      return share;
    }
  }
  throw std::runtime_error(
      "needle_guidance: the package's files (config/) were not found: source the workspace's "
      "setup.bash (devel or install space), or set NG_PACKAGE_DIR to the package's folder");
}

/// The package's config/ folder (scenes, TG-43 source tables, DICOM case mapping, rviz).
inline std::filesystem::path configDir() {
  return packageDir() / "config";
}

}  // namespace needle_guidance
