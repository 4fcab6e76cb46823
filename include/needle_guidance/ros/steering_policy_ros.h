// ROS wrapper of the steerable-needle policy (node steering_policy, dissertation 5.4.3-5.5):
// solves or loads the MDP look-up table for the node's scene and target, answers every incoming
// tip pose with the optimal control and its P_s, and serves the best start state. The MDP, the
// solver, the table file and the look-up are the core's (steering/); this class only converts
// and wires.
#pragma once

#include <ros/ros.h>

#include <cstdint>
#include <memory>
#include <optional>
#include <string>

#include "needle_guidance/BestStart.h"
#include "needle_guidance/NeedleTip.h"
#include "needle_guidance/SolvePolicy.h"
#include "needle_guidance/steering/adaptive_policy.h"
#include "needle_guidance/steering/policy_table.h"
#include "needle_guidance/steering/start_verification.h"
#include "needle_guidance/steering/steering_model.h"

namespace needle_guidance {

/// "interpolated, grid 0.7 mm, s = 3, 4839360 states": the discretisation a table belongs to.
std::string modelDescription(const steering::SteeringModel& model);

/// Subscribes `tip` (NeedleTip, frame scene; remap it to the tracker's or the robot's topic) and
/// publishes one `~control` (SteeringControl) per well-formed tip. Serves `~solve` (SolvePolicy)
/// and `~best_start` (BestStart). Publishes latched `~ps_map` (Marker CUBE_LIST, max P_s per grid
/// position) and `~best_start_marker` (Marker ARROW) after every solve or load.
///
/// Tables are files `<table_dir>/<scene name>_<problem hash, 16 hex digits>.table`; a file is
/// used only if it was solved for the same problem (hash) to an epsilon no larger than the one
/// asked for, otherwise the MDP is solved and the file (re)written. A failed solve keeps the
/// previous table.
class SteeringPolicyRos {
public:
  /// Parameters, read once and echoed.
  struct Settings {
    std::string scene = "steering_workspace";  ///< ~scene: embedded scene name or YAML path
    std::string target;                        ///< ~target: target name, "" = the first
    double epsilon = 1e-3;       ///< ~epsilon: value-iteration threshold, (0, 0.1] (5.4.3)
    int threads = 2;             ///< ~threads: model pre-computation and solver threads, 1..2
    std::string table_dir;       ///< ~table_dir, resolved against ROS_HOME; "" = never save
    bool solve_on_start = true;  ///< ~solve_on_start
    bool adapt_noise = true;     ///< ~adapt_noise: learn sigma from the tips and re-solve
  };

  /// Reads and checks every parameter, builds the MDP of the scene's target (diagnostics are
  /// logged as warnings), solves or loads the table when ~solve_on_start, then advertises.
  /// Throws std::runtime_error naming a bad parameter, and std::invalid_argument /
  /// std::out_of_range for a scene without a steering section or an unknown target. A failed
  /// start-up solve is logged, not thrown: the node waits for ~solve.
  SteeringPolicyRos(ros::NodeHandle& nh, ros::NodeHandle& private_nh);

  /// The result of one solve-or-load request.
  struct SolveOutcome {
    bool success = false;
    std::string message;
    std::string source;    ///< solved | loaded | cached ("" on failure)
    int sweeps = 0;        ///< value-iteration sweeps of the table in use
    double seconds = 0.0;  ///< wall time of this request [s]
  };

private:
  /// Makes a table available for `epsilon` (see the class comment); on success publishes the
  /// maps, on failure leaves table_ and the topics as they were. Never throws.
  SolveOutcome solveOrLoad(double epsilon, bool force);
  void onTip(const NeedleTipConstPtr& msg);
  /// Makes `source` the table in use (model_, table_ share it).
  void adopt(const std::shared_ptr<const steering::PolicySource>& source);
  /// Feeds adaptive_ the step from the first tip at rest at one step boundary to the first at
  /// the next; its control is whether the bevel changed.
  void learnFrom(const NeedleTip& tip, const steering::TipPose& pose, bool vouched);
  /// Swaps in a re-solved table once its background solve has finished (checked on every tip).
  void adoptFinishedResolve();
  bool onSolve(SolvePolicy::Request& req, SolvePolicy::Response& res);
  bool onBestStart(BestStart::Request& req, BestStart::Response& res);
  /// Publishes ~ps_map for table_ (which must be set) and, with verify_start, verifies its start
  /// and publishes ~best_start_marker.
  void publishMaps(bool verify_start);
  /// The verified start of table_ (verifyBestStart), computed once per table.
  const steering::VerifiedStart& verifiedStart();

  Settings settings_;
  std::string scene_name_;
  steering::StartOptions start_options_;
  std::shared_ptr<const steering::SteeringModel> model_;  ///< of table_ (shares its source)
  std::shared_ptr<const steering::PolicyTable> table_;
  /// Learns sigma_i / sigma_r from the tips answered and swaps in re-solved tables (~adapt_noise).
  std::unique_ptr<steering::AdaptivePolicy> adaptive_;
  /// Pairs the tips answered into whole steps for adaptive_ (set with it).
  std::optional<steering::StepPairing> steps_;
  std::optional<steering::VerifiedStart> verified_;
  const steering::PolicyTable* verified_for_ = nullptr;  ///< the table verified_ belongs to
  std::string table_source_;                             ///< how table_ was made: solved | loaded
  steering::SteeringProblem problem_;                    ///< the scene's, with its ps_tolerance
  std::string description_;       ///< model, estimated error and time of table_
  double estimated_error_ = 0.0;  ///< NaN when not estimated (ps_tolerance 0)
  ros::Publisher control_pub_;
  ros::Publisher ps_map_pub_;
  ros::Publisher ps_key_pub_;  ///< ~ps_map_key: the map's colour key
  ros::Publisher best_start_pub_;
  ros::Subscriber tip_sub_;
  ros::ServiceServer solve_srv_;
  ros::ServiceServer best_start_srv_;
};

}  // namespace needle_guidance
