#include "needle_guidance/ros/afterloader_ros.h"

#include <geometry_msgs/TransformStamped.h>
#include <std_msgs/String.h>
#include <visualization_msgs/Marker.h>

#include <filesystem>

#include "needle_guidance/AfterloaderState.h"
#include "needle_guidance/report/output_path.h"
#include "needle_guidance/ros/delivery_conversions.h"
#include "needle_guidance/ros/params.h"

namespace needle_guidance {

using delivery::DeliveryState;

AfterloaderRos::AfterloaderRos(ros::NodeHandle& nh, ros::NodeHandle& private_nh) {
  (void)nh;
  ROS_INFO("afterloader parameters:");
  delivery::AfterloaderConfig config;
  config.journal_dir =
      ros_params::rosHomePath(ros_params::text(private_nh, "journal_dir", "afterloader", true));
  if (const std::string why = report::systemLocation(config.journal_dir);
      !why.empty() && !ros_params::flag(private_nh, "allow_system_paths", false)) {
    throw std::runtime_error("parameter " + private_nh.resolveName("journal_dir") +
                             ": refused: " + why + " (allow_system_paths:=true to write there)");
  }
  config.limits.channels =
      static_cast<int>(ros_params::number(private_nh, "channels", 18, 1, 40, "channels"));
  config.limits.max_length_m =
      ros_params::number(private_nh, "max_channel_length_m", 1.5, 0.1, 3.0, "m");
  config.limits.max_dwell_s =
      ros_params::number(private_nh, "max_dwell_s", 999.0, 1.0, 3600.0, "s");
  config.source_speed_m_s =
      ros_params::number(private_nh, "source_speed_m_s", 0.5, 0.01, 2.0, "m/s");
  config.commit_quantum_s =
      ros_params::number(private_nh, "commit_quantum_s", 0.05, 0.001, 0.1, "s");
  time_scale_ = ros_params::number(private_nh, "time_scale", 1.0, 0.1, 1000.0, "x real time");
  const double control_rate_hz =
      ros_params::number(private_nh, "control_rate_hz", 100.0, 10.0, 1000.0, "Hz");
  publish_period_s_ =
      1.0 / ros_params::number(private_nh, "publish_rate_hz", 20.0, 1.0, control_rate_hz, "Hz");
  frame_id_ = ros_params::text(private_nh, "frame_id", "patient", true);
  std::error_code ec;
  std::filesystem::create_directories(config.journal_dir, ec);
  if (ec)
    throw std::runtime_error("cannot create journal directory " + config.journal_dir + ": " +
                             ec.message());
  device_ = std::make_unique<delivery::Afterloader>(config);

  // Deliveries a crash interrupted: they resume when their schedule is sent again.
  std::string interrupted;
  for (const auto& entry : std::filesystem::directory_iterator(config.journal_dir)) {
    if (entry.path().extension() != ".journal")
      continue;
    try {
      const delivery::Journal journal(entry.path().string());
      const auto ledger = delivery::replay(journal.records(), nullptr, config.source_speed_m_s);
      if (!ledger.completed && ledger.begun)
        interrupted += " " + ledger.plan_id;
    } catch (const std::exception& e) {
      ROS_ERROR_STREAM("afterloader: " << e.what());
    }
  }
  if (!interrupted.empty()) {
    ROS_WARN_STREAM("afterloader: unfinished deliveries in "
                    << config.journal_dir << ":" << interrupted
                    << " (send the same schedule to resume)");
  }

  state_pub_ = private_nh.advertise<AfterloaderState>("state", 1, true);
  journal_pub_ = private_nh.advertise<std_msgs::String>("journal", 10000);
  marker_pub_ = private_nh.advertise<visualization_msgs::Marker>("source_marker", 1, true);
  pause_srv_ = private_nh.advertiseService("pause", &AfterloaderRos::onPause, this);
  resume_srv_ = private_nh.advertiseService("resume", &AfterloaderRos::onResume, this);
  door_srv_ = private_nh.advertiseService("set_door_open", &AfterloaderRos::onDoor, this);
  obstruction_srv_ =
      private_nh.advertiseService("set_obstruction", &AfterloaderRos::onObstruction, this);
  server_ = std::make_unique<Server>(
      private_nh, "deliver", [this](Server::GoalHandle g) { onGoal(g); },
      [this](Server::GoalHandle g) { onCancel(g); }, false);
  server_->start();
  last_step_ = last_publish_ = ros::WallTime::now();
  publish(false);
  timer_ = private_nh.createWallTimer(ros::WallDuration(1.0 / control_rate_hz),
                                      &AfterloaderRos::onTimer, this);
  ROS_INFO_STREAM("afterloader: ready, " << config.limits.channels << " channels, journal in "
                                         << config.journal_dir);
}

DeliverResult AfterloaderRos::result(const std::string& status, const std::string& message) const {
  DeliverResult r;
  r.status = status;
  r.message = message;
  for (const auto& d : device_->records()) {
    r.channel.push_back(d.channel);
    r.dwell_index.push_back(d.dwell);
    r.planned_s.push_back(d.planned_s);
    r.delivered_s.push_back(d.delivered_s);
  }
  const auto ledger = device_->ledger();
  for (const auto& [channel, trips] : ledger.trips) {
    r.trips_channel.push_back(channel);
    r.trips.push_back(trips);
  }
  r.transit_in_patient_s = ledger.transit_in_patient_s;
  r.interruptions = ledger.interruptions;
  r.journal = device_->journalPath();
  return r;
}

void AfterloaderRos::onGoal(Server::GoalHandle goal) {
  const auto refuse = [&](const std::string& why) {
    DeliverResult r;
    r.status = "refused";
    r.message = why;
    ROS_WARN_STREAM("afterloader: goal refused: " << why);
    goal.setRejected(r, why);
  };
  if (goal_)
    return refuse("a delivery is in progress (plan '" + device_->schedule()->plan_id + "')");
  const delivery::Schedule schedule = ros_conversions::fromMessage(goal.getGoal()->schedule);
  const delivery::Status status = device_->start(schedule);
  if (!status.ok())
    return refuse(status.message());
  goal.setAccepted(device_->lastMessage());
  goal_ = goal;
  cancelling_ = false;
  goal_start_time_s_ = device_->time();
  ROS_INFO_STREAM("afterloader: " << device_->lastMessage() << ", " << device_->remainingDwellTime()
                                  << " s of dwell time to deliver");
  publish(true);
}

void AfterloaderRos::onCancel(Server::GoalHandle goal) {
  if (!goal_ || !(goal == *goal_))
    return;
  const auto status = device_->abort("delivery goal cancelled");
  cancelling_ = true;
  ROS_WARN_STREAM("afterloader: " << (status.ok() ? device_->lastMessage() : status.message()));
}

void AfterloaderRos::onTimer(const ros::WallTimerEvent&) {
  const ros::WallTime now = ros::WallTime::now();
  const double dt = std::max(0.0, (now - last_step_).toSec()) * time_scale_;
  last_step_ = now;
  try {
    device_->step(dt);
  } catch (const std::exception& e) {
    ROS_ERROR_STREAM("afterloader: " << e.what() << "; delivery stopped, source retracted");
  }
  for (const auto& line : device_->takeJournalLines()) {
    std_msgs::String m;
    m.data = line;
    journal_pub_.publish(m);
  }
  const DeliveryState state = device_->state();
  if (goal_ && device_->sourceChannel() == 0 &&
      (state == DeliveryState::kCompleted || state == DeliveryState::kStopped)) {
    const bool completed = state == DeliveryState::kCompleted;
    const std::string status = completed ? "completed" : cancelling_ ? "aborted" : "stopped";
    const DeliverResult r = result(status, device_->lastMessage());
    if (completed)
      goal_->setSucceeded(r, r.message);
    else if (cancelling_)
      goal_->setCanceled(r, r.message);
    else
      goal_->setAborted(r, r.message);
    ROS_INFO_STREAM("afterloader: " << status << ": " << r.message);
    goal_.reset();
    cancelling_ = false;
    publish(false);
  }
  if ((now - last_publish_).toSec() >= publish_period_s_) {
    last_publish_ = now;
    publish(true);
  }
}

void AfterloaderRos::publish(bool feedback) {
  const ros::Time stamp = ros::Time::now();
  AfterloaderState s;
  s.header.stamp = stamp;
  s.state = goal_ || device_->state() != DeliveryState::kIdle ? delivery::toString(device_->state())
                                                              : "IDLE";
  s.plan_id = device_->schedule() ? device_->schedule()->plan_id : "";
  s.channel = device_->sourceChannel();
  s.dwell = device_->sourceDwell();
  s.source_distance_m = device_->sourceDistance();
  s.source_in_patient = device_->sourceInPatient();
  s.door_open = device_->doorOpen();
  s.obstructed_channels = device_->obstructedChannels();
  s.delivered_fraction = device_->deliveredFraction();
  s.last_message = device_->lastMessage();
  state_pub_.publish(s);

  visualization_msgs::Marker m;
  m.header.frame_id = frame_id_;
  m.header.stamp = stamp;
  m.ns = "afterloader_source";
  m.id = 0;
  m.type = visualization_msgs::Marker::SPHERE;
  m.pose.orientation.w = 1.0;
  // The source's tf is always published (at the frame origin while parked), so that the
  // patient frame exists for rviz before and after a delivery.
  const delivery::Point3 p =
      s.source_in_patient ? device_->sourcePosition() : delivery::Point3::Zero();
  geometry_msgs::TransformStamped t;
  t.header = m.header;
  t.child_frame_id = "afterloader_source";
  t.transform.translation.x = p.x();
  t.transform.translation.y = p.y();
  t.transform.translation.z = p.z();
  t.transform.rotation.w = 1.0;
  tf_.sendTransform(t);
  if (s.source_in_patient) {
    m.action = visualization_msgs::Marker::ADD;
    m.pose.position = ros_conversions::toPointMessage(p);
    m.scale.x = m.scale.y = m.scale.z = 0.003;
    m.color.r = 1.0f;
    m.color.g = s.dwell >= 0 ? 0.1f : 0.6f;
    m.color.a = 1.0f;
  } else {
    m.action = visualization_msgs::Marker::DELETE;
  }
  marker_pub_.publish(m);

  if (feedback && goal_) {
    DeliverFeedback f;
    f.state = s.state;
    f.channel = s.channel;
    f.dwell_index = s.dwell;
    f.elapsed_s = device_->time() - goal_start_time_s_;
    f.remaining_s = device_->remainingDwellTime();
    f.delivered_fraction = s.delivered_fraction;
    goal_->publishFeedback(f);
  }
}

bool AfterloaderRos::onPause(std_srvs::Trigger::Request&, std_srvs::Trigger::Response& res) {
  const auto st = device_->pause("operator");
  res.success = st.ok();
  res.message = st.ok() ? device_->lastMessage() : st.message();
  publish(true);
  return true;
}

bool AfterloaderRos::onResume(std_srvs::Trigger::Request&, std_srvs::Trigger::Response& res) {
  const auto st = device_->resume();
  res.success = st.ok();
  res.message = st.ok() ? device_->lastMessage() : st.message();
  publish(true);
  return true;
}

bool AfterloaderRos::onDoor(std_srvs::SetBool::Request& req, std_srvs::SetBool::Response& res) {
  device_->setDoorOpen(req.data);
  res.success = true;
  res.message = std::string("door ") + (req.data ? "open" : "closed") + "; " +
                delivery::toString(device_->state());
  publish(true);
  return true;
}

bool AfterloaderRos::onObstruction(SetChannelObstruction::Request& req,
                                   SetChannelObstruction::Response& res) {
  const auto st = device_->setObstruction(req.channel, req.obstructed);
  res.success = st.ok();
  res.message = st.ok() ? "channel " + std::to_string(req.channel) +
                              (req.obstructed ? " obstructed" : " clear")
                        : st.message();
  publish(true);
  return true;
}

}  // namespace needle_guidance
