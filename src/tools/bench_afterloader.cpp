// Fault campaign of the afterloader: seeded HDR deliveries by the real afterloader node
// (its own roscore, the node started as a process) with random SIGKILLs of the node (restarted
// and resumed from its journal), operator pauses, aborts followed by a resume, door-open and
// catheter-obstruction interlocks. Every delivery must complete or stop safely; the journals
// are checked afterwards: dwell-time error bound per dwell, double deliveries, journal lines the
// node published that are not in its file. Also the commit-quantum trade-off (core only): journal
// writes and wall time against the worst-case dwell-time error a crash can leave.
// Usage: bench_afterloader --out DIR [--quick]
#include <actionlib/client/simple_action_client.h>
#include <fcntl.h>
#include <ros/ros.h>
#include <signal.h>
#include <std_msgs/String.h>
#include <std_srvs/SetBool.h>
#include <std_srvs/Trigger.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <map>
#include <mutex>
#include <random>
#include <set>
#include <sstream>

#include "needle_guidance/AfterloaderState.h"
#include "needle_guidance/DeliverAction.h"
#include "needle_guidance/SetChannelObstruction.h"
#include "needle_guidance/delivery/afterloader.h"
#include "needle_guidance/delivery/journal.h"
#include "needle_guidance/delivery/schedule.h"
#include "needle_guidance/procedures/hdr_pipeline.h"
#include "needle_guidance/report/bench_args.h"
#include "needle_guidance/report/statistics.h"
#include "needle_guidance/report/table.h"
#include "needle_guidance/ros/delivery_conversions.h"

namespace ng = needle_guidance;
namespace delivery = ng::delivery;
namespace fs = std::filesystem;
using Client = actionlib::SimpleActionClient<ng::DeliverAction>;

namespace {

constexpr double kSpeed = 0.5;         // [m/s] source speed (node default)
constexpr double kTimeScale = 100.0;   // device seconds per wall second in the campaign
constexpr double kQuantum = 0.05;      // [s] the node's default commit quantum
constexpr double kTargetErrorS = 0.1;  // [s] bound on the dwell-time error
// [s] two kills in one dwell leave two quanta of doubt (0.1 s), which a floating-point sum may
// exceed in the last bit
constexpr double kTimeSumRoundingS = 1e-9;

double now() {
  return std::chrono::duration<double>(std::chrono::steady_clock::now().time_since_epoch()).count();
}

/// Starts a process with its output appended to `log`; returns its pid.
pid_t spawn(const std::vector<std::string>& argv, const std::string& log) {
  const pid_t pid = fork();
  if (pid == 0) {
    setpgid(0, 0);
    const int fd = ::open(log.c_str(), O_WRONLY | O_CREAT | O_APPEND, 0644);
    if (fd >= 0) {
      dup2(fd, 1);
      dup2(fd, 2);
    }
    std::vector<char*> args;
    for (const auto& a : argv)
      args.push_back(const_cast<char*>(a.c_str()));
    args.push_back(nullptr);
    execvp(args[0], args.data());
    _exit(127);
  }
  return pid;
}

void stop(pid_t pid, int sig) {
  if (pid <= 0)
    return;
  ::kill(pid, sig);
  for (int i = 0; i < 500; ++i) {
    if (waitpid(pid, nullptr, WNOHANG) == pid)
      return;
    usleep(10000);
  }
  ::kill(pid, SIGKILL);
  waitpid(pid, nullptr, 0);
}

/// Every journal line the node published, by plan (the campaign's independent witness).
std::mutex g_mutex;
std::string g_plan;
std::map<std::string, std::vector<std::string>> g_published;
ng::AfterloaderState g_state;
double g_fraction = 0.0;

ng::AfterloaderState state() {
  std::lock_guard<std::mutex> lock(g_mutex);
  return g_state;
}

struct Outcome {
  int faults = 0, kills = 0, pauses = 0, aborts = 0, doors = 0, obstructions = 0;
  std::string status = "none";
  bool safe = false;
  double wall_s = 0.0;
};

class Campaign {
public:
  Campaign(std::string node_binary, std::string journal_dir, std::string log)
      : binary_(std::move(node_binary)),
        journal_dir_(std::move(journal_dir)),
        log_(std::move(log)) {}
  ~Campaign() { stop(node_, SIGINT); }

  void startNode() {
    node_ =
        spawn({binary_, "__name:=afterloader", "_time_scale:=" + std::to_string(kTimeScale),
               "_journal_dir:=" + journal_dir_, "_commit_quantum_s:=" + std::to_string(kQuantum)},
              log_);
    client_ = std::make_unique<Client>("afterloader/deliver", true);
    if (!client_->waitForServer(ros::Duration(30.0)))
      throw std::runtime_error("afterloader did not come up");
    ros::WallDuration(0.3).sleep();
  }

  void killNode() {
    stop(node_, SIGKILL);
    node_ = -1;
    client_.reset();
  }

  void send(const delivery::Schedule& s) {
    {
      std::lock_guard<std::mutex> lock(g_mutex);
      g_plan = s.plan_id;
    }
    ng::DeliverGoal goal;
    goal.schedule = ng::ros_conversions::toMessage(s, "patient");
    client_->sendGoal(goal, {}, {}, [](const ng::DeliverFeedbackConstPtr& f) {
      std::lock_guard<std::mutex> lock(g_mutex);
      g_fraction = f->delivered_fraction;
    });
  }

  /// Waits for the delivered fraction to reach f (or the goal to end); false if it ended.
  bool waitFraction(double f) {
    const double end = now() + 120.0;
    while (now() < end) {
      if (client_->getState().isDone())
        return false;
      {
        std::lock_guard<std::mutex> lock(g_mutex);
        if (g_fraction >= f)
          return true;
      }
      usleep(2000);
    }
    return false;
  }

  std::string waitResult() {
    if (!client_->waitForResult(ros::Duration(300.0)))
      return "timeout";
    const auto r = client_->getResult();
    return r ? r->status : "none";
  }

  Outcome deliver(const delivery::Schedule& s, std::mt19937& rng) {
    Outcome o;
    const double t0 = now();
    std::uniform_int_distribution<int> count(1, 3), kind(0, 4);
    std::uniform_real_distribution<double> at(0.05, 0.95), jitter(0.0, 0.05);
    std::vector<std::pair<double, int>> faults;
    for (int k = count(rng); k > 0; --k)
      faults.emplace_back(at(rng), kind(rng));
    std::sort(faults.begin(), faults.end());
    {
      std::lock_guard<std::mutex> lock(g_mutex);
      g_fraction = 0.0;
    }
    send(s);
    for (const auto& [fraction, what] : faults) {
      if (!waitFraction(fraction))
        break;
      ros::WallDuration(jitter(rng)).sleep();  // land anywhere: dwelling or in transit
      ++o.faults;
      std_srvs::Trigger t;
      if (what == 0) {  // SIGKILL, restart, resend: resumes from the journal
        ++o.kills;
        killNode();
        startNode();
        send(s);
      } else if (what == 1) {  // operator pause
        ++o.pauses;
        ros::service::call("afterloader/pause", t);
        ros::WallDuration(jitter(rng) * 4.0).sleep();
        ros::service::call("afterloader/resume", t);
      } else if (what == 2) {  // abort, then deliver the same plan again
        ++o.aborts;
        client_->cancelGoal();
        waitResult();
        send(s);
      } else if (what == 3) {  // door opened and closed, then resume
        ++o.doors;
        std_srvs::SetBool b;
        b.request.data = true;
        ros::service::call("afterloader/set_door_open", b);
        ros::WallDuration(jitter(rng) * 4.0).sleep();
        b.request.data = false;
        ros::service::call("afterloader/set_door_open", b);
        ros::service::call("afterloader/resume", t);
      } else {  // obstruction of the channel the source is in (or the next one)
        ++o.obstructions;
        int channel = state().channel;
        if (channel == 0)
          channel = s.channels.back().channel;
        ng::SetChannelObstruction ob;
        ob.request.channel = channel;
        ob.request.obstructed = true;
        ros::service::call("afterloader/set_obstruction", ob);
        const std::string st = waitResult();
        ob.request.obstructed = false;
        ros::service::call("afterloader/set_obstruction", ob);
        if (st == "stopped")
          send(s);  // the rest of the obstructed channel, once cleared
      }
    }
    o.status = waitResult();
    const auto st = state();
    o.safe = st.channel == 0 && !st.source_in_patient;
    o.wall_s = now() - t0;
    return o;
  }

private:
  std::string binary_, journal_dir_, log_;
  pid_t node_ = -1;
  std::unique_ptr<Client> client_;
};

/// The worst dwell-time error the journal allows, over the scheduled dwells: |recorded - plan|
/// plus the committed quanta a crash left in doubt; and the dwells recorded above their plan.
struct ErrorBound {
  double worst_s = 0.0;
  int over_plan = 0;
};
ErrorBound errorBound(const delivery::Ledger& ledger, const delivery::Schedule& s) {
  ErrorBound b;
  for (const auto& c : s.channels) {
    for (std::size_t k = 0; k < c.time_s.size(); ++k) {
      const std::pair<int, int> key{c.channel, c.dwell_index[k]};
      const double got = ledger.delivered_s.count(key) ? ledger.delivered_s.at(key) : 0.0;
      const double doubt = ledger.uncertainty_s.count(key) ? ledger.uncertainty_s.at(key) : 0.0;
      b.worst_s = std::max(b.worst_s, std::abs(got - c.time_s[k]) + doubt);
      if (got > c.time_s[k] + 1e-9)
        ++b.over_plan;
    }
  }
  return b;
}

/// The commit quantum's trade (core only, no ROS): one delivery of `s` with crashes at
/// `crashes` random moments; journal records, wall time and the worst dwell-time error left.
struct QuantumRow {
  double quantum_s, wall_s, records, device_s_per_wall_s, max_error_bound_s;
};
QuantumRow quantumTrial(const delivery::Schedule& s, double quantum, int crashes,
                        const std::string& dir) {
  fs::remove_all(dir);
  fs::create_directories(dir);
  delivery::AfterloaderConfig config;
  config.journal_dir = dir;
  config.commit_quantum_s = quantum;
  std::mt19937 rng(11);
  const double device_total = s.totalDwellTime();
  std::uniform_real_distribution<double> when(0.0, device_total);
  std::vector<double> crash_at;
  for (int k = 0; k < crashes; ++k)
    crash_at.push_back(when(rng));
  std::sort(crash_at.begin(), crash_at.end());
  const double t0 = now();
  double device_time = 0.0;
  std::size_t next_crash = 0;
  for (int session = 0; session < crashes + 2; ++session) {
    delivery::Afterloader a(config);
    if (!a.start(s).ok())
      break;
    while (a.state() == delivery::DeliveryState::kDelivering || a.sourceChannel() != 0) {
      a.step(0.01);
      device_time += 0.01;
      if (next_crash < crash_at.size() && a.deliveredTotal() >= crash_at[next_crash]) {
        ++next_crash;
        break;  // destroyed mid-delivery, as by SIGKILL
      }
    }
  }
  const double wall = now() - t0;
  const delivery::Journal journal(dir + "/" + s.plan_id + ".journal");
  const auto ledger = delivery::replay(journal.records(), &s, kSpeed);
  const double worst = errorBound(ledger, s).worst_s;
  return {quantum, wall, static_cast<double>(journal.records().size()), device_time / wall, worst};
}

/// Schedules of synthetic cases 1..n planned by LP (the same pipeline as dwell_scheduler).
std::vector<delivery::Schedule> casePlans(int cases) {
  std::vector<delivery::Schedule> plans;
  ng::procedures::SourceCache sources;
  for (int c = 1; c <= cases; ++c) {
    ng::procedures::HdrCaseInput input;
    input.synthetic_seed = c;
    plans.push_back(ng::procedures::planHdr(ng::procedures::loadHdrCase(input),
                                            "case" + std::to_string(c), {}, sources)
                        .schedule);
    std::cout << "[bench] case " << c << ": " << plans.back().dwellCount() << " dwells, "
              << plans.back().totalDwellTime() << " s in " << plans.back().channels.size()
              << " channels\n";
  }
  return plans;
}

}  // namespace

int main(int argc, char** argv) {
  const auto args = ng::report::parseBenchArgs(argc, argv, "bench_afterloader");
  if (!args)
    return 2;
  const int deliveries = args->quick ? 10 : 50;
  const int cases = 5;
  const std::string out =
      fs::absolute(args->out_dir).string();  // the node resolves relative paths against ROS_HOME
  const std::string journal_dir = out + "/journal";
  fs::remove_all(journal_dir);
  fs::create_directories(journal_dir);

  const std::vector<delivery::Schedule> plans = casePlans(cases);

  // 1. Commit quantum: journal writes and speed against the error a crash can leave (core).
  ng::report::Table quantum(
      {"quantum_s", "wall_s", "journal_records", "device_s_per_wall_s", "max_error_bound_s"});
  for (double q : {0.01, 0.02, 0.05, 0.1}) {
    const auto row = quantumTrial(plans[0], q, 10, out + "/quantum_journal");
    quantum.addRow(
        {row.quantum_s, row.wall_s, row.records, row.device_s_per_wall_s, row.max_error_bound_s});
    std::cout << "[bench] quantum " << q << " s: " << row.records << " records, " << row.wall_s
              << " s wall, " << row.device_s_per_wall_s
              << " device s per wall s, worst error bound " << row.max_error_bound_s << " s\n";
  }
  fs::remove_all(out + "/quantum_journal");
  quantum.writeCsv(out + "/quantum.csv");

  // 2. The campaign against the real node.
  const int port = 11900 + static_cast<int>(getpid() % 90);
  const std::string master = "http://localhost:" + std::to_string(port);
  setenv("ROS_MASTER_URI", master.c_str(), 1);
  const std::string log = out + "/processes.log";
  fs::remove(log);
  const pid_t roscore = spawn({"roscore", "-p", std::to_string(port)}, log);
  ros::init(argc, argv, "afterloader_campaign", ros::init_options::NoSigintHandler);
  for (int i = 0; i < 300 && !ros::master::check(); ++i)
    usleep(100000);
  if (!ros::master::check()) {
    std::cerr << "bench_afterloader: roscore did not start on " << master << "\n";
    stop(roscore, SIGINT);
    return 1;
  }
  int exit_code = 0;
  {
    ros::NodeHandle nh;
    ros::Subscriber journal_sub =
        nh.subscribe<std_msgs::String>("afterloader/journal", 100000,
                                       boost::function<void(const std_msgs::String::ConstPtr&)>(
                                           [](const std_msgs::String::ConstPtr& m) {
                                             std::lock_guard<std::mutex> lock(g_mutex);
                                             g_published[g_plan].push_back(m->data);
                                           }));
    ros::Subscriber state_sub = nh.subscribe<ng::AfterloaderState>(
        "afterloader/state", 10,
        boost::function<void(const ng::AfterloaderState::ConstPtr&)>(
            [](const ng::AfterloaderState::ConstPtr& m) {
              std::lock_guard<std::mutex> lock(g_mutex);
              g_state = *m;
            }));
    ros::AsyncSpinner spinner(2);
    spinner.start();
    const std::string binary =
        fs::read_symlink("/proc/self/exe").parent_path().string() + "/afterloader";
    Campaign campaign(binary, journal_dir, log);
    campaign.startNode();

    ng::report::Table table({"delivery", "case", "dwells", "planned_s", "faults", "kills", "pauses",
                             "aborts", "doors", "obstructions", "status", "stopped_safely",
                             "max_dwell_error_s", "double_delivered", "lost_entries",
                             "journal_records", "wall_s"});
    int completed = 0, safe = 0, faults = 0, kills = 0, doubles = 0, lost = 0;
    double max_error = 0.0;
    std::vector<double> wall;
    for (int d = 0; d < deliveries; ++d) {
      std::mt19937 rng(1000 + d);
      delivery::Schedule s = plans[d % cases];
      s.plan_id = "campaign_" + std::to_string(d);
      const Outcome o = campaign.deliver(s, rng);
      ros::WallDuration(0.2).sleep();  // the last published journal lines arrive
      // The journal, replayed independently of the node.
      const delivery::Journal journal(journal_dir + "/" + s.plan_id + ".journal");
      const auto ledger = delivery::replay(journal.records(), &s, kSpeed);
      const ErrorBound bound = errorBound(ledger, s);
      const double worst = bound.worst_s;
      const int doubled = static_cast<int>(ledger.anomalies.size()) + bound.over_plan;
      std::set<std::string> in_file;
      {
        std::ifstream in(journal.path());
        for (std::string line; std::getline(in, line);)
          in_file.insert(line);
      }
      int missing = static_cast<int>(ledger.seq_gaps);
      {
        std::lock_guard<std::mutex> lock(g_mutex);
        for (const auto& line : g_published[s.plan_id])
          missing += in_file.count(line) ? 0 : 1;
      }
      // Completed per the journal (a kill just after the last dwell makes the resent goal
      // "refused: already fully delivered", which is right).
      const bool done = ledger.completed;
      completed += done;
      safe += done || o.safe;
      faults += o.faults;
      kills += o.kills;
      doubles += doubled;
      lost += missing;
      max_error = std::max(max_error, worst);
      wall.push_back(o.wall_s);
      table.addRow({double(d), double(d % cases + 1), double(s.dwellCount()), s.totalDwellTime(),
                    double(o.faults), double(o.kills), double(o.pauses), double(o.aborts),
                    double(o.doors), double(o.obstructions), o.status, double(o.safe), worst,
                    double(doubled), double(missing), double(journal.records().size()), o.wall_s});
      std::cout << "[bench] delivery " << d << ": " << o.status << ", " << o.faults << " faults ("
                << o.kills << " kills), max dwell error " << worst << " s, " << doubled
                << " doubled, " << missing << " lost, " << o.wall_s << " s\n";
    }
    table.writeCsv(out + "/afterloader.csv");
    std::ostringstream json;
    json << "{\n  \"deliveries\": " << deliveries << ",\n  \"faults_injected\": " << faults
         << ",\n  \"max_dwell_time_error_s\": " << max_error
         << ",\n  \"double_delivered_dwells\": " << doubles
         << ",\n  \"lost_journal_entries\": " << lost << ",\n  \"completed\": " << completed
         << ",\n  \"completed_or_stopped_safely\": " << safe << ",\n  \"process_kills\": " << kills
         << ",\n  \"time_scale\": " << kTimeScale << ",\n  \"commit_quantum_s\": " << kQuantum
         << ",\n  \"delivery_wall_s_median\": " << ng::report::median(wall)
         << ",\n  \"target_met\": "
         << (safe == deliveries && max_error <= kTargetErrorS + kTimeSumRoundingS && doubles == 0 &&
                     lost == 0
                 ? "true"
                 : "false")
         << "\n}\n";
    ng::report::writeTextFile(out + "/summary.json", json.str());
    ng::report::writeTextFile(
        out + "/plot.json",
        R"json([{"csv": "quantum.csv", "x": "wall_s", "y": "max_error_bound_s", "annotate": "quantum_s",
  "title": "Commit quantum (labels, s): wall time vs worst dwell error, 10 crashes", "png": "quantum.png"},
 {"csv": "afterloader.csv", "x": "faults", "y": "max_dwell_error_s", "points": true, "annotate": "kills",
  "title": "Fault campaign: dwell error bound per delivery (labels: kills)", "png": "afterloader.png"}]
)json");
    if (safe != deliveries)
      exit_code = 1;
  }
  ros::shutdown();
  stop(roscore, SIGINT);
  return exit_code;
}
