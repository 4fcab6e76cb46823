// rostest for the dwell_scheduler node: plans synthetic case 1 with the LP, checks the plan, its
// schedule and the latched topic; refused requests leave the latched plan as it was; evaluating a
// delivery equal to the plan gives the plan's indices back, transit adds dose, bad deliveries are
// refused. DwellSchedulerDecay.*: a node with a calibrated source plans at start-up.
#include <gtest/gtest.h>
#include <ros/ros.h>

#include <algorithm>
#include <cmath>
#include <map>
#include <optional>
#include <string>
#include <vector>

#include "../ros_wait.h"
#include "needle_guidance/DwellPlan.h"
#include "needle_guidance/EvaluateDelivery.h"
#include "needle_guidance/PlanDwells.h"

namespace {

using needle_guidance::DwellPlan;
using needle_guidance::EvaluateDelivery;
using needle_guidance::PlanDwells;

constexpr double kObjectiveRelTol = 1e-6;  ///< objective >= lower bound - this x |objective|
constexpr double kTotalTimeTol_s = 1e-9;   ///< total_dwell_s vs the sum of the schedule's times
constexpr double kIndexRelTol = 1e-6;      ///< delivered == planned indices (same dwell times)
constexpr double kIndexAbsTol = 1e-12;     ///< [% or Gy], for indices that are 0
constexpr double kScaledRelTol = 1e-9;  ///< D90 of half the times is half the D90 (dose is linear)
constexpr double kV100Min_pct = 80.0;   ///< an LP plan covers the prostate (synthetic case 1)
constexpr double kV100Max_pct = 100.0;
constexpr double kIr192HalfLife_days = 73.83;  ///< independent of the code under test
constexpr double kDecayRelTol = 1e-9;
const std::string kNode = "/dwell_scheduler";
const ros::Duration kServiceWait(60.0);
constexpr double kTopicWait_s = 30.0;

bool waitForServices() {
  return ros::service::waitForService(kNode + "/plan", kServiceWait) &&
         ros::service::waitForService(kNode + "/evaluate", kServiceWait);
}

PlanDwells::Response plan(const std::string& case_dir, int seed, const std::string& method,
                          const std::string& plan_id = "") {
  PlanDwells srv;
  srv.request.case_dir = case_dir;
  srv.request.synthetic_seed = seed;
  srv.request.method = method;
  srv.request.plan_id = plan_id;
  EXPECT_TRUE(ros::service::call(kNode + "/plan", srv)) << "the plan service call failed";
  return srv.response;
}

EvaluateDelivery::Response evaluate(const EvaluateDelivery::Request& request) {
  EvaluateDelivery srv;
  srv.request = request;
  EXPECT_TRUE(ros::service::call(kNode + "/evaluate", srv)) << "the evaluate service call failed";
  return srv.response;
}

/// The latched ~plan as a new subscriber receives it (nullopt if nothing arrives).
std::optional<DwellPlan> latchedPlan() {
  return firstMessage<DwellPlan>(kNode + "/plan", kTopicWait_s);
}

/// Synthetic case 1 planned with the LP once for the whole suite.
const PlanDwells::Response& firstPlan() {
  static const PlanDwells::Response response = plan("", 1, "lp");
  return response;
}

/// The delivery of every scheduled dwell at `fraction` of its scheduled time.
EvaluateDelivery::Request deliveryOf(const DwellPlan& p, double fraction) {
  EvaluateDelivery::Request request;
  request.plan_id = p.plan_id;
  for (const auto& ch : p.schedule.channels) {
    for (std::size_t k = 0; k < ch.time_s.size(); ++k) {
      request.channel.push_back(ch.channel);
      request.dwell_index.push_back(ch.dwell_index[k]);
      request.delivered_s.push_back(fraction * ch.time_s[k]);
    }
  }
  return request;
}

std::map<std::string, double> byName(const std::vector<std::string>& names,
                                     const std::vector<double>& values) {
  std::map<std::string, double> out;
  for (std::size_t k = 0; k < names.size() && k < values.size(); ++k)
    out[names[k]] = values[k];
  return out;
}

TEST(DwellScheduler, PlansSyntheticCaseWithLp) {
  ASSERT_TRUE(waitForServices());
  const PlanDwells::Response& res = firstPlan();
  ASSERT_TRUE(res.success) << res.message;
  const DwellPlan& p = res.plan;
  EXPECT_FALSE(p.plan_id.empty());
  EXPECT_EQ(p.method, "lp");
  EXPECT_EQ(p.case_name, "synthetic_1");
  ASSERT_TRUE(std::isfinite(p.objective));
  ASSERT_TRUE(std::isfinite(p.lower_bound));
  EXPECT_GE(p.objective, p.lower_bound - kObjectiveRelTol * std::abs(p.objective));
  EXPECT_GE(p.optimisation_s, 0.0);

  ASSERT_EQ(p.index_names.size(), p.index_values.size());
  EXPECT_TRUE(std::is_sorted(p.index_names.begin(), p.index_names.end()));
  const auto indices = byName(p.index_names, p.index_values);
  ASSERT_EQ(indices.count("prostate_V100"), 1u);
  EXPECT_GT(indices.at("prostate_V100"), kV100Min_pct);
  EXPECT_LE(indices.at("prostate_V100"), kV100Max_pct);
  for (const auto& [name, value] : indices)
    EXPECT_TRUE(std::isfinite(value)) << name;

  ASSERT_FALSE(p.schedule.channels.empty());
  EXPECT_EQ(p.schedule.plan_id, p.plan_id);
  EXPECT_EQ(p.schedule.frame_id, "patient");
  double sum_s = 0.0;
  for (const auto& ch : p.schedule.channels) {
    ASSERT_FALSE(ch.time_s.empty()) << "channel " << ch.channel;
    ASSERT_EQ(ch.distance_m.size(), ch.time_s.size());
    ASSERT_EQ(ch.dwell_index.size(), ch.time_s.size());
    ASSERT_EQ(ch.position.size(), ch.time_s.size());
    for (std::size_t k = 0; k < ch.time_s.size(); ++k) {
      EXPECT_GT(ch.time_s[k], 0.0) << "channel " << ch.channel << " dwell " << k;
      EXPECT_LE(ch.distance_m[k], ch.length_m) << "channel " << ch.channel;
      EXPECT_GT(ch.distance_m[k], ch.transfer_length_m) << "channel " << ch.channel;
      if (k > 0) {
        EXPECT_LT(ch.distance_m[k], ch.distance_m[k - 1])
            << "channel " << ch.channel << " dwell " << k;
      }
      sum_s += ch.time_s[k];
    }
  }
  EXPECT_NEAR(p.total_dwell_s, sum_s, kTotalTimeTol_s);
  EXPECT_GT(p.transit_s, 0.0);

  const auto latched = latchedPlan();
  ASSERT_TRUE(latched.has_value()) << "no latched ~plan";
  EXPECT_EQ(latched->plan_id, p.plan_id);
}

TEST(DwellScheduler, RefusalsLeaveThePublishedPlan) {
  ASSERT_TRUE(waitForServices());
  const std::string id = "rostest_before_refusals";
  const PlanDwells::Response before = plan("", 2, "lp", id);
  ASSERT_TRUE(before.success) << before.message;

  const std::string missing = "/tmp/dwell_scheduler_rostest_no_such_case_dir";
  const PlanDwells::Response no_dir = plan(missing, 0, "lp");
  EXPECT_FALSE(no_dir.success);
  EXPECT_NE(no_dir.message.find(missing), std::string::npos) << no_dir.message;

  const PlanDwells::Response bad_method = plan("", 1, "xyz");
  EXPECT_FALSE(bad_method.success);
  EXPECT_NE(bad_method.message.find("xyz"), std::string::npos) << bad_method.message;

  const PlanDwells::Response bad_seed = plan("", -4, "lp");
  EXPECT_FALSE(bad_seed.success);
  EXPECT_NE(bad_seed.message.find("-4"), std::string::npos) << bad_seed.message;

  const PlanDwells::Response reused = plan("", 1, "lp", id);
  EXPECT_FALSE(reused.success) << "a plan id names one plan only";
  EXPECT_NE(reused.message.find(id), std::string::npos) << reused.message;

  const PlanDwells::Response bad_id = plan("", 1, "lp", "../escape");
  EXPECT_FALSE(bad_id.success);

  const auto latched = latchedPlan();
  ASSERT_TRUE(latched.has_value()) << "no latched ~plan";
  EXPECT_EQ(latched->plan_id, id);
  EXPECT_EQ(latched->case_name, "synthetic_2");
}

TEST(DwellScheduler, DeliveredAsPlannedGivesThePlannedIndices) {
  ASSERT_TRUE(waitForServices());
  const PlanDwells::Response& planned = firstPlan();
  ASSERT_TRUE(planned.success) << planned.message;
  const EvaluateDelivery::Response res = evaluate(deliveryOf(planned.plan, 1.0));
  ASSERT_TRUE(res.success) << res.message;
  ASSERT_EQ(res.index_names, planned.plan.index_names);
  ASSERT_EQ(res.planned_values.size(), res.index_names.size());
  ASSERT_EQ(res.delivered_values.size(), res.index_names.size());
  ASSERT_EQ(res.with_transit_values.size(), res.index_names.size());
  for (std::size_t k = 0; k < res.index_names.size(); ++k) {
    const double p = res.planned_values[k];
    EXPECT_NEAR(p, planned.plan.index_values[k], kIndexRelTol * std::abs(p) + kIndexAbsTol)
        << res.index_names[k];
    EXPECT_NEAR(res.delivered_values[k], p, kIndexRelTol * std::abs(p) + kIndexAbsTol)
        << res.index_names[k];
    // No trips reported: no transit dose.
    EXPECT_EQ(res.with_transit_values[k], res.delivered_values[k]) << res.index_names[k];
  }
  EXPECT_EQ(res.transit_dose_max_Gy, 0.0);
}

TEST(DwellScheduler, TransitAddsDose) {
  ASSERT_TRUE(waitForServices());
  const PlanDwells::Response& planned = firstPlan();
  ASSERT_TRUE(planned.success) << planned.message;
  EvaluateDelivery::Request request = deliveryOf(planned.plan, 1.0);
  for (const auto& ch : planned.plan.schedule.channels) {
    request.trips_channel.push_back(ch.channel);
    request.trips.push_back(1);
  }
  const EvaluateDelivery::Response res = evaluate(request);
  ASSERT_TRUE(res.success) << res.message;
  EXPECT_GT(res.transit_dose_max_Gy, 0.0);
  EXPECT_GT(res.transit_dose_mean_Gy, 0.0);
  EXPECT_LE(res.transit_dose_mean_Gy, res.transit_dose_max_Gy);
  const auto delivered = byName(res.index_names, res.delivered_values);
  const auto with_transit = byName(res.index_names, res.with_transit_values);
  ASSERT_EQ(delivered.count("prostate_D90"), 1u);
  EXPECT_GE(with_transit.at("prostate_D90"), delivered.at("prostate_D90"));
  // Every index (V_x, D_x) grows with dose.
  for (const auto& [name, value] : delivered)
    EXPECT_GE(with_transit.at(name), value) << name;
}

TEST(DwellScheduler, HalfTheTimesGiveHalfTheDose) {
  ASSERT_TRUE(waitForServices());
  const PlanDwells::Response& planned = firstPlan();
  ASSERT_TRUE(planned.success) << planned.message;
  const EvaluateDelivery::Response res = evaluate(deliveryOf(planned.plan, 0.5));
  ASSERT_TRUE(res.success) << res.message;
  const auto p = byName(res.index_names, res.planned_values);
  const auto d = byName(res.index_names, res.delivered_values);
  ASSERT_EQ(p.count("prostate_D90"), 1u);
  EXPECT_NEAR(d.at("prostate_D90"), 0.5 * p.at("prostate_D90"),
              kScaledRelTol * p.at("prostate_D90"));
  EXPECT_LT(d.at("prostate_V100"), p.at("prostate_V100"));
}

TEST(DwellScheduler, BadDeliveriesRefused) {
  ASSERT_TRUE(waitForServices());
  const PlanDwells::Response& planned = firstPlan();
  ASSERT_TRUE(planned.success) << planned.message;
  const EvaluateDelivery::Request good = deliveryOf(planned.plan, 1.0);
  ASSERT_FALSE(good.channel.empty());

  EvaluateDelivery::Request negative = good;
  negative.delivered_s[0] = -1.0;
  const auto r1 = evaluate(negative);
  EXPECT_FALSE(r1.success);
  EXPECT_NE(r1.message.find("entry 0"), std::string::npos) << r1.message;
  EXPECT_TRUE(r1.index_names.empty());

  EvaluateDelivery::Request not_finite = good;
  not_finite.delivered_s.back() = std::nan("");
  EXPECT_FALSE(evaluate(not_finite).success);

  EvaluateDelivery::Request unknown_plan = good;
  unknown_plan.plan_id = "no_such_plan";
  const auto r2 = evaluate(unknown_plan);
  EXPECT_FALSE(r2.success);
  EXPECT_NE(r2.message.find("no_such_plan"), std::string::npos) << r2.message;

  EvaluateDelivery::Request short_arrays = good;
  short_arrays.dwell_index.pop_back();
  EXPECT_FALSE(evaluate(short_arrays).success);

  EvaluateDelivery::Request unknown_channel = good;
  unknown_channel.channel[0] = 999;
  const auto r3 = evaluate(unknown_channel);
  EXPECT_FALSE(r3.success);
  EXPECT_NE(r3.message.find("999"), std::string::npos) << r3.message;

  EvaluateDelivery::Request unknown_dwell = good;
  unknown_dwell.dwell_index[0] = 12345;
  EXPECT_FALSE(evaluate(unknown_dwell).success);

  EvaluateDelivery::Request negative_trips = good;
  negative_trips.trips_channel = {good.channel[0]};
  negative_trips.trips = {-1};
  EXPECT_FALSE(evaluate(negative_trips).success);

  EvaluateDelivery::Request trip_lengths = good;
  trip_lengths.trips_channel = {good.channel[0]};
  EXPECT_FALSE(evaluate(trip_lengths).success);

  // The plan is still there and evaluates.
  EXPECT_TRUE(evaluate(good).success);
}

// A node started with plan_on_start and a calibrated source (dwell_scheduler_decay.test).
TEST(DwellSchedulerDecay, StartUpPlanIsDecayCorrected) {
  ros::NodeHandle private_nh("~");
  double calibration_U = 0.0, days = 0.0;
  ASSERT_TRUE(private_nh.getParam("calibration_air_kerma_strength_U", calibration_U));
  ASSERT_TRUE(private_nh.getParam("expected_decay_days", days));
  const auto latched = latchedPlan();
  ASSERT_TRUE(latched.has_value()) << "no plan published at start-up";
  const auto& s = latched->schedule;
  EXPECT_NEAR(s.decay_days, days, 1e-9 * days);
  const double expected_U = calibration_U * std::pow(0.5, days / kIr192HalfLife_days);
  EXPECT_NEAR(s.current_air_kerma_strength_U, expected_U, kDecayRelTol * expected_U);
  ASSERT_GT(s.plan_air_kerma_strength_U, 0.0);
  // Planning S_K, the case's, stays; the decayed source dwells longer (or shorter) in proportion.
  ASSERT_TRUE(waitForServices());
  EvaluateDelivery::Request request = deliveryOf(*latched, 1.0);
  const auto res = evaluate(request);
  ASSERT_TRUE(res.success) << res.message;
  for (std::size_t k = 0; k < res.index_names.size(); ++k) {
    const double p = res.planned_values[k];
    EXPECT_NEAR(res.delivered_values[k], p, kIndexRelTol * std::abs(p) + kIndexAbsTol)
        << res.index_names[k];
  }
}

}  // namespace

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  ros::init(argc, argv, "dwell_scheduler_rostest");
  ros::NodeHandle keep_alive;  // the node shuts down when its last NodeHandle goes
  return RUN_ALL_TESTS();
}
