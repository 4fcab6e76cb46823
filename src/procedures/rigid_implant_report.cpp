// The rigid seed-implant report: CSV, JSON, markdown and a PNG of the seed error per target, so a
// plain roslaunch writes the whole report (no plotting script needed afterwards).
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <cmath>
#include <sstream>
#include <stdexcept>

#include "needle_guidance/procedures/rigid_implant.h"
#include "needle_guidance/report/table.h"

namespace needle_guidance::procedures {
namespace {

report::Cell cell(double value) {
  return std::isfinite(value) ? report::Cell(value) : report::Cell(std::string());
}

report::Table movesTable(const RigidImplantReport& rep) {
  report::Table moves({"target",
                       "target_x_mm",
                       "target_y_mm",
                       "release_x_mm",
                       "release_y_mm",
                       "depth_reached_mm",
                       "depth_error_mm",
                       "tip_error_mm",
                       "insert_s",
                       "insert_velocity_mm_s",
                       "velocity_error_pct",
                       "retract_s",
                       "seed_x_mm",
                       "seed_y_mm",
                       "seed_error_mm",
                       "predicted_error_mm",
                       "unplanned_predicted_mm",
                       "plan_s",
                       "status",
                       "outcome",
                       "verified_error_mm",
                       "reason",
                       "target_z_mm",
                       "release_z_mm",
                       "seed_z_mm"},
                      6);
  const double v = rep.settings.insertion_velocity_m_s;
  for (const TargetRecord& r : rep.records) {
    const bool in = r.inserted();  // a target never inserted has no move figures
    const double none = NAN;
    moves.addRow({r.name,
                  1e3 * r.target.x(),
                  1e3 * r.target.y(),
                  1e3 * r.aim.x(),
                  1e3 * r.aim.y(),
                  cell(in ? 1e3 * r.insert.reached_m : none),
                  cell(in ? 1e3 * std::abs(r.insert.reached_m - r.aim.x()) : none),
                  cell(in ? 1e3 * r.tip_error_m : none),
                  cell(in ? r.insert.duration_s : none),
                  cell(in ? 1e3 * r.insert.mean_velocity_m_s : none),
                  cell(in ? 100.0 * std::abs(r.insert.mean_velocity_m_s - v) / v : none),
                  cell(in ? r.retract.duration_s : none),
                  cell(1e3 * r.seed.x()),
                  cell(1e3 * r.seed.y()),
                  cell(1e3 * r.seedError_m()),
                  cell(1e3 * r.plan.predicted_error_m),
                  cell(1e3 * r.plan.unplanned_error_m),
                  cell(r.plan.plan_s),
                  r.status,
                  std::string(toString(r.outcome)),
                  cell(1e3 * r.plan.verified_error_m),
                  r.reason,
                  1e3 * r.target.z(),
                  1e3 * r.aim.z(),
                  cell(1e3 * r.seed.z())});
  }
  return moves;
}

/// Bars of the seed error per target (log scale, 1 um to 10 mm) against the tolerance; green
/// placed, red missed, grey refused / error (no bar).
void writePlot(const RigidImplantReport& rep, const std::string& path) {
  const int n = std::max<int>(1, static_cast<int>(rep.records.size()));
  const int left = 70, right = 20, top = 40, bottom = 110, bar = 36;
  const int width = left + right + n * bar, height = 420;
  cv::Mat img(height, std::max(width, 600), CV_8UC3, cv::Scalar(255, 255, 255));
  const double lo = -3.0, hi = 1.0;  // log10 mm
  auto yOf = [&](double mm) {
    const double l = std::clamp(std::log10(std::max(mm, 1e-3)), lo, hi);
    return top + static_cast<int>((hi - l) / (hi - lo) * (height - top - bottom));
  };
  const cv::Scalar black(0, 0, 0), grey(150, 150, 150);
  for (int d = -3; d <= 1; ++d) {
    const int y = yOf(std::pow(10.0, d));
    cv::line(img, {left, y}, {img.cols - right, y}, cv::Scalar(225, 225, 225));
    std::ostringstream label;
    label << std::pow(10.0, d);
    cv::putText(img, label.str(), {5, y + 4}, cv::FONT_HERSHEY_SIMPLEX, 0.4, black);
  }
  const int y_tol = yOf(1e3 * rep.settings.placement_tolerance_m);
  cv::line(img, {left, y_tol}, {img.cols - right, y_tol}, cv::Scalar(255, 0, 0), 2);
  for (std::size_t i = 0; i < rep.records.size(); ++i) {
    const TargetRecord& r = rep.records[i];
    const int x0 = left + static_cast<int>(i) * bar + 6;
    const double e = 1e3 * r.seedError_m();
    const cv::Scalar colour = r.outcome == TargetOutcome::kPlaced   ? cv::Scalar(60, 170, 60)
                              : r.outcome == TargetOutcome::kMissed ? cv::Scalar(40, 40, 220)
                                                                    : grey;
    if (std::isfinite(e)) {
      cv::rectangle(img, {x0, yOf(e)}, {x0 + bar - 12, yOf(1e-3)}, colour, cv::FILLED);
    } else {
      cv::putText(img, toString(r.outcome), {x0, yOf(1e-3) - 4}, cv::FONT_HERSHEY_SIMPLEX, 0.3,
                  grey);
    }
    cv::Mat text(14, 100, CV_8UC3, cv::Scalar(255, 255, 255));
    cv::putText(text, r.name.substr(0, 16), {0, 11}, cv::FONT_HERSHEY_SIMPLEX, 0.35, black);
    cv::rotate(text, text, cv::ROTATE_90_COUNTERCLOCKWISE);
    text.copyTo(img(cv::Rect(x0 + 6, height - bottom + 6, text.cols, text.rows)));
  }
  std::ostringstream title;
  title << "Seed error per target [mm, log] - scene " << rep.scene << ": "
        << rep.count(TargetOutcome::kPlaced) << " placed, " << rep.count(TargetOutcome::kMissed)
        << " missed (blue: tolerance)";
  cv::putText(img, title.str(), {5, 20}, cv::FONT_HERSHEY_SIMPLEX, 0.4, black);
  if (!cv::imwrite(path, img)) {
    throw std::runtime_error("RigidImplantReport: cannot write " + path);
  }
}

}  // namespace

int RigidImplantReport::count(TargetOutcome outcome) const {
  return static_cast<int>(std::count_if(
      records.begin(), records.end(), [&](const TargetRecord& r) { return r.outcome == outcome; }));
}

bool RigidImplantReport::success() const {
  if (fault || static_cast<int>(records.size()) != targets_in_scene) {
    return false;
  }
  return std::all_of(records.begin(), records.end(), [&](const TargetRecord& r) {
    return planned ? r.outcome == TargetOutcome::kPlaced ||
                         (r.outcome == TargetOutcome::kRefused && r.plan.unreachable)
                   : r.status == "ok";
  });
}

int RigidImplantReport::unreachableCount() const {
  return static_cast<int>(std::count_if(records.begin(), records.end(), [](const TargetRecord& r) {
    return r.outcome == TargetOutcome::kRefused && r.plan.unreachable;
  }));
}

std::string RigidImplantReport::summaryJson() const {
  double max_seed = 0.0, sum_seed = 0.0, max_depth = 0.0, max_tip = 0.0, max_velocity = 0.0,
         sum_plan = 0.0;
  int seeds = 0, plans = 0;
  for (const TargetRecord& r : records) {
    if (std::isfinite(r.seedError_m())) {
      max_seed = std::max(max_seed, 1e3 * r.seedError_m());
      sum_seed += 1e3 * r.seedError_m();
      ++seeds;
    }
    if (std::isfinite(r.plan.plan_s)) {
      sum_plan += r.plan.plan_s;
      ++plans;
    }
    if (r.inserted()) {
      max_depth = std::max(max_depth, 1e3 * std::abs(r.insert.reached_m - r.aim.x()));
      max_tip = std::isfinite(r.tip_error_m) ? std::max(max_tip, 1e3 * r.tip_error_m) : max_tip;
      max_velocity =
          std::max(max_velocity,
                   100.0 * std::abs(r.insert.mean_velocity_m_s - settings.insertion_velocity_m_s) /
                       settings.insertion_velocity_m_s);
    }
  }
  using report::jsonNumber;
  std::ostringstream json;
  json << "{\n  \"procedure\": \""
       << (planned       ? "rigid_seed_implant"
           : with_tissue ? "unplanned_seed_implant"
                         : "robot_insertion")
       << "\",\n  \"scene\": \"" << scene
       << "\",\n  \"success\": " << (success() ? "true" : "false")
       << ",\n  \"targets\": " << targets_in_scene << ",\n  \"targets_tried\": " << records.size()
       << ",\n  \"placed\": " << count(TargetOutcome::kPlaced)
       << ",\n  \"missed\": " << count(TargetOutcome::kMissed)
       << ",\n  \"refused\": " << count(TargetOutcome::kRefused)
       << ",\n  \"refused_unreachable\": " << unreachableCount()
       << ",\n  \"lateral_stage\": " << (settings.lateral_stage ? "true" : "false")
       << ",\n  \"error\": " << count(TargetOutcome::kError)
       << ",\n  \"placement_tolerance_mm\": " << jsonNumber(1e3 * settings.placement_tolerance_m)
       << ",\n  \"success_means\": \""
       << (planned ? "every target placed (seed within the placement tolerance) or refused as "
                     "unreachable for a physical reason"
                   : "every move succeeded")
       << "\",\n  \"max_depth_error_mm\": " << jsonNumber(max_depth, 9)
       << ",\n  \"max_tip_error_mm\": " << jsonNumber(max_tip, 9)
       << ",\n  \"max_velocity_error_pct\": " << jsonNumber(max_velocity);
  if (with_tissue) {
    json << ",\n  \"seeds\": " << seeds << ",\n  \"max_seed_error_mm\": " << jsonNumber(max_seed, 9)
         << ",\n  \"mean_seed_error_mm\": " << jsonNumber(seeds ? sum_seed / seeds : NAN, 9);
  }
  if (planned) {
    json << ",\n  \"planning_s_mean\": " << jsonNumber(plans ? sum_plan / plans : NAN);
  }
  if (fault) {  // the same top-level keys as every procedure's report (dead_node, cause)
    json << ",\n  \"dead_node\": \"" << fault->node << "\",\n  \"cause\": \"node " << fault->node
         << " " << fault->reason << " at " << jsonNumber(fault->at_s) << " s; robot: " << safe_stop
         << "\",\n  \"detected_unix_s\": " << report::jsonNumber(fault->detected_unix_s, 15);
  }
  json << ",\n  \"fault\": ";
  if (fault) {
    json << "{\"node\": \"" << fault->node << "\", \"at_s\": " << jsonNumber(fault->at_s)
         << ", \"reason\": \"" << fault->reason << "\", \"safe_stop\": \"" << safe_stop << "\"}";
  } else {
    json << "null";
  }
  json << ",\n  \"wall_time_s\": " << jsonNumber(wall_time_s) << "\n}\n";
  return json.str();
}

std::string RigidImplantReport::summaryMarkdown() const {
  std::ostringstream md;
  md << "# "
     << (planned       ? "Rigid seed implant with offset planning (ch. 4)"
         : with_tissue ? "Seed implant without deformation compensation"
                       : "Robot insertion")
     << " — scene `" << scene << "`\n\n"
     << "Each target: move to its height" << (settings.lateral_stage ? " and lateral position" : "")
     << ", insert to its depth at " << 1e3 * settings.insertion_velocity_m_s << " mm/s"
     << (with_tissue ? ", implant a seed" : "") << ", retract to " << 1e3 * settings.retract_depth_m
     << " mm. Seed error is where the seed rests in the FEM tissue once the needle is out, "
        "against its target. Outcomes: placed (within "
     << 1e3 * settings.placement_tolerance_m
     << " mm), missed, refused (the planner's reason), error (a move, the implant or a node "
        "failed).\n\n"
     << movesTable(*this).toMarkdown() << "\nTargets tried: " << records.size() << " of "
     << targets_in_scene << ": " << count(TargetOutcome::kPlaced) << " placed, "
     << count(TargetOutcome::kMissed) << " missed, " << count(TargetOutcome::kRefused)
     << " refused, " << count(TargetOutcome::kError) << " error.\n";
  if (fault) {
    md << "\n**Stopped by a fault:** node `" << fault->node << "` " << fault->reason << " at "
       << fault->at_s << " s; robot: " << safe_stop << ".\n";
  }
  md << "\nResult: "
     << (success() ? (planned ? "every seed placed" : "all moves succeeded") : "FAILED")
     << ", wall time " << wall_time_s << " s.\n\n![seed error per target](seed_errors.png)\n";
  return md.str();
}

std::string RigidImplantReport::text() const {
  return movesTable(*this).toText();
}

void RigidImplantReport::write(const std::string& dir) const {
  // summary.json last: it is the file a reader waits for, so the rest is there when it appears.
  movesTable(*this).writeCsv(dir + "/moves.csv");
  report::writeTextFile(dir + "/summary.md", summaryMarkdown());
  writePlot(*this, dir + "/seed_errors.png");
  report::writeTextFile(dir + "/summary.json", summaryJson());
}

}  // namespace needle_guidance::procedures
