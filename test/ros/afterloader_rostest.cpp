// rostest for the afterloader node (roslaunch respawns it): a full delivery, pause/resume, abort
// and resume, a catheter obstruction mid-dwell, the door interlock, refused schedules, and
// SIGKILL mid-delivery followed by a restart that resumes from the journal with exact totals.
#include <actionlib/client/simple_action_client.h>
#include <gtest/gtest.h>
#include <ros/network.h>
#include <ros/ros.h>
#include <std_srvs/SetBool.h>
#include <std_srvs/Trigger.h>
#include <unistd.h>
#include <xmlrpcpp/XmlRpcClient.h>

#include <csignal>
#include <filesystem>
#include <mutex>

#include "../ros_wait.h"
#include "needle_guidance/AfterloaderState.h"
#include "needle_guidance/DeliverAction.h"
#include "needle_guidance/SetChannelObstruction.h"
#include "needle_guidance/delivery/journal.h"
#include "needle_guidance/delivery/schedule.h"
#include "needle_guidance/ros/delivery_conversions.h"

namespace {

namespace ng = needle_guidance;
namespace delivery = needle_guidance::delivery;
using Client = actionlib::SimpleActionClient<ng::DeliverAction>;

constexpr double kExactS = 1e-9;       // [s] journal totals against the plan
constexpr double kQuantumS = 0.05;     // [s] the node's default commit quantum
constexpr double kSourceSpeed = 0.5;   // [m/s] the node's default
constexpr double kResultWaitS = 60.0;  // [s] wall time for one delivery at 10x

std::mutex g_mutex;
ng::AfterloaderState g_state;
int g_feedback = 0;
double g_last_fraction = 0.0;
bool g_fraction_decreased = false;

/// Three channels (2, 5, 7) along -z, tip at z = 0, 1 m transfer tube, 4 dwells every 5 mm.
delivery::Schedule schedule(const std::string& name) {
  delivery::Schedule s;
  s.plan_id =
      name + "_" + std::to_string(getpid()) + "_" + std::to_string(ros::WallTime::now().toNSec());
  s.plan_air_kerma_strength_U = s.current_air_kerma_strength_U = 40700.0;
  int n = 0;
  for (int ch : {2, 5, 7}) {
    delivery::ChannelSchedule c;
    c.channel = ch;
    c.catheter = "cath" + std::to_string(ch);
    c.transfer_length_m = 1.0;
    c.length_m = 1.08;
    c.path_m = {delivery::Point3(0.01 * ch, 0.0, 0.0), delivery::Point3(0.01 * ch, 0.0, -0.08)};
    for (int k = 0; k < 4; ++k) {
      c.dwell_index.push_back(k);
      c.distance_m.push_back(1.08 - 0.005 * k);
      c.time_s.push_back(1.5 + 0.25 * ((n++) % 5));
      c.position_m.push_back(c.sourcePosition(c.distance_m.back()));
    }
    s.channels.push_back(c);
  }
  return s;
}

ng::DeliverGoal goalOf(const delivery::Schedule& s) {
  ng::DeliverGoal g;
  g.schedule = ng::ros_conversions::toMessage(s, "patient");
  return g;
}

ng::AfterloaderState state() {
  std::lock_guard<std::mutex> lock(g_mutex);
  return g_state;
}

/// Waits until the source dwells and at least `fraction` of the plan is delivered.
bool waitDwelling(double fraction) {
  return waitFor(
      [&] {
        const auto s = state();
        return s.dwell >= 0 && s.delivered_fraction >= fraction;
      },
      30.0);
}

Client& client() {
  static Client c("afterloader/deliver", true);
  return c;
}

void send(const delivery::Schedule& s) {
  {
    std::lock_guard<std::mutex> lock(g_mutex);
    g_feedback = 0;
    g_last_fraction = 0.0;
    g_fraction_decreased = false;
  }
  client().sendGoal(goalOf(s), Client::SimpleDoneCallback(), Client::SimpleActiveCallback(),
                    [](const ng::DeliverFeedbackConstPtr& f) {
                      std::lock_guard<std::mutex> lock(g_mutex);
                      ++g_feedback;
                      if (f->delivered_fraction < g_last_fraction - 1e-12)
                        g_fraction_decreased = true;
                      g_last_fraction = f->delivered_fraction;
                    });
}

/// Every dwell of the result delivered exactly as planned.
void expectExact(const ng::DeliverResult& r, const delivery::Schedule& s) {
  ASSERT_EQ(r.delivered_s.size(), s.dwellCount());
  for (std::size_t k = 0; k < r.delivered_s.size(); ++k) {
    EXPECT_NEAR(r.delivered_s[k], r.planned_s[k], kExactS)
        << "channel " << r.channel[k] << " dwell " << r.dwell_index[k];
  }
}

/// Waits for the running goal's result; it must have completed with every dwell exact.
ng::DeliverResult expectCompleted(const delivery::Schedule& s) {
  EXPECT_TRUE(client().waitForResult(ros::Duration(kResultWaitS)));
  EXPECT_EQ(client().getState(), actionlib::SimpleClientGoalState::SUCCEEDED)
      << client().getState().getText();
  const ng::DeliverResult r = client().getResult() ? *client().getResult() : ng::DeliverResult{};
  EXPECT_EQ(r.status, "completed") << r.message;
  expectExact(r, s);
  return r;
}

std::string journalPath(const delivery::Schedule& s) {
  std::string dir;
  ros::NodeHandle("~").getParam("journal_dir", dir);
  return dir + "/" + s.plan_id + ".journal";
}

bool trigger(const std::string& name) {
  std_srvs::Trigger t;
  return ros::service::call("afterloader/" + name, t) && t.response.success;
}

bool door(bool open) {
  std_srvs::SetBool b;
  b.request.data = open;
  return ros::service::call("afterloader/set_door_open", b) && b.response.success;
}

bool obstruct(int channel, bool obstructed) {
  ng::SetChannelObstruction o;
  o.request.channel = channel;
  o.request.obstructed = obstructed;
  return ros::service::call("afterloader/set_obstruction", o) && o.response.success;
}

/// The afterloader's process id, asked from the node itself (what `rosnode info` does).

TEST(Afterloader, DeliversAScheduleExactly) {
  ASSERT_TRUE(client().waitForServer(ros::Duration(30.0)));
  const auto s = schedule("full");
  send(s);
  const auto r = expectCompleted(s);
  ASSERT_EQ(r.trips.size(), 3u);
  double transit = 0.0;
  for (const auto& c : s.channels)
    transit += delivery::tripTransitSeconds(c, kSourceSpeed);
  EXPECT_NEAR(r.transit_in_patient_s, transit, 1e-6);
  for (int t : r.trips)
    EXPECT_EQ(t, 1);
  std::lock_guard<std::mutex> lock(g_mutex);
  EXPECT_GE(g_feedback, 3);
  EXPECT_FALSE(g_fraction_decreased);
}

TEST(Afterloader, PauseHoldsTheDoseAndResumeCompletes) {
  const auto s = schedule("pause");
  send(s);
  ASSERT_TRUE(waitDwelling(0.2));
  ASSERT_TRUE(trigger("pause"));
  ASSERT_TRUE(waitFor([] { return !state().source_in_patient; }, 10.0)) << "source not retracted";
  const double held = state().delivered_fraction;
  ros::WallDuration(0.5).sleep();  // 5 s of device time
  EXPECT_EQ(state().state, "PAUSED");
  EXPECT_NEAR(state().delivered_fraction, held, 1e-12);
  ASSERT_TRUE(trigger("resume"));
  const auto r = expectCompleted(s);
  EXPECT_GE(r.interruptions, 1);
}

TEST(Afterloader, AbortStopsAndTheSameScheduleResumes) {
  const auto s = schedule("abort");
  send(s);
  ASSERT_TRUE(waitDwelling(0.3));
  client().cancelGoal();
  ASSERT_TRUE(client().waitForResult(ros::Duration(kResultWaitS)));
  EXPECT_EQ(client().getState(), actionlib::SimpleClientGoalState::PREEMPTED);
  auto r = *client().getResult();
  EXPECT_EQ(r.status, "aborted");
  double delivered = 0.0, planned = 0.0;
  for (std::size_t k = 0; k < r.delivered_s.size(); ++k) {
    delivered += r.delivered_s[k];
    planned += r.planned_s[k];
  }
  EXPECT_GT(delivered, 0.25 * planned);
  EXPECT_LT(delivered, planned - 1.0);
  send(s);
  expectCompleted(s);
  // A fully delivered plan is refused: nothing is delivered twice.
  send(s);
  ASSERT_TRUE(client().waitForResult(ros::Duration(10.0)));
  EXPECT_EQ(client().getState(), actionlib::SimpleClientGoalState::REJECTED);
  EXPECT_NE(client().getResult()->message.find("already fully delivered"), std::string::npos);
}

TEST(Afterloader, ObstructionMidDwellRetractsAndSkipsTheChannel) {
  const auto s = schedule("obstruction");
  send(s);
  ASSERT_TRUE(waitDwelling(0.1));
  const int channel = state().channel;
  ASSERT_GT(channel, 0);
  ASSERT_TRUE(obstruct(channel, true));
  ASSERT_TRUE(client().waitForResult(ros::Duration(kResultWaitS)));
  EXPECT_EQ(client().getState(), actionlib::SimpleClientGoalState::ABORTED);
  auto r = *client().getResult();
  EXPECT_EQ(r.status, "stopped");
  EXPECT_NE(r.message.find("channel(s) " + std::to_string(channel)), std::string::npos)
      << r.message;
  double short_s = 0.0;
  for (std::size_t k = 0; k < r.channel.size(); ++k) {
    if (r.channel[k] == channel)
      short_s += r.planned_s[k] - r.delivered_s[k];
    else
      EXPECT_NEAR(r.delivered_s[k], r.planned_s[k], kExactS)
          << "other channels are delivered in full";
  }
  EXPECT_GT(short_s, 1.0);
  ASSERT_TRUE(obstruct(channel, false));
  send(s);
  expectCompleted(s);
}

TEST(Afterloader, OpenDoorPausesAndBlocksResume) {
  const auto s = schedule("door");
  send(s);
  ASSERT_TRUE(waitDwelling(0.2));
  ASSERT_TRUE(door(true));
  EXPECT_TRUE(waitFor([] { return state().state == "PAUSED"; }, 5.0));
  EXPECT_FALSE(trigger("resume"));
  ASSERT_TRUE(door(false));
  ASSERT_TRUE(trigger("resume"));
  expectCompleted(s);
}

TEST(Afterloader, RefusesUnknownChannelsAndNegativeTimesBeforeAnythingMoves) {
  // The source of the test before may still be on its way home: start from the safe.
  ASSERT_TRUE(waitFor([] { return state().channel == 0; }, 10.0));
  auto s = schedule("unknown_channel");
  s.channels[1].channel = 99;
  send(s);
  ASSERT_TRUE(client().waitForResult(ros::Duration(10.0)));
  EXPECT_EQ(client().getState(), actionlib::SimpleClientGoalState::REJECTED);
  EXPECT_NE(client().getResult()->message.find("channel 99: unknown"), std::string::npos)
      << client().getResult()->message;
  EXPECT_FALSE(std::filesystem::exists(journalPath(s)));
  s = schedule("negative_time");
  s.channels[2].time_s[1] = -1.0;
  send(s);
  ASSERT_TRUE(client().waitForResult(ros::Duration(10.0)));
  EXPECT_EQ(client().getState(), actionlib::SimpleClientGoalState::REJECTED);
  EXPECT_NE(client().getResult()->message.find("time -1"), std::string::npos)
      << client().getResult()->message;
  EXPECT_FALSE(std::filesystem::exists(journalPath(s)));
  EXPECT_EQ(state().channel, 0);  // nothing moved
}

TEST(Afterloader, SigkillMidDwellThenRestartResumesWithExactTotals) {
  const auto s = schedule("sigkill");
  send(s);
  ASSERT_TRUE(waitDwelling(0.4));
  const int pid = nodePid("/afterloader");
  ASSERT_GT(pid, 0);
  ASSERT_EQ(::kill(pid, SIGKILL), 0);
  // roslaunch respawns the node; its first latched state comes from the new process.
  ASSERT_TRUE(waitFor(
      [&] {
        const int p = nodePid("/afterloader");
        return p > 0 && p != pid;
      },
      30.0));
  ASSERT_TRUE(client().waitForServer(ros::Duration(30.0)));
  ros::WallDuration(1.0).sleep();  // let the goal topic connect to the new server
  send(s);
  const auto r = expectCompleted(s);
  // The journal itself: complete, consistent, and the crash left at most one quantum in doubt.
  const delivery::Journal journal(journalPath(s));
  const auto ledger = delivery::replay(journal.records(), &s, kSourceSpeed);
  EXPECT_TRUE(ledger.completed);
  EXPECT_TRUE(ledger.anomalies.empty());
  EXPECT_EQ(ledger.seq_gaps, 0);
  EXPECT_GE(ledger.interruptions, 1);
  double doubt = 0.0;
  for (const auto& [key, u] : ledger.uncertainty_s)
    doubt += u;
  EXPECT_LE(doubt, kQuantumS + kExactS);
  for (const auto& c : s.channels) {
    for (std::size_t k = 0; k < c.time_s.size(); ++k) {
      EXPECT_NEAR(ledger.delivered_s.at({c.channel, c.dwell_index[k]}), c.time_s[k], kExactS);
    }
  }
}

}  // namespace

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  ros::init(argc, argv, "afterloader_rostest");
  ros::NodeHandle nh;
  const boost::function<void(const ng::AfterloaderStateConstPtr&)> on_state =
      [](const ng::AfterloaderStateConstPtr& m) {
        std::lock_guard<std::mutex> lock(g_mutex);
        g_state = *m;
      };
  ros::Subscriber sub = nh.subscribe<ng::AfterloaderState>("afterloader/state", 10, on_state);
  ros::AsyncSpinner spinner(2);
  spinner.start();
  const int code = RUN_ALL_TESTS();
  ros::shutdown();
  return code;
}
