// Where the suite may write: report folders and journal files. Procedures run as
// root here, so a mistyped `report_dir` or `journal_file` must not clobber a system file or a
// user's file the suite did not make.
#pragma once

#include <string>
#include <vector>

namespace needle_guidance::report {

/// "" if `path` may be written, else why not: it lies in a system directory (/bin, /boot, /dev,
/// /etc, /lib*, /opt, /proc, /run, /sbin, /srv, /sys, /usr, /var except /var/tmp, or / itself).
/// The path is made absolute and normalised first ("/tmp/../etc/x" is /etc/x).
std::string systemLocation(const std::string& path);

/// The marker file a report folder made by the suite holds.
constexpr const char* kReportMarker = ".needle_guidance_report";

/// Makes `dir` ready for a report: creates it (and its parents) with the marker file. Throws
/// std::runtime_error naming `what` (e.g. the parameter) and the path when it is a system
/// location (unless `allow_system`), is a file, or is an existing folder that holds a file but
/// not the marker (one the suite did not create; empty subfolders, such as a journal folder
/// another node of the launch made first, are accepted). Nothing is created when it throws.
void prepareReportDir(const std::string& dir, const std::string& what, bool allow_system);

/// Checks a file the suite appends to: throws (naming `what` and the path) when it is in a system
/// location (unless `allow_system`), is a folder, or exists, is not empty and its first line is
/// none of `first_lines` (a file the suite did not write). A missing file is fine.
void checkAppendFile(const std::string& path, const std::vector<std::string>& first_lines,
                     const std::string& what, bool allow_system);

}  // namespace needle_guidance::report
