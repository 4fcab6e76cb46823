// rostest for the closed-loop steerable-needle trials: the real insertion robot (steerable mode),
// steering_policy and steerable_procedure run 8 trials; the report is checked against the
// scene: every trial ends in a defined outcome, every success ends in the target disc, every
// path starts at the best start and stays in the workspace, and flips are where the policy said.
#include <gtest/gtest.h>
#include <ros/ros.h>

#include <cmath>
#include <fstream>
#include <map>
#include <set>
#include <sstream>
#include <string>

#include "../csv_rows.h"
#include "../ros_wait.h"
#include "needle_guidance/scene/scene.h"
#include "needle_guidance/steering/steering_model.h"

namespace {

constexpr int kTrials = 8;
constexpr double kMmTol = 1e-3;  // [mm] CSV rounding of positions (6 significant digits)
constexpr double kContactTol = 0.05;
// [mm] a tip the tracker called confident (position sd <= 0.5 mm) is within this of the truth
constexpr double kConfidentTipErrorMm =
    2.5;  // [mm] a stopped tip lies on the workspace edge or outside no further

TEST(SteerableNeedle, TrialsRunToAnOutcomeAndTheReportMatchesTheScene) {
  ros::NodeHandle private_nh("~");
  std::string report_dir;
  ASSERT_TRUE(private_nh.getParam("report_dir", report_dir));
  const std::string summary = report_dir + "/summary.json";
  const std::optional<std::string> text = waitForText(summary, 200.0);
  ASSERT_TRUE(text) << "the procedure wrote no report in 200 s";
  EXPECT_NE(text->find("\"trials\": 8,"), std::string::npos) << *text;
  // The report reads the table steering_policy saved; it does not solve the MDP again.
  EXPECT_NE(text->find("\"policy_table\": \"loaded\""), std::string::npos) << *text;
  // The start is the policy's verified one; the report gives the verification and its own check.
  // A first look of max(16000, 1 / tol^2) x 4 p (1 - p) trials at steering_workspace's
  // tolerance 0.005 (a standard error of at most half the tolerance at the start's P_s),
  // continued to at most 100,000 while the prediction is not confirmed.
  const double verification_trials = jsonNumber(*text, "verification_trials");
  const double predicted = jsonNumber(*text, "predicted_ps");
  EXPECT_LE(verification_trials, 100000.0) << *text;
  EXPECT_LE(std::sqrt(predicted * (1.0 - predicted) / verification_trials), 0.5 * 0.005 + 1e-7)
      << *text;
  // The reported P_s is the prediction when the policy confirmed it, else the verified rate.
  const bool confirmed = text->find("\"start_confirmed_by_policy\": true") != std::string::npos;
  EXPECT_EQ(jsonNumber(*text, "reported_ps"),
            confirmed ? predicted : jsonNumber(*text, "verified_ps"))
      << *text;
  EXPECT_NE(text->find("\"start_confirmed_by_policy\": "), std::string::npos) << *text;
  EXPECT_NE(text->find("\"prediction_confirmed_by_mc\": "), std::string::npos) << *text;
  // The report's own Monte Carlo resolves the tolerance: 1.96 SE <= tolerance / 2 at the
  // reported P_s (or the trial limit), and it confirms the reported P_s within the tolerance.
  const double reported = jsonNumber(*text, "reported_ps");
  const double mc_trials = jsonNumber(*text, "monte_carlo_trials");
  EXPECT_TRUE(mc_trials >= 200000.0 ||
              1.96 * std::sqrt(reported * (1.0 - reported) / mc_trials) <= 0.5 * 0.005 + 1e-6)
      << *text;
  EXPECT_NE(text->find("\"reported_confirmed_by_mc\": true"), std::string::npos) << *text;

  namespace st = needle_guidance::steering;
  const st::SteeringProblem problem =
      st::problemFromScene(needle_guidance::scene::loadSceneSpec("steering_workspace"));
  const auto trials = readCsvRows(report_dir + "/trials.csv");
  ASSERT_EQ(trials.size(), static_cast<std::size_t>(kTrials));
  const std::set<std::string> outcomes = {"reached_target", "hit_obstacle", "left_workspace",
                                          "step_limit"};
  std::map<std::string, std::string> outcome_of;
  for (const auto& row : trials) {
    EXPECT_TRUE(outcomes.count(row.at("outcome")))
        << row.at("outcome") << ": " << row.at("message");
    outcome_of[row.at("trial")] = row.at("outcome");
  }

  // Decision points: the first of each trial is the best start; the last of a success is in
  // the target disc; every flip decision is followed by a bevel change.
  const auto decisions = readCsvRows(report_dir + "/decisions.csv");
  std::map<std::string, std::vector<std::map<std::string, std::string>>> by_trial;
  for (const auto& row : decisions)
    by_trial[row.at("trial")].push_back(row);
  ASSERT_EQ(by_trial.size(), static_cast<std::size_t>(kTrials));
  const double tx = problem.target.position.x() * 1e3, ty = problem.target.position.y() * 1e3;
  const double tr = problem.target.radius_m * 1e3;
  for (const auto& [trial, rows] : by_trial) {
    ASSERT_FALSE(rows.empty());
    EXPECT_NEAR(std::stod(rows.front().at("x_mm")), 0.0, kMmTol) << "trial " << trial;
    for (std::size_t i = 0; i + 1 < rows.size(); ++i) {
      if (rows[i].at("control") == "flip") {
        EXPECT_NE(rows[i].at("bevel"), rows[i + 1].at("bevel"))
            << "trial " << trial << " step " << i;
      } else if (rows[i].at("control") == "insert") {
        EXPECT_EQ(rows[i].at("bevel"), rows[i + 1].at("bevel"))
            << "trial " << trial << " step " << i;
      }
    }
    const double x = std::stod(rows.back().at("x_mm")), y = std::stod(rows.back().at("y_mm"));
    if (outcome_of[trial] == "reached_target") {
      EXPECT_LE(std::hypot(x - tx, y - ty), tr + kMmTol) << "trial " << trial;
    } else if (outcome_of[trial] == "left_workspace") {
      const double edge = std::min({x, y, 100.0 - x, 100.0 - y});
      EXPECT_NEAR(edge, 0.0, kContactTol)
          << "trial " << trial << " stopped at (" << x << ", " << y << ")";
    }
  }
  // With image feedback (steerable_needle_image.test) the policy acted on tracked tips: every
  // decision names its source, and those the tracker was confident of are close to the truth.
  std::string feedback = "ground_truth";
  private_nh.getParam("feedback", feedback);
  EXPECT_NE(text->find("\"feedback\": \"" + feedback + "\""), std::string::npos) << *text;
  int confident_decisions = 0;
  for (const auto& row : decisions) {
    if (row.at("control") == "end") {
      continue;
    }
    if (feedback == "ground_truth") {
      EXPECT_EQ(row.at("source"), "ground_truth");
      EXPECT_NEAR(std::stod(row.at("tip_error_mm")), 0.0, kMmTol);
    } else if (row.at("confident") == "1") {
      ++confident_decisions;
      EXPECT_TRUE(row.at("source") == "entry" || row.at("source") == "tracked") << row.at("source");
      EXPECT_LT(std::stod(row.at("tip_error_mm")), kConfidentTipErrorMm)
          << "trial " << row.at("trial") << " step " << row.at("step");
    }
  }
  if (feedback == "image") {
    EXPECT_GT(confident_decisions, 0);
  }
  // Every recorded tip lies in the (closed) workspace.
  for (const auto& row : readCsvRows(report_dir + "/paths.csv")) {
    const double x = std::stod(row.at("x_mm")), y = std::stod(row.at("y_mm"));
    EXPECT_GE(x, -kContactTol);
    EXPECT_LE(x, 100.0 + kContactTol);
    EXPECT_GE(y, -kContactTol);
    EXPECT_LE(y, 100.0 + kContactTol);
  }
}

}  // namespace

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  ros::init(argc, argv, "steerable_needle_rostest");
  return RUN_ALL_TESTS();
}
