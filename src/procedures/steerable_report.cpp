// The steerable-needle report: CSVs, JSON, markdown and the two figures (paths, figure 5.8; P_s
// map with its colour key, figure 5.7), so a plain roslaunch writes the whole report.
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <cmath>
#include <sstream>

#include "needle_guidance/math.h"
#include "needle_guidance/procedures/steerable_trials.h"
#include "needle_guidance/report/plot.h"
#include "needle_guidance/report/statistics.h"
#include "needle_guidance/report/table.h"
#include "needle_guidance/steering/start_verification.h"

namespace needle_guidance::procedures {
namespace {

constexpr double kMm = 1e3;
constexpr double kDeg = 180.0 / kPi;
constexpr std::size_t kMaxPlottedPaths = 6;

double maximum(const std::vector<double>& v) {
  return v.empty() ? 0.0 : *std::max_element(v.begin(), v.end());
}

/// Tip and heading errors at the answered decisions [mm], [deg].
void decisionErrors(const SteerableReport& rep, std::vector<double>& tip_mm,
                    std::vector<double>& heading_deg) {
  for (const auto& r : rep.records) {
    for (const auto& d : r.decisions) {
      if (d.answered) {
        tip_mm.push_back(d.tipError_m() * kMm);
        heading_deg.push_back(d.headingError_rad() * kDeg);
      }
    }
  }
}

/// The samples plotted for a trial: from entry on (the retracted ones before are left out).
std::vector<const SteerableTip*> pathSamples(const SteerableTrialRecord& r) {
  std::vector<const SteerableTip*> out;
  for (std::size_t k = 0; k < r.samples.size(); ++k) {
    if (r.samples[k].inserted_length_m > 0.0 || k + 1 == r.samples.size()) {
      out.push_back(&r.samples[k]);
    }
  }
  return out;
}

void writeTables(const SteerableReport& rep, const std::string& dir) {
  report::Table trials({"trial", "outcome", "steps", "flips", "seconds", "message"}, 6);
  report::Table paths({"trial", "sample", "x_mm", "y_mm", "theta_deg", "bevel"}, 6);
  report::Table decisions(
      {"trial", "step", "x_mm", "y_mm", "theta_deg", "bevel", "control", "predicted_ps", "source",
       "confident", "tip_error_mm", "heading_error_deg"},
      6);
  for (std::size_t i = 0; i < rep.records.size(); ++i) {
    const SteerableTrialRecord& r = rep.records[i];
    const double trial = double(i + 1);
    trials.addRow({trial, std::string(toString(r.outcome)), double(r.steps), double(r.flips),
                   r.seconds, r.message});
    for (std::size_t k = 0; k < r.samples.size(); ++k) {
      const SteerableTip& s = r.samples[k];
      if (s.inserted_length_m <= 0.0 && k + 1 < r.samples.size()) {
        continue;  // before entry (retracted or at the guide)
      }
      paths.addRow({trial, double(k), s.pose.p_SceneTip.x() * kMm, s.pose.p_SceneTip.y() * kMm,
                    s.pose.theta_rad * kDeg, steering::toString(s.pose.bevel)});
    }
    for (std::size_t k = 0; k < r.decisions.size(); ++k) {
      const SteerableDecision& d = r.decisions[k];
      const steering::TipPose& p = d.truth.pose;
      decisions.addRow({trial, double(k), p.p_SceneTip.x() * kMm, p.p_SceneTip.y() * kMm,
                        p.theta_rad * kDeg, steering::toString(p.bevel),
                        d.answered ? steering::toString(d.answer.control) : std::string("end"),
                        d.answer.probability_of_success, d.answer.source,
                        std::string(d.answer.confident ? "1" : "0"), d.tipError_m() * kMm,
                        d.headingError_rad() * kDeg});
    }
  }
  report::Table ps_map({"bevel", "y_mm", "theta_deg", "ps"}, 6);
  for (const auto& c : rep.ps_map) {
    ps_map.addRow({steering::toString(c.pose.bevel), c.pose.p_SceneTip.y() * kMm,
                   c.pose.theta_rad * kDeg, double(c.probability_of_success)});
  }
  report::Table outlines({"structure", "contour", "x_mm", "y_mm"}, 6);
  const steering::ContinuousWorkspace world(rep.problem);
  for (std::size_t o = 0; o < rep.problem.obstacles.size(); ++o) {
    const auto& obstacle = rep.problem.obstacles[o];
    for (const auto& v : obstacle.polygon.vertices()) {
      outlines.addRow({std::string("obstacle"), obstacle.name, v.x() * kMm, v.y() * kMm});
    }
    for (const auto& v : world.expandedObstacles()[o].vertices()) {
      outlines.addRow(
          {std::string("clearance"), obstacle.name + "_expanded", v.x() * kMm, v.y() * kMm});
    }
  }
  trials.writeCsv(dir + "/trials.csv");
  paths.writeCsv(dir + "/paths.csv");
  decisions.writeCsv(dir + "/decisions.csv");
  ps_map.writeCsv(dir + "/ps_map.csv");
  outlines.writeCsv(dir + "/obstacles.csv");
}

void addClosed(report::LinePlot& plot, const std::string& name,
               const std::vector<geometry::Point2>& vertices, const cv::Scalar& bgr,
               int thickness) {
  std::vector<double> x, y;
  for (const auto& v : vertices) {
    x.push_back(v.x() * kMm);
    y.push_back(v.y() * kMm);
  }
  if (!vertices.empty()) {
    x.push_back(x.front());
    y.push_back(y.front());
  }
  plot.addLine(name, x, y, bgr, thickness);
}

/// Figure 5.8: the workspace, obstacles with their clearance, the target, and up to six trials'
/// paths with their decisions (small dots insert, large dots flip). Equal axes.
void writePathsPlot(const SteerableReport& rep, const std::string& path) {
  const steering::SteeringProblem& p = rep.problem;
  report::LinePlot plot("Closed-loop trials (figure 5.8): small dots insert, large dots flip",
                        "x [mm]", "y [mm]");
  const steering::ContinuousWorkspace world(p);
  for (std::size_t o = 0; o < p.obstacles.size(); ++o) {
    addClosed(plot, o == 0 ? "obstacle" : "", p.obstacles[o].polygon.vertices(),
              cv::Scalar(60, 60, 60), 2);
    addClosed(plot, o == 0 ? "clearance" : "", world.expandedObstacles()[o].vertices(),
              cv::Scalar(170, 170, 170), 1);
  }
  std::vector<geometry::Point2> circle;
  for (int k = 0; k < 72; ++k) {
    circle.push_back(p.target.position +
                     p.target.radius_m *
                         geometry::Point2(std::cos(k * kPi / 36.0), std::sin(k * kPi / 36.0)));
  }
  addClosed(plot, "target", circle, cv::Scalar(40, 160, 40), 2);
  for (std::size_t i = 0; i < std::min(rep.records.size(), kMaxPlottedPaths); ++i) {
    const SteerableTrialRecord& r = rep.records[i];
    const cv::Scalar colour = report::seriesColour(i);
    std::vector<double> x, y, ix, iy, fx, fy;
    for (const SteerableTip* s : pathSamples(r)) {
      x.push_back(s->pose.p_SceneTip.x() * kMm);
      y.push_back(s->pose.p_SceneTip.y() * kMm);
    }
    for (const auto& d : r.decisions) {
      const bool flip = d.answered && d.answer.control == steering::Control::kFlip;
      (flip ? fx : ix).push_back(d.truth.pose.p_SceneTip.x() * kMm);
      (flip ? fy : iy).push_back(d.truth.pose.p_SceneTip.y() * kMm);
    }
    plot.addLine("trial " + std::to_string(i + 1) + " " + toString(r.outcome), x, y, colour, 2);
    plot.addPoints("", ix, iy, colour, 2);
    plot.addPoints("", fx, fy, colour, 5);
  }
  const double w_mm = (p.workspace_max.x() - p.workspace_min.x()) * kMm;
  const double h_mm = (p.workspace_max.y() - p.workspace_min.y()) * kMm;
  plot.setXRange(p.workspace_min.x() * kMm, p.workspace_max.x() * kMm);
  plot.setYRange(p.workspace_min.y() * kMm, p.workspace_max.y() * kMm);
  constexpr int kWidth = 900, kAxesMarginX = 90, kAxesMarginY = 105;  // LinePlot's margins
  const int height =
      kAxesMarginY +
      static_cast<int>(std::lround((kWidth - kAxesMarginX) * h_mm / std::max(w_mm, 1e-9)));
  plot.save(path, kWidth, std::clamp(height, 300, 1400));
}

/// The grid step of a set of grid values: the median gap between distinct sorted values (robust
/// to rounding), or `fallback` with fewer than two.
double gridStep(const std::vector<double>& v, double fallback) {
  std::vector<double> sorted(v);
  std::sort(sorted.begin(), sorted.end());
  std::vector<double> gaps;
  for (std::size_t k = 1; k < sorted.size(); ++k) {
    if (sorted[k] - sorted[k - 1] > 1e-9) {
      gaps.push_back(sorted[k] - sorted[k - 1]);
    }
  }
  return gaps.empty() ? fallback : report::median(gaps);
}

/// Figure 5.7: P_s of the start states on the entry line for the start's bevel, with a colour
/// key and the chosen start marked.
void writePsMap(const SteerableReport& rep, const std::string& path) {
  std::vector<double> theta, y, ps;
  for (const auto& c : rep.ps_map) {
    if (c.pose.bevel == rep.start.pose.bevel) {
      theta.push_back(c.pose.theta_rad * kDeg);
      y.push_back(c.pose.p_SceneTip.y() * kMm);
      ps.push_back(c.probability_of_success);
    }
  }
  const std::string bevel = steering::toString(rep.start.pose.bevel);
  report::LinePlot plot("P_s of start states on the entry line (figure 5.7), bevel " + bevel,
                        "entry angle theta [deg]", "entry height y [mm]");
  if (!ps.empty()) {
    const double dt = gridStep(theta, 1.0), dy = gridStep(y, 1.0);
    plot.addCells(theta, y, ps, dt, dy, cv::COLORMAP_VIRIDIS, 0.0, 1.0);
    plot.setXRange(*std::min_element(theta.begin(), theta.end()) - 0.5 * dt,
                   *std::max_element(theta.begin(), theta.end()) + 0.5 * dt);
    plot.setYRange(*std::min_element(y.begin(), y.end()) - 0.5 * dy,
                   *std::max_element(y.begin(), y.end()) + 0.5 * dy);
  }
  plot.addPoints("chosen start", {rep.start.pose.theta_rad * kDeg},
                 {rep.start.pose.p_SceneTip.y() * kMm}, cv::Scalar(0, 0, 230), 6);
  const cv::Mat figure =
      report::withColourKey(plot.render(800, 560), cv::COLORMAP_VIRIDIS, 0.0, 1.0, "P_s");
  if (!cv::imwrite(path, figure)) {
    throw std::runtime_error("SteerableReport: cannot write '" + path + "'");
  }
}

/// The tables that answered, when the policy re-solved (more than one, or not the scene's).
std::string tablesMarkdown(const SteerableReport& rep) {
  if (rep.tables.empty()) {
    return "";
  }
  std::ostringstream md;
  md << "Tables that answered (the policy re-solves for the noise it learns; each predicts its "
        "own trials):\n\n| sigma_i / sigma_r [deg] | trials | reached | predicted P_s | "
        "Monte Carlo |\n| --- | --- | --- | --- | --- |\n";
  for (const SteerableTableReport& t : rep.tables) {
    int reached = 0;
    for (int i : t.trials) {
      reached +=
          rep.records[static_cast<std::size_t>(i)].outcome == SteerableOutcome::kReachedTarget;
    }
    md << "| " << t.noise.sigma_insert_rad * kDeg << " / " << t.noise.sigma_flip_rad * kDeg << " | "
       << t.trials.size() << " | " << reached << " | " << t.predicted_ps << " | "
       << t.monte_carlo.rate() << " |\n";
  }
  md << "\n";
  return md.str();
}

/// Where the reported P_s comes from: "the model's prediction, confirmed by the policy's
/// verification" or "the policy's verified rate over N trials [low, high]; the model's P was
/// not confirmed within the tolerance (off by G)".
std::string reportedSource(const SteerableStart& start) {
  std::ostringstream out;
  if (start.verification_trials == 0) {
    out << "the model's prediction, not verified";
  } else if (start.confirmed) {
    out << "the model's prediction, confirmed by the policy's verification";
  } else {
    out << "the policy's verified rate over " << start.verification_trials << " trials ["
        << start.verified_ci.low << ", " << start.verified_ci.high << "]; the model's "
        << start.predicted_ps << " was not confirmed (off by "
        << std::abs(start.predicted_ps - start.verified_ps) << ")";
  }
  return out.str();
}

}  // namespace

int SteerableReport::successes() const {
  return static_cast<int>(std::count_if(records.begin(), records.end(), [](const auto& r) {
    return r.outcome == SteerableOutcome::kReachedTarget;
  }));
}

int SteerableReport::errored() const {
  return static_cast<int>(std::count_if(records.begin(), records.end(), [](const auto& r) {
    return r.outcome == SteerableOutcome::kError;
  }));
}

int SteerableReport::counted() const {
  return static_cast<int>(records.size()) - errored();
}

steering::Interval SteerableReport::successInterval() const {
  return steering::wilsonInterval(successes(), counted());
}

bool SteerableReport::success() const {
  const bool ground_truth = settings.feedback == "ground_truth";
  return !fault && errored() == 0 && counted() == settings.trials &&
         (!ground_truth || successInterval().high >= start.reportedPs());
}

std::string SteerableReport::summaryJson() const {
  using report::jsonNumber;
  std::vector<double> tip_mm, heading_deg;
  decisionErrors(*this, tip_mm, heading_deg);
  const int n = counted();
  const steering::Interval ci = successInterval();
  const double rate = n > 0 ? double(successes()) / n : 0.0;
  double steps = 0.0, flips = 0.0;
  int unconfident = 0;
  for (const auto& r : records) {
    steps += r.steps;
    flips += r.flips;
    unconfident += r.unconfident_decisions;
  }
  const std::string cause = fault ? fault->toString() + " after " + std::to_string(records.size()) +
                                        " of " + std::to_string(settings.trials) +
                                        " trials; the run was stopped" +
                                        (safe_stop.empty() ? "" : "; robot: " + safe_stop)
                                  : "";
  std::ostringstream json;
  json << "{\n  \"procedure\": \"steerable_needle\",\n  \"scene\": \"" << scene
       << "\",\n  \"success\": " << (success() ? "true" : "false") << ",\n  \"trials\": " << n
       << ",\n  \"successes\": " << successes() << ",\n  \"errored_trials\": " << errored()
       << ",\n  \"trials_requested\": " << settings.trials << ",\n  \"dead_node\": \""
       << (fault ? fault->node : "") << "\",\n  \"cause\": \"" << cause << "\""
       << ",\n  \"detected_unix_s\": " << jsonNumber(fault ? fault->detected_unix_s : 0.0, 15)
       << ",\n  \"success_rate\": " << jsonNumber(rate) << ",\n  \"success_rate_ci\": ["
       << jsonNumber(ci.low) << ", " << jsonNumber(ci.high)
       << "],\n  \"reported_ps\": " << jsonNumber(start.reportedPs())
       << ",\n  \"reported_ps_source\": \""
       << (start.verification_trials > 0 && !start.confirmed ? "verification" : "model") << "\""
       << ",\n  \"reported_gap_mc\": "
       << jsonNumber(std::abs(start.reportedPs() - monte_carlo.rate()))
       << ",\n  \"reported_confirmed_by_mc\": "
       << (start.reportedAgreesWith(monte_carlo, steering::verificationTolerance(problem))
               ? "true"
               : "false")
       << ",\n  \"predicted_ps\": " << jsonNumber(start.predicted_ps)
       << ",\n  \"predicted_within_ci\": " << (ci.contains(start.predicted_ps) ? "true" : "false")
       << ",\n  \"monte_carlo_ps\": " << jsonNumber(monte_carlo.rate())
       << ",\n  \"monte_carlo_trials\": " << monte_carlo.trials << ",\n  \"prediction_gap_mc\": "
       << jsonNumber(std::abs(start.predicted_ps - monte_carlo.rate()))
       << ",\n  \"prediction_confirmed_by_mc\": "
       << (start.confirmedBy(monte_carlo, steering::verificationTolerance(problem)) ? "true"
                                                                                    : "false")
       << ",\n  \"verified_ps\": " << jsonNumber(start.verified_ps) << ",\n  \"verified_ps_ci\": ["
       << jsonNumber(start.verified_ci.low) << ", " << jsonNumber(start.verified_ci.high)
       << "],\n  \"verification_trials\": " << start.verification_trials
       << ",\n  \"start_confirmed_by_policy\": " << (start.confirmed ? "true" : "false")
       << ",\n  \"table_best_ps\": " << jsonNumber(start.table_best_ps) << ",\n  \"model\": \""
       << model << "\",\n  \"policy_table\": \"" << policy_table << "\""
       << ",\n  \"ps_tolerance\": " << jsonNumber(problem.ps_tolerance)
       << ",\n  \"estimated_ps_error\": " << jsonNumber(estimated_ps_error)
       << ",\n  \"start_y_mm\": " << jsonNumber(start.pose.p_SceneTip.y() * kMm)
       << ",\n  \"start_theta_deg\": " << jsonNumber(start.pose.theta_rad * kDeg)
       << ",\n  \"start_bevel\": \"" << steering::toString(start.pose.bevel) << "\""
       << ",\n  \"feedback\": \"" << settings.feedback << "\""
       << ",\n  \"seed\": " << settings.seed << ",\n  \"decisions\": " << tip_mm.size()
       << ",\n  \"tip_error_mm_median\": " << jsonNumber(report::median(tip_mm))
       << ",\n  \"tip_error_mm_max\": " << jsonNumber(maximum(tip_mm))
       << ",\n  \"heading_error_deg_median\": " << jsonNumber(report::median(heading_deg))
       << ",\n  \"unconfident_decisions\": " << unconfident
       << ",\n  \"mean_steps\": " << jsonNumber(n > 0 ? steps / n : 0.0)
       << ",\n  \"mean_flips\": " << jsonNumber(n > 0 ? flips / n : 0.0)
       << ",\n  \"tables_used\": [";
  for (std::size_t k = 0; k < tables.size(); ++k) {
    const SteerableTableReport& t = tables[k];
    int reached = 0;
    for (int i : t.trials) {
      reached += records[static_cast<std::size_t>(i)].outcome == SteerableOutcome::kReachedTarget;
    }
    json << (k ? ", " : "")
         << "{\"sigma_insert_deg\": " << jsonNumber(t.noise.sigma_insert_rad * kDeg)
         << ", \"sigma_flip_deg\": " << jsonNumber(t.noise.sigma_flip_rad * kDeg)
         << ", \"trials\": " << t.trials.size() << ", \"successes\": " << reached
         << ", \"predicted_ps\": " << jsonNumber(t.predicted_ps)
         << ", \"monte_carlo_ps\": " << jsonNumber(t.monte_carlo.rate()) << "}";
  }
  json << "],\n  \"wall_time_s\": " << jsonNumber(wall_time_s) << "\n}\n";
  return json.str();
}

std::string SteerableReport::summaryMarkdown() const {
  std::vector<double> tip_mm, heading_deg;
  decisionErrors(*this, tip_mm, heading_deg);
  const int n = counted();
  const steering::Interval ci = successInterval();
  int unconfident = 0;
  double steps = 0.0, flips = 0.0;
  report::Table trials({"trial", "outcome", "steps", "flips", "seconds", "message"}, 6);
  for (std::size_t i = 0; i < records.size(); ++i) {
    const auto& r = records[i];
    unconfident += r.unconfident_decisions;
    steps += r.steps;
    flips += r.flips;
    trials.addRow({double(i + 1), std::string(toString(r.outcome)), double(r.steps),
                   double(r.flips), r.seconds, r.message});
  }
  std::ostringstream md;
  md << "# Steerable needle: " << n << " closed-loop trials on " << scene << "\n\n"
     << "| figure | value |\n| --- | --- |\n"
     << "| start | y = " << start.pose.p_SceneTip.y() * kMm
     << " mm, theta = " << start.pose.theta_rad * kDeg << " deg, bevel "
     << steering::toString(start.pose.bevel) << " |\n"
     << "| reported P_s at the start | " << start.reportedPs() << " (" << reportedSource(start)
     << ") |\n"
     << "| predicted P_s (MDP) | " << start.predicted_ps
     << " (the table's best start: " << start.table_best_ps << ") |\n"
     << "| verified by the policy | " << start.verified_ps << " [" << start.verified_ci.low << ", "
     << start.verified_ci.high << "], " << start.verification_trials << " trials, "
     << (start.confirmed ? "confirmed" : "not confirmed") << " |\n"
     << "| model | " << model << " (ps_tolerance " << problem.ps_tolerance << ") |\n"
     << (fault ? "| STOPPED | " + fault->toString() + "; robot: " + safe_stop + " |\n" : "")
     << "| errored trials (not counted as misses) | " << errored() << " |\n"
     << "| success rate (closed loop) | " << successes() << " / " << n << " = "
     << (n > 0 ? double(successes()) / n : 0.0) << ", 95 % CI [" << ci.low << ", " << ci.high
     << "] |\n"
     << "| feedback | " << settings.feedback << "; tip error at decisions median "
     << report::median(tip_mm) << " mm (max " << maximum(tip_mm) << "), heading "
     << report::median(heading_deg) << " deg; " << unconfident
     << " decisions on unconfident tips |\n"
     << "| Monte Carlo (core, " << monte_carlo.trials << " trials) | " << monte_carlo.rate()
     << " |\n"
     << "| mean steps / flips | " << (n > 0 ? steps / n : 0.0) << " / " << (n > 0 ? flips / n : 0.0)
     << " |\n\n"
     << tablesMarkdown(*this) << "![paths](paths.png)\n\n![P_s map](ps_map.png)\n\n"
     << trials.toMarkdown();
  return md.str();
}

bool SteerableStart::confirmedBy(const steering::MonteCarloResult& mc, double tolerance) const {
  return steering::verificationConfirms(predicted_ps, mc, tolerance);
}

bool SteerableStart::reportedAgreesWith(const steering::MonteCarloResult& mc,
                                        double tolerance) const {
  return mc.trials > 0 && std::abs(reportedPs() - mc.rate()) <= tolerance;
}

std::string SteerableReport::text() const {
  const int n = counted();
  const steering::Interval ci = successInterval();
  std::ostringstream out;
  out << "\n== Steerable needle (" << settings.feedback << " feedback; MDP model " << model
      << "): " << successes() << " / " << n << " closed-loop trials reached the target (rate "
      << (n > 0 ? double(successes()) / n : 0.0) << ", 95 % CI [" << ci.low << ", " << ci.high
      << "]); reported P_s " << start.reportedPs() << " (" << reportedSource(start)
      << "); predicted P_s " << start.predicted_ps << "; the report's own Monte Carlo "
      << monte_carlo.rate() << " over " << monte_carlo.trials << " trials: reported "
      << std::abs(start.reportedPs() - monte_carlo.rate()) << " and predicted "
      << std::abs(start.predicted_ps - monte_carlo.rate()) << " from it (tolerance "
      << steering::verificationTolerance(problem) << ": the reported P_s "
      << (start.reportedAgreesWith(monte_carlo, steering::verificationTolerance(problem))
              ? "confirmed"
              : "NOT confirmed")
      << ") ==\nstart y = " << start.pose.p_SceneTip.y() * kMm
      << " mm, theta = " << start.pose.theta_rad * kDeg << " deg, bevel "
      << steering::toString(start.pose.bevel) << "; " << wall_time_s << " s\n"
      << (errored() > 0 ? std::to_string(errored()) + " errored trial(s), not counted\n" : "")
      << (fault ? "FAIL: " + fault->toString() + "; robot: " + safe_stop + "\n" : "");
  return out.str();
}

void SteerableReport::write(const std::string& dir) const {
  writeTables(*this, dir);
  report::writeTextFile(dir + "/summary.json", summaryJson());
  report::writeTextFile(dir + "/summary.md", summaryMarkdown());
  writePathsPlot(*this, dir + "/paths.png");
  writePsMap(*this, dir + "/ps_map.png");
}

}  // namespace needle_guidance::procedures
