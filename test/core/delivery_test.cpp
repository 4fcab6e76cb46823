// HDR delivery: schedule (decay, distances from the indexer), journal (CRC, torn tail) and the
// simulated afterloader (full delivery, pause, abort, interlocks, crashes at random moments).
#include <gtest/gtest.h>

#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <random>

#include "needle_guidance/delivery/afterloader.h"
#include "needle_guidance/delivery/journal.h"
#include "needle_guidance/delivery/schedule.h"
#include "needle_guidance/dose/prostate_case.h"
#include "needle_guidance/procedures/hdr_report.h"

using namespace needle_guidance::delivery;
namespace fs = std::filesystem;

namespace {

constexpr double kExactS = 1e-9;     // [s] bookkeeping that must be exact up to round-off
constexpr double kPositionM = 1e-9;  // [m]

struct TempDir {
  fs::path path;
  TempDir() {
    char tmpl[] = "/tmp/ng_delivery_XXXXXX";
    path = mkdtemp(tmpl);
  }
  ~TempDir() { fs::remove_all(path); }
};

/// Two channels along +z, transfer tube 1 m, dwells every 5 mm from 2 cm into the patient.
Schedule smallSchedule(const std::string& id = "test_plan") {
  Schedule s;
  s.plan_id = id;
  s.plan_air_kerma_strength_U = s.current_air_kerma_strength_U = 40700.0;
  for (int ch = 1; ch <= 2; ++ch) {
    ChannelSchedule c;
    c.channel = ch + 2;
    c.catheter = "c" + std::to_string(ch);
    c.transfer_length_m = 1.0;
    c.length_m = 1.06;
    c.path_m = {Point3(0.01 * ch, 0, 0.0), Point3(0.01 * ch, 0, -0.06)};
    for (int k = 0; k < 3; ++k) {
      c.dwell_index.push_back(k);
      c.distance_m.push_back(1.06 - 0.005 * k);
      c.time_s.push_back(1.0 + 0.5 * k + ch);
      c.position_m.push_back(c.sourcePosition(c.distance_m.back()));
    }
    s.channels.push_back(c);
  }
  return s;
}

AfterloaderConfig config(const TempDir& dir, double quantum = 0.05) {
  AfterloaderConfig c;
  c.journal_dir = dir.path.string();
  c.commit_quantum_s = quantum;
  return c;
}

void runToEnd(Afterloader& a, double dt = 0.013) {
  for (int i = 0; i < 100000 && (a.state() == DeliveryState::kDelivering || a.sourceChannel() != 0);
       ++i)
    a.step(dt);
}

void expectDeliveredAsPlanned(const Ledger& l, const Schedule& s, double tolerance_s) {
  for (const auto& c : s.channels) {
    for (std::size_t k = 0; k < c.time_s.size(); ++k) {
      const auto it = l.delivered_s.find({c.channel, c.dwell_index[k]});
      ASSERT_NE(it, l.delivered_s.end()) << "channel " << c.channel << " dwell " << k;
      EXPECT_NEAR(it->second, c.time_s[k], tolerance_s)
          << "channel " << c.channel << " dwell " << k;
    }
  }
}

}  // namespace

TEST(Schedule, Ir192DecaysByHalfInOneHalfLife) {
  EXPECT_NEAR(ir192DecayFactor(kIr192HalfLifeDays), 0.5, 1e-12);
  EXPECT_NEAR(ir192DecayFactor(0.0), 1.0, 1e-15);
  EXPECT_THROW(ir192DecayFactor(-1.0), std::invalid_argument);
  EXPECT_THROW(ir192DecayFactor(std::nan("")), std::invalid_argument);
}

TEST(Schedule, ParsesUtcDatesAndRefusesBadOnes) {
  // Reference values from Python's datetime (UTC).
  EXPECT_DOUBLE_EQ(parseUtcSeconds("2026-11-22"), 1795305600.0);
  EXPECT_DOUBLE_EQ(parseUtcSeconds("2024-02-29T13:45:10"), 1709214310.0);
  EXPECT_DOUBLE_EQ(parseUtcSeconds("2024-02-29T13:45"), 1709214300.0);
  for (const char* bad :
       {"2026-13-01", "2026-02-30", "2026-11-22x", "22/11/2026", "", "2026-11-22T25:00"}) {
    EXPECT_THROW(parseUtcSeconds(bad), std::invalid_argument) << bad;
  }
}

TEST(Schedule, SyntheticCaseChannelsDistancesAndDecay) {
  needle_guidance::dose::SyntheticCaseOptions o;
  o.seed = 3;
  const auto c = needle_guidance::dose::syntheticProstateCase(o);
  std::vector<double> times(c.dwells.size(), 2.0);
  ScheduleOptions so;
  so.calibration_air_kerma_strength_U = c.air_kerma_strength_U;
  so.days_since_calibration = kIr192HalfLifeDays;  // half the strength: twice the time
  const Schedule s = makeSchedule(c, times, "case3", so);
  ASSERT_EQ(s.channels.size(), c.catheters.size());
  EXPECT_EQ(s.dwellCount(), c.dwells.size());
  EXPECT_NEAR(s.totalDwellTime(), 4.0 * c.dwells.size(), 1e-9);
  EXPECT_TRUE(validateSchedule(s, DeviceLimits{}).empty());
  for (const auto& ch : s.channels) {
    for (std::size_t k = 0; k < ch.time_s.size(); ++k) {
      // The source at the scheduled distance is at the dwell position.
      EXPECT_LT((ch.sourcePosition(ch.distance_m[k]) - ch.position_m[k]).norm(), 1e-7);
      EXPECT_GT(ch.distance_m[k], ch.transfer_length_m);
      if (k > 0) {
        EXPECT_LT(ch.distance_m[k], ch.distance_m[k - 1]);
      }
    }
    EXPECT_GT(tripTransitSeconds(ch, 0.5), 0.0);
  }
  // Negative time, wrong count and a dead source are refused.
  times[5] = -1.0;
  EXPECT_THROW(makeSchedule(c, times, "x"), std::invalid_argument);
  EXPECT_THROW(makeSchedule(c, std::vector<double>(3, 1.0), "x"), std::invalid_argument);
  so.days_since_calibration = 600.0;  // 0.36 % left
  EXPECT_THROW(makeSchedule(c, std::vector<double>(c.dwells.size(), 1.0), "x", so),
               std::invalid_argument);
}

TEST(Schedule, TransitSamplesAddUpToTheTripTime) {
  const Schedule s = smallSchedule();
  const auto& c = s.channels[0];
  const auto samples = tripTransitSamples(c, 0.5, 1e-3);
  double t = 0.0;
  for (const auto& x : samples)
    t += x.time_s;
  EXPECT_NEAR(t, tripTransitSeconds(c, 0.5), kExactS);
  EXPECT_NEAR(tripTransitSeconds(c, 0.5), 2.0 * 0.06 / 0.5, kExactS);  // 6 cm in and out at 0.5 m/s
}

TEST(Schedule, ValidationNamesEveryProblem) {
  Schedule s = smallSchedule();
  EXPECT_TRUE(validateSchedule(s, DeviceLimits{}).empty());
  s.channels[0].channel = 19;
  s.channels[1].time_s[1] = -0.5;
  const auto problems = validateSchedule(s, DeviceLimits{});
  ASSERT_EQ(problems.size(), 2u);
  EXPECT_NE(problems[0].find("channel 19: unknown"), std::string::npos) << problems[0];
  EXPECT_NE(problems[1].find("dwell 1: time -0.5"), std::string::npos) << problems[1];
  s = smallSchedule("../etc/passwd");
  EXPECT_FALSE(validateSchedule(s, DeviceLimits{}).empty());
  s = smallSchedule();
  s.channels[0].distance_m.pop_back();
  EXPECT_FALSE(validateSchedule(s, DeviceLimits{}).empty());
}

TEST(Journal, RecordsSurviveReopenAndATornTailIsCut) {
  TempDir dir;
  const std::string path = (dir.path / "j.journal").string();
  {
    Journal j(path);
    j.append({0, 0.0, "begin", 0, -1, 0.0, "p 0 1 1"});
    j.append({0, 0.0, "commit", 3, 2, 0.05, ""});
  }
  {  // A crash mid-write leaves half a line.
    std::ofstream out(path, std::ios::app);
    out << "3,1795305600.0,commit,3,2,0.1";
  }
  Journal j(path);
  ASSERT_EQ(j.records().size(), 2u);
  EXPECT_GT(j.tornTailBytes(), 0u);
  EXPECT_EQ(j.records()[1].kind, "commit");
  EXPECT_DOUBLE_EQ(j.records()[1].value, 0.05);
  j.append({0, 0.0, "commit", 3, 2, 0.1, ""});
  EXPECT_EQ(j.records().back().seq, 3);
  EXPECT_EQ(Journal(path).records().size(), 3u);  // the cut tail does not come back

  // A damaged record followed by others is not a torn tail: refuse to trust the file.
  std::string text;
  {
    std::ifstream in(path);
    text.assign(std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>());
  }
  text[text.find("commit")] = 'k';
  std::ofstream(path, std::ios::trunc) << text;
  EXPECT_THROW(Journal{path}, std::runtime_error);
  EXPECT_FALSE(parseRecord("1,2,commit,3,2,0.1,,deadbeef").has_value());
}

TEST(Afterloader, DeliversEveryDwellExactlyAndRecordsTransit) {
  TempDir dir;
  Afterloader a(config(dir));
  const Schedule s = smallSchedule();
  ASSERT_TRUE(a.start(s).ok());
  runToEnd(a);
  EXPECT_EQ(a.state(), DeliveryState::kCompleted);
  EXPECT_EQ(a.sourceChannel(), 0);
  const Ledger l = a.ledger();
  EXPECT_TRUE(l.completed);
  EXPECT_TRUE(l.anomalies.empty());
  expectDeliveredAsPlanned(l, s, kExactS);
  EXPECT_EQ(l.trips.at(3), 1);
  EXPECT_EQ(l.trips.at(4), 1);
  EXPECT_NEAR(l.transit_in_patient_s,
              tripTransitSeconds(s.channels[0], 0.5) + tripTransitSeconds(s.channels[1], 0.5),
              kExactS);
  EXPECT_NEAR(a.deliveredTotal(), s.totalDwellTime(), kExactS);
  // Delivered already: the same plan again is refused, and nothing is written.
  const auto lines = Journal(a.journalPath()).records().size();
  EXPECT_FALSE(a.start(s).ok());
  EXPECT_EQ(Journal(a.journalPath()).records().size(), lines);
}

TEST(Afterloader, RefusesBadSchedulesBeforeAnythingMoves) {
  TempDir dir;
  Afterloader a(config(dir));
  Schedule s = smallSchedule();
  s.channels[1].channel = 40;
  Status st = a.start(s);
  EXPECT_FALSE(st.ok());
  EXPECT_NE(st.message().find("channel 40: unknown"), std::string::npos) << st.message();
  s = smallSchedule();
  s.channels[0].time_s[0] = -2.0;
  EXPECT_FALSE(a.start(s).ok());
  EXPECT_EQ(a.state(), DeliveryState::kIdle);
  EXPECT_TRUE(fs::is_empty(dir.path));  // no journal written
  // A different schedule under an id already used is refused.
  ASSERT_TRUE(a.start(smallSchedule("p1")).ok());
  a.step(0.5);
  EXPECT_FALSE(a.start(smallSchedule("p2")).ok());  // busy
  ASSERT_TRUE(a.abort("test").ok());
  runToEnd(a);
  s = smallSchedule("p1");
  s.channels[0].time_s[2] += 1.0;
  st = a.start(s);
  EXPECT_FALSE(st.ok());
  EXPECT_NE(st.message().find("different schedule"), std::string::npos) << st.message();
}

TEST(Afterloader, PauseSettlesTheExactTimeAndResumeCompletes) {
  TempDir dir;
  Afterloader a(config(dir, 0.1));
  const Schedule s = smallSchedule();
  ASSERT_TRUE(a.start(s).ok());
  // Out to the first dwell (1.06 m / 0.5 m/s = 2.12 s) and 0.437 s into it.
  for (int i = 0; i < 2557; ++i)
    a.step(0.001);
  ASSERT_EQ(a.sourceDwell(), 0);
  ASSERT_TRUE(a.pause("operator").ok());
  EXPECT_FALSE(a.pause("again").ok());
  const auto rec = a.records();
  EXPECT_NEAR(rec[0].delivered_s, 0.437, 1e-6);  // settled to what was dwelt, not the commit
  runToEnd(a);
  EXPECT_EQ(a.sourceChannel(), 0);  // retracted while paused
  a.step(1.0);
  EXPECT_NEAR(a.records()[0].delivered_s, 0.437, 1e-6);  // nothing delivered while paused
  ASSERT_TRUE(a.resume().ok());
  runToEnd(a);
  EXPECT_EQ(a.state(), DeliveryState::kCompleted);
  const Ledger l = a.ledger();
  expectDeliveredAsPlanned(l, s, kExactS);
  EXPECT_EQ(l.trips.at(3), 2);  // went out again after the pause
  EXPECT_EQ(l.interruptions, 1);
}

TEST(Afterloader, DoorInterlockPausesAndBlocksResume) {
  TempDir dir;
  Afterloader a(config(dir));
  ASSERT_TRUE(a.start(smallSchedule()).ok());
  a.step(1.0);
  a.setDoorOpen(true);
  EXPECT_EQ(a.state(), DeliveryState::kPaused);
  EXPECT_FALSE(a.resume().ok());
  a.setDoorOpen(false);
  EXPECT_TRUE(a.resume().ok());
  runToEnd(a);
  EXPECT_EQ(a.state(), DeliveryState::kCompleted);
}

TEST(Afterloader, ObstructionRetractsSkipsTheChannelAndALaterDeliveryFinishesIt) {
  TempDir dir;
  Afterloader a(config(dir));
  const Schedule s = smallSchedule();
  ASSERT_TRUE(a.start(s).ok());
  for (int i = 0; i < 3000; ++i)
    a.step(0.001);  // 2.12 s out, 0.88 s into dwell 0 of channel 3
  ASSERT_EQ(a.sourceChannel(), 3);
  ASSERT_TRUE(a.setObstruction(3, true).ok());
  const double dwelt = a.records()[0].delivered_s;
  EXPECT_NEAR(dwelt, 0.88, 1e-6);
  runToEnd(a);
  EXPECT_EQ(a.state(), DeliveryState::kStopped);
  EXPECT_NE(a.lastMessage().find("obstructed channel(s) 3"), std::string::npos) << a.lastMessage();
  auto l = a.ledger();
  EXPECT_NEAR(l.delivered_s.at({3, 0}), dwelt, kExactS);
  EXPECT_NEAR(l.delivered_s.at({4, 2}), s.channels[1].time_s[2],
              kExactS);  // channel 4 delivered in full
  // Still obstructed: the next session skips it at once.
  ASSERT_TRUE(a.start(s).ok());
  runToEnd(a);
  EXPECT_EQ(a.state(), DeliveryState::kStopped);
  ASSERT_TRUE(a.setObstruction(3, false).ok());
  ASSERT_TRUE(a.start(s).ok());
  runToEnd(a);
  EXPECT_EQ(a.state(), DeliveryState::kCompleted);
  l = a.ledger();
  expectDeliveredAsPlanned(l, s, kExactS);
  EXPECT_TRUE(l.anomalies.empty());
  EXPECT_FALSE(a.setObstruction(0, true).ok());
}

// A crash (the device object destroyed without a word, as SIGKILL does) at random moments, many
// times over one delivery: the journal never loses delivered time, never delivers a quantum
// twice, and what the source really dwelt stays within one commit quantum of the plan.
TEST(Afterloader, CrashesAtRandomMomentsNeverLoseOrRepeatDose) {
  TempDir dir;
  const double quantum = 0.05;
  const Schedule s = smallSchedule();
  double truth_s = 0.0;  // what the simulated source really dwelt, all sessions
  std::mt19937 rng(7);
  std::uniform_int_distribution<int> steps(1, 400);
  int crashes = 0;
  for (int session = 0; session < 200; ++session) {
    Afterloader a(config(dir, quantum));
    const Status st = a.start(s);
    if (!st.ok()) {
      ASSERT_NE(st.message().find("already fully delivered"), std::string::npos) << st.message();
      break;
    }
    std::map<std::pair<int, int>, double> before;
    for (const auto& r : a.records())
      before[{r.channel, r.dwell}] = r.delivered_s;
    const int n = steps(rng);
    for (int i = 0; i < n && a.state() == DeliveryState::kDelivering; ++i)
      a.step(0.0071);
    // a.deliveredTotal() is the source's real dwell time so far (delivered_, not committed_).
    double real_this_session = a.deliveredTotal();
    for (const auto& [key, t] : before)
      real_this_session -= t;
    truth_s += real_this_session;
    if (a.state() == DeliveryState::kDelivering)
      ++crashes;  // destroyed mid-delivery
  }
  EXPECT_GT(crashes, 5);
  Afterloader last(config(dir, quantum));
  EXPECT_FALSE(last.start(s).ok());  // fully delivered: refused
  const Ledger l = replay(Journal((dir.path / "test_plan.journal").string()).records(), &s, 0.5);
  EXPECT_TRUE(l.completed);
  EXPECT_TRUE(l.anomalies.empty()) << l.anomalies.front();
  EXPECT_EQ(l.seq_gaps, 0);
  expectDeliveredAsPlanned(l, s, kExactS);  // the record: exactly the plan
  // The source really dwelt at most the plan, and no less than one quantum per crash under it.
  double uncertainty = 0.0;  // each crash leaves at most one quantum unaccounted
  for (const auto& [key, u] : l.uncertainty_s)
    uncertainty += u;
  EXPECT_LE(truth_s, s.totalDwellTime() + kExactS);
  EXPECT_GE(truth_s, s.totalDwellTime() - uncertainty - kExactS);
  EXPECT_LE(uncertainty, crashes * quantum + kExactS);
}

TEST(HdrDeliveryReport, AfterACrashTheDeliveredDoseComesFromTheJournal) {
  TempDir dir;
  const double quantum = 0.05;  // the journal commits in quanta [s]
  const Schedule s = smallSchedule();
  double given_s = 0.0;
  {
    Afterloader a(config(dir, quantum));
    ASSERT_TRUE(a.start(s).ok());
    while (a.state() == DeliveryState::kDelivering && a.deliveredTotal() < 0.4 * s.totalDwellTime())
      a.step(0.0071);
    ASSERT_EQ(a.state(), DeliveryState::kDelivering);  // destroyed mid-delivery: a crash
    given_s = a.deliveredTotal();
  }
  ASSERT_GT(given_s, 0.0);
  needle_guidance::procedures::HdrDeliveryReport r;
  r.deliveredFromJournal(s, (dir.path / "test_plan.journal").string());
  EXPECT_EQ(r.delivered_from, "journal");
  std::size_t planned_dwells = 0;
  for (const auto& c : s.channels)
    planned_dwells += c.time_s.size();
  ASSERT_EQ(r.dwells.size(), planned_dwells);
  EXPECT_NEAR(r.plannedTotal_s(), s.totalDwellTime(), kExactS);
  // Write-ahead: the record holds what was committed, what was given and at most one quantum
  // more, and that quantum is the uncertainty it reports.
  EXPECT_GE(r.deliveredTotal_s(), given_s - kExactS);
  EXPECT_LE(r.deliveredTotal_s(), given_s + quantum + kExactS);
  double uncertainty_s = 0.0;
  for (const auto& d : r.dwells)
    uncertainty_s += d.uncertainty_s;
  EXPECT_GE(uncertainty_s, r.deliveredTotal_s() - given_s - kExactS);

  needle_guidance::procedures::HdrDeliveryReport none;
  none.deliveredFromJournal(s, (dir.path / "missing.journal").string());
  EXPECT_EQ(none.delivered_from.rfind("nothing: journal not readable", 0), 0u)
      << none.delivered_from;
  EXPECT_EQ(none.dwells.size(), planned_dwells);
  EXPECT_EQ(none.deliveredTotal_s(), 0.0);
}

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
