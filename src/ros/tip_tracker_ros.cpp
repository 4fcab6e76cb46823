#include "needle_guidance/ros/tip_tracker_ros.h"
#include "needle_guidance/math.h"

#include <cv_bridge/cv_bridge.h>

#include <Eigen/Eigenvalues>

#include <cmath>
#include <opencv2/imgproc.hpp>
#include <stdexcept>

#include "needle_guidance/NeedleTip.h"
#include "needle_guidance/ros/params.h"

namespace needle_guidance {
namespace {

constexpr const char* kName = "tip_tracker";
constexpr double kThrottle_s = 5.0;
constexpr std::size_t kMaxBufferedDrives = 1000;
constexpr double kDebugTipRadius_px = 6.0;
constexpr double kDebugHeadingLength_px = 30.0;

NeedleTip toMessage(const imaging::TipEstimate& e, const std_msgs::Header& image_header) {
  NeedleTip msg;
  msg.header.stamp = image_header.stamp;
  msg.header.frame_id = "scene";
  msg.pose.x = e.tip.p_SceneTip.x();
  msg.pose.y = e.tip.p_SceneTip.y();
  msg.pose.theta = e.tip.theta_rad;
  msg.bevel = needle_model::toString(e.tip.bevel);
  msg.inserted_length_m = e.inserted_length_m;
  msg.source = imaging::toString(e.status);
  msg.confident = e.confident;
  for (int r = 0; r < 3; ++r) {
    for (int c = 0; c < 3; ++c) {
      msg.covariance[static_cast<std::size_t>(3 * r + c)] = e.covariance(r, c);
    }
  }
  return msg;
}

/// The frame in colour with the estimate drawn: green = confident, yellow = not; the detection
/// (if any) as a cyan cross; the status in the corner.
cv::Mat debugImage(const cv::Mat& frame, const imaging::TipEstimate& e,
                   const imaging::ImageGeometry& g) {
  cv::Mat bgr;
  if (frame.type() == CV_8UC1) {
    cv::cvtColor(frame, bgr, cv::COLOR_GRAY2BGR);
  } else {
    bgr = cv::Mat(g.size(), CV_8UC3, cv::Scalar(0, 0, 0));
  }
  const cv::Scalar colour = e.confident ? cv::Scalar(0, 220, 0) : cv::Scalar(0, 220, 255);
  const cv::Point2d tip = g.toPixel(e.tip.p_SceneTip);
  const cv::Point2d ahead(tip.x + kDebugHeadingLength_px * std::cos(e.tip.theta_rad),
                          tip.y - kDebugHeadingLength_px * std::sin(e.tip.theta_rad));
  cv::circle(bgr, tip, static_cast<int>(kDebugTipRadius_px), colour, 1, cv::LINE_AA);
  cv::line(bgr, tip, ahead, colour, 1, cv::LINE_AA);
  // One-sigma position ellipse.
  const Eigen::Matrix2d p = e.covariance.topLeftCorner<2, 2>();
  const Eigen::SelfAdjointEigenSolver<Eigen::Matrix2d> eig(p);
  if (eig.info() == Eigen::Success && eig.eigenvalues().minCoeff() >= 0.0) {
    const Eigen::Vector2d axis = eig.eigenvectors().col(1);
    const double angle_deg = std::atan2(-axis.y(), axis.x()) * 180.0 / kPi;
    cv::ellipse(bgr, tip,
                cv::Size2d(std::sqrt(eig.eigenvalues()(1)) / g.pixel_size_m + 1.0,
                           std::sqrt(eig.eigenvalues()(0)) / g.pixel_size_m + 1.0),
                angle_deg, 0.0, 360.0, colour, 1, cv::LINE_AA);
  }
  if (e.detection.found) {
    cv::drawMarker(bgr, g.toPixel(e.detection.p_SceneTip), cv::Scalar(255, 255, 0),
                   cv::MARKER_CROSS, 10, 1);
  }
  cv::putText(bgr, imaging::toString(e.status) + (e.confident ? " (confident)" : ""),
              cv::Point(8, 20), cv::FONT_HERSHEY_SIMPLEX, 0.5, colour, 1, cv::LINE_AA);
  return bgr;
}

}  // namespace

TipTrackerRos::TipTrackerRos(ros::NodeHandle& nh, ros::NodeHandle& private_nh) {
  ROS_INFO("tip_tracker parameters:");
  scene_ = scene::loadSceneSpec(ros_params::text(private_nh, "scene", "steering_workspace"));
  // Validate that the scene can be tracked now, with the scene's own imaging settings.
  settings_ = imaging::trackerConfigFromScene(scene_, imaging::imagerConfigFromScene(scene_));
  settings_.search_margin_m =
      ros_params::number(private_nh, "search_margin_m", settings_.search_margin_m, 0.0, 0.1, "m");
  settings_.gate_chi2 =
      ros_params::number(private_nh, "gate_chi2", settings_.gate_chi2, 1.0, 1e6, "");
  settings_.confident_position_std_m = ros_params::number(
      private_nh, "confident_position_std_m", settings_.confident_position_std_m, 1e-6, 0.1, "m");
  settings_.confident_heading_std_rad =
      ros_params::number(private_nh, "confident_heading_std_rad",
                         settings_.confident_heading_std_rad, 1e-4, 1.0, "rad");
  // drive: the robot's NeedleDrive predicts the tip (the image-guided loop); axis: no robot (a
  // bag, a recorded or freehand sequence): the needle is acquired without a prior and followed
  // along its own axis (SequenceTracker); auto (default): drive while the robot's drive is
  // available, axis otherwise, decided per frame (imaging::chooseMotionModel).
  const std::string model = ros_params::text(private_nh, "motion_model", "auto");
  const auto motion_model = imaging::motionModelFromString(model);
  if (!motion_model) {
    throw std::runtime_error("parameter " + private_nh.resolveName("motion_model") +
                             " must be auto, drive or axis, not '" + model + "'");
  }
  motion_model_ = *motion_model;
  if (motion_model_ != imaging::MotionModel::kDrive) {
    imaging::AcquisitionOptions options;
    const std::string entry = ros_params::text(private_nh, "entry", "auto");
    const auto side = imaging::entrySideFromString(entry);
    if (!side) {
      throw std::runtime_error("parameter " + private_nh.resolveName("entry") +
                               " must be auto, left, right, top or bottom, not '" + entry + "'");
    }
    options.entry = *side;
    // Priors (as track_frames --entry-point X,Y --entry-angle DEG): where the needle enters the
    // image [px] and roughly at what angle towards its tip [deg]; absent: worked out.
    if (private_nh.hasParam("entry_point_x_px") || private_nh.hasParam("entry_point_y_px")) {
      options.entry_point_px =
          cv::Point2d(ros_params::number(private_nh, "entry_point_x_px", 0.0, -1e4, 1e4, "px"),
                      ros_params::number(private_nh, "entry_point_y_px", 0.0, -1e4, 1e4, "px"));
    }
    if (private_nh.hasParam("entry_angle_deg")) {
      options.entry_angle_rad =
          ros_params::number(private_nh, "entry_angle_deg", 0.0, -360.0, 360.0, "deg") * kPi /
          180.0;
    }
    imaging::keepFreedMemory();
    // Needle model without a scene: straight, or an arc of ~radius_m (0 = straight).
    const double radius_m =
        ros_params::number(private_nh, "radius_m", 0.0, 0.0, 100.0, "m (0 = straight)");
    sequence_options_ = options;
    sequence_radius_m_ = radius_m;
    // Calibration as parameters (a recording without an ImageCalibration message); a message
    // on `calibration` replaces it. 0 = wait for the message.
    geometry_.pixel_size_m =
        ros_params::number(private_nh, "pixel_size_m", 0.0, 0.0, 0.01, "m (0 = from the message)");
    geometry_.origin_m =
        imaging::Point2(ros_params::number(private_nh, "origin_x_m", 0.0, -10.0, 10.0, "m"),
                        ros_params::number(private_nh, "origin_y_m", 0.0, -10.0, 10.0, "m"));
    resetSequence();
  }
  tip_pub_ = private_nh.advertise<NeedleTip>("tip", 10);
  debug_pub_ = private_nh.advertise<sensor_msgs::Image>("debug_image", 2);
  calibration_sub_ = nh.subscribe("calibration", 1, &TipTrackerRos::onCalibration, this);
  drive_sub_ = nh.subscribe("drive", 200, &TipTrackerRos::onDrive, this);
  image_sub_ = nh.subscribe("image", 5, &TipTrackerRos::onImage, this);
}

void TipTrackerRos::onCalibration(const ImageCalibrationConstPtr& msg) {
  imaging::TrackerConfig config = settings_;
  const auto modality = imaging::modalityFromString(msg->modality);
  if (!modality) {
    ROS_ERROR_STREAM_NAMED(kName, "tip_tracker: calibration refused: modality '"
                                      << msg->modality << "' is not ultrasound or fluoroscopy");
    return;
  }
  config.modality = *modality;
  config.geometry.origin_m = imaging::Point2(msg->origin_x_m, msg->origin_y_m);
  config.geometry.pixel_size_m = msg->pixel_size_m;
  config.geometry.cols = static_cast<int>(msg->width);
  config.geometry.rows = static_cast<int>(msg->height);
  if (motion_model_ != imaging::MotionModel::kDrive) {
    if (!(msg->pixel_size_m > 0.0) || !std::isfinite(msg->pixel_size_m) ||
        !std::isfinite(msg->origin_x_m) || !std::isfinite(msg->origin_y_m)) {
      ROS_ERROR_STREAM_NAMED(kName, "tip_tracker: calibration refused: pixel size "
                                        << msg->pixel_size_m << " m or origin not finite/positive");
      return;
    }
    const imaging::ImageGeometry previous = geometry_;
    geometry_ = config.geometry;
    try {
      resetSequence();  // the arc's radius in pixels follows the pixel size
    } catch (const std::invalid_argument& e) {
      geometry_ = previous;  // refused: the state before the message stays
      ROS_ERROR_STREAM_NAMED(kName, "tip_tracker: calibration refused: " << e.what());
      return;
    }
    ROS_INFO_STREAM_NAMED(kName,
                          "tip_tracker: calibration " << msg->pixel_size_m * 1e3 << " mm pixels");
    if (motion_model_ == imaging::MotionModel::kAxis) {
      return;
    }
  }
  try {
    auto tracker = std::make_unique<imaging::TipTracker>(config);
    tracker_ = std::move(tracker);  // the state before the new calibration is not kept
    have_entry_ = false;
    ROS_INFO_STREAM_NAMED(kName, "tip_tracker: calibration " << msg->modality << " " << msg->width
                                                             << " x " << msg->height << " px of "
                                                             << msg->pixel_size_m * 1e3 << " mm");
  } catch (const std::invalid_argument& e) {
    ROS_ERROR_STREAM_NAMED(kName, "tip_tracker: calibration refused: " << e.what());
  }
}

void TipTrackerRos::onDrive(const NeedleDriveConstPtr& msg) {
  drives_.push_back(*msg);
  if (drives_.size() > kMaxBufferedDrives) {
    drives_.pop_front();
  }
}

void TipTrackerRos::applyDrives(const ros::Time& stamp) {
  while (!drives_.empty() && drives_.front().header.stamp <= stamp) {
    const NeedleDrive d = drives_.front();
    drives_.pop_front();
    const auto bevel = needle_model::bevelFromString(d.bevel);
    if (!bevel || !std::isfinite(d.inserted_length_m) || !std::isfinite(d.entry.x) ||
        !std::isfinite(d.entry.y) || !std::isfinite(d.entry.theta)) {
      ROS_ERROR_STREAM_THROTTLE_NAMED(kThrottle_s, kName,
                                      "tip_tracker: drive message with bevel '"
                                          << d.bevel << "' or a non-finite value ignored");
      continue;
    }
    if (!have_entry_ || d.entry_id != entry_id_) {
      needle_model::TipPose entry;
      entry.p_SceneTip = imaging::Point2(d.entry.x, d.entry.y);
      entry.theta_rad = d.entry.theta;
      entry.bevel = *bevel;
      // The guide is where the robot put it; the bevel at the entry is the one before any flip.
      if (d.flips % 2 == 1) {
        entry.bevel = needle_model::flipped(*bevel);
      }
      tracker_->reset(entry);
      entry_id_ = d.entry_id;
      have_entry_ = true;
    }
    tracker_->onDrive(d.inserted_length_m, *bevel, d.flips);
    last_drive_ = d;
  }
}

void TipTrackerRos::onImageWithoutRobot(const sensor_msgs::ImageConstPtr& msg) {
  if (!(geometry_.pixel_size_m > 0.0)) {
    ROS_WARN_STREAM_THROTTLE_NAMED(kThrottle_s, kName,
                                   "tip_tracker: no calibration (message or ~pixel_size_m) yet; "
                                   "frame ignored");
    return;
  }
  cv::Mat frame;
  try {
    // Any depth and channel count cv_bridge can read; acquisition converts 8/16-bit mono or
    // colour to grey and refuses the rest with the reason.
    frame = cv_bridge::toCvShare(msg)->image;
  } catch (const std::exception& e) {
    ROS_WARN_STREAM_THROTTLE_NAMED(
        kThrottle_s, kName,
        "tip_tracker: image encoding '" << msg->encoding << "' unusable: " << e.what());
    return;
  }
  const imaging::SequenceTracker::Output out = sequence_->onFrame(frame);
  ++frames_;
  NeedleTip tip;
  tip.header.stamp = msg->header.stamp;
  tip.header.frame_id = "scene";
  if (!out.segment.found) {
    tip.source = "not_found";  // nothing usable: never a confident tip
    tip.pose.x = tip.pose.y = tip.pose.theta = std::nan("");
    tip_pub_.publish(tip);
    return;
  }
  const imaging::Point2 p = geometry_.toScene(out.segment.tip_px);
  tip.pose.x = p.x();
  tip.pose.y = p.y();
  tip.pose.theta = std::atan2(-std::sin(out.segment.angle_rad), std::cos(out.segment.angle_rad));
  tip.bevel = "";  // a recording does not tell the bevel
  tip.source = out.predicted ? "predicted" : "tracked";
  tip.confident = out.confident;
  // About 3 px of tip and 2 degrees of heading (one sigma), more when only predicted.
  const double s_px = out.predicted ? 9.0 : 3.0;
  const double s_m = s_px * geometry_.pixel_size_m;
  tip.covariance[0] = tip.covariance[4] = s_m * s_m;
  tip.covariance[8] = std::pow((out.predicted ? 6.0 : 2.0) * kPi / 180.0, 2);
  tip_pub_.publish(tip);
}

/// Throws std::invalid_argument (from AcquisitionOptions) for a radius too small for the pixels.
void TipTrackerRos::resetSequence() {
  imaging::AcquisitionOptions options = sequence_options_;
  if (sequence_radius_m_ > 0.0 && geometry_.pixel_size_m > 0.0) {
    options.radius_px = sequence_radius_m_ / geometry_.pixel_size_m;
  }
  sequence_ = std::make_unique<imaging::SequenceTracker>(options);
}

void TipTrackerRos::onImage(const sensor_msgs::ImageConstPtr& msg) {
  // One path: the drive model when the robot's drive is there, the axis model when it is not.
  const bool drive_available = have_entry_ || !drives_.empty() || drive_sub_.getNumPublishers() > 0;
  if (imaging::chooseMotionModel(motion_model_, drive_available) == imaging::MotionModel::kAxis) {
    onImageWithoutRobot(msg);
    return;
  }
  if (!tracker_) {
    ROS_WARN_STREAM_THROTTLE_NAMED(kThrottle_s, kName,
                                   "tip_tracker: no calibration yet; frame ignored");
    return;
  }
  applyDrives(msg->header.stamp);
  if (!have_entry_) {
    ROS_WARN_STREAM_THROTTLE_NAMED(kThrottle_s, kName,
                                   "tip_tracker: no needle guide pose from the robot yet; frame "
                                   "ignored");
    return;
  }
  cv::Mat frame;
  std::string encoding_error;
  try {
    frame = cv_bridge::toCvShare(msg)->image;  // as sent: the tracker checks size and type
  } catch (const std::exception& e) {
    encoding_error = e.what();
  }
  imaging::TipEstimate estimate = tracker_->onFrame(frame);
  if (!encoding_error.empty()) {
    estimate.message = "image encoding '" + msg->encoding + "' unusable: " + encoding_error;
  }
  ++frames_;
  if (estimate.status == imaging::TrackStatus::kBadFrame) {
    ROS_WARN_STREAM_THROTTLE_NAMED(kThrottle_s, kName, "tip_tracker: " << estimate.message);
  }
  tip_pub_.publish(toMessage(estimate, msg->header));
  if (debug_pub_.getNumSubscribers() > 0) {
    cv_bridge::CvImage debug(msg->header, "bgr8",
                             debugImage(frame, estimate, tracker_->config().geometry));
    debug_pub_.publish(debug.toImageMsg());
  }
}

}  // namespace needle_guidance
