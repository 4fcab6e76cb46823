// A plain case folder: any HDR case (synthetic or imported) as text files anyone can read.
//   case.yaml        name, source, air_kerma_strength_U, prescription_Gy
//   structures.csv   structure,role,contour,z_mm,x_mm,y_mm    (one row per contour vertex)
//   catheters.csv    catheter,point,x_mm,y_mm,z_mm             (first point = distal tip)
//   dwells.csv       catheter,index,x_mm,y_mm,z_mm,axis_x,axis_y,axis_z,time_s
//   points.csv       structure,kind,x_mm,y_mm,z_mm             (kind: surface | volume)
//   criteria.csv     structure,kind,min_Gy,max_Gy,weight_under,weight_over
#pragma once

#include <string>

#include "needle_guidance/dose/hdr_case.h"

namespace needle_guidance::dose {

/// Writes the case into `dir` (created if missing). Throws std::runtime_error if a file cannot be
/// written.
void writeCaseFolder(const HdrCase& c, const std::string& dir);

/// Reads a case folder. Throws std::invalid_argument naming the file, line and reason for a
/// malformed or inconsistent file (unknown structure or catheter, bad number, missing column).
HdrCase readCaseFolder(const std::string& dir);

}  // namespace needle_guidance::dose
