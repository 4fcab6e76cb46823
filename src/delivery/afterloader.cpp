#include "needle_guidance/delivery/afterloader.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <sstream>
#include <stdexcept>

namespace needle_guidance::delivery {

namespace {
constexpr double kTimeEps = 1e-9;  // [s] delivered within this of planned counts as done
}

const char* toString(DeliveryState state) {
  switch (state) {
    case DeliveryState::kIdle:
      return "IDLE";
    case DeliveryState::kDelivering:
      return "DELIVERING";
    case DeliveryState::kPaused:
      return "PAUSED";
    case DeliveryState::kStopped:
      return "STOPPED";
    case DeliveryState::kCompleted:
      return "COMPLETED";
  }
  return "?";
}

Afterloader::Afterloader(AfterloaderConfig config) : config_(std::move(config)) {
  if (!(config_.source_speed_m_s > 0.0) || !std::isfinite(config_.source_speed_m_s)) {
    throw std::invalid_argument("afterloader: source speed must be > 0 m/s");
  }
  if (!(config_.commit_quantum_s > 0.0) || !std::isfinite(config_.commit_quantum_s)) {
    throw std::invalid_argument("afterloader: commit quantum must be > 0 s");
  }
  if (config_.limits.channels < 1)
    throw std::invalid_argument("afterloader: needs at least one channel");
}

Afterloader::~Afterloader() = default;

std::string Afterloader::journalPath() const {
  return schedule_ ? config_.journal_dir + "/" + schedule_->plan_id + ".journal" : "";
}

Status Afterloader::start(const Schedule& schedule) {
  if (state_ == DeliveryState::kDelivering || state_ == DeliveryState::kPaused) {
    return Status::refused("a delivery of plan '" + schedule_->plan_id + "' is " +
                           (state_ == DeliveryState::kPaused ? "paused" : "running") +
                           "; abort it first");
  }
  if (channel_index_ >= 0)
    return Status::refused("the source is still retracting");
  if (door_open_)
    return Status::refused("the treatment-room door is open");
  const auto problems = validateSchedule(schedule, config_.limits);
  if (!problems.empty()) {
    std::string why = "schedule refused:";
    for (const auto& p : problems)
      why += " " + p + ";";
    why.pop_back();
    return Status::refused(why);
  }
  std::unique_ptr<Journal> journal;
  const std::string path = config_.journal_dir + "/" + schedule.plan_id + ".journal";
  try {
    journal = std::make_unique<Journal>(path);
  } catch (const std::exception& e) {
    return Status::refused(e.what());
  }
  const Ledger ledger = replay(journal->records(), &schedule, config_.source_speed_m_s);
  char hash[32];
  std::snprintf(hash, sizeof hash, "%016llx",
                static_cast<unsigned long long>(schedule.contentHash()));
  if (ledger.begun &&
      (ledger.plan_id != schedule.plan_id || ledger.content_hash != schedule.contentHash())) {
    return Status::refused("journal " + path + " holds a different schedule for plan '" +
                           schedule.plan_id + "' (plan ids must be unique per schedule)");
  }
  if (ledger.completed)
    return Status::refused("plan '" + schedule.plan_id + "' is already fully delivered (" + path +
                           ")");
  if (!ledger.anomalies.empty()) {
    return Status::refused("journal " + path + " is inconsistent: " + ledger.anomalies.front());
  }
  for (const auto& [key, t] : ledger.delivered_s) {
    const int ci = schedule.channelIndex(key.first);
    const auto& idx = ci >= 0 ? schedule.channels[ci].dwell_index : std::vector<int>{};
    if (std::find(idx.begin(), idx.end(), key.second) == idx.end()) {
      return Status::refused("journal " + path + " records channel " + std::to_string(key.first) +
                             " dwell " + std::to_string(key.second) +
                             ", which the schedule does not have");
    }
  }
  schedule_ = std::make_unique<Schedule>(schedule);
  journal_ = std::move(journal);
  delivered_ = ledger.delivered_s;  // conservative: a crash's open quantum counts as delivered
  committed_ = ledger.delivered_s;
  skipped_.clear();
  dwell_k_ = -1;
  moving_ = false;
  state_ = DeliveryState::kDelivering;
  if (!ledger.begun) {
    std::ostringstream text;
    text << schedule.plan_id << " " << hash << " " << schedule.dwellCount() << " "
         << schedule.totalDwellTime();
    write({0, 0.0, "begin", 0, -1, 0.0, text.str()});
  }
  if (ledger.open_session)
    write({0, 0.0, "recover", 0, -1, 0.0, "previous session ended without a record"});
  write({0, 0.0, "session", 0, -1, deliveredTotal(), ledger.sessions == 0 ? "start" : "resume"});
  last_message_ =
      (ledger.sessions == 0 ? "delivering plan '" : "resuming plan '") + schedule.plan_id + "'";
  return Status::accepted();
}

void Afterloader::write(JournalRecord r) {
  new_lines_.push_back(journal_->append(std::move(r)));
}

void Afterloader::settleCurrent() {
  for (auto& [key, com] : committed_) {
    const double del = delivered_[key];
    if (com > del + kTimeEps) {
      write({0, 0.0, "settle", key.first, key.second, del, ""});
      com = del;
    }
  }
}

Status Afterloader::pause(const std::string& reason) {
  if (state_ != DeliveryState::kDelivering)
    return Status::refused(std::string("nothing to pause (") + toString(state_) + ")");
  settleCurrent();
  write({0, 0.0, "pause", sourceChannel(), -1, 0.0, reason});
  state_ = DeliveryState::kPaused;
  last_message_ = "paused: " + reason;
  return Status::accepted();
}

Status Afterloader::resume() {
  if (state_ != DeliveryState::kPaused)
    return Status::refused(std::string("not paused (") + toString(state_) + ")");
  if (door_open_)
    return Status::refused("the treatment-room door is open");
  write({0, 0.0, "resume", 0, -1, 0.0, ""});
  state_ = DeliveryState::kDelivering;
  last_message_ = "resumed";
  return Status::accepted();
}

Status Afterloader::abort(const std::string& reason) {
  if (state_ != DeliveryState::kDelivering && state_ != DeliveryState::kPaused) {
    return Status::refused(std::string("nothing to abort (") + toString(state_) + ")");
  }
  settleCurrent();
  write({0, 0.0, "abort", sourceChannel(), -1, 0.0, reason});
  write({0, 0.0, "end", 0, -1, deliveredTotal(), "aborted"});
  state_ = DeliveryState::kStopped;
  last_message_ = "aborted: " + reason;
  return Status::accepted();
}

void Afterloader::setDoorOpen(bool open) {
  door_open_ = open;
  if (open && state_ == DeliveryState::kDelivering)
    pause("door open");
}

Status Afterloader::setObstruction(int channel, bool obstructed) {
  if (channel < 1 || channel > config_.limits.channels) {
    return Status::refused("no channel " + std::to_string(channel) + " (1-" +
                           std::to_string(config_.limits.channels) + ")");
  }
  obstructed_[channel] = obstructed;
  if (!obstructed) {
    skipped_.erase(channel);
    return Status::accepted();
  }
  if (journal_ && sourceChannel() == channel && state_ != DeliveryState::kIdle) {
    settleCurrent();
    write({0, 0.0, "interlock", channel, -1, 0.0, "obstruction"});
    skipped_[channel] = true;
    dwell_k_ = -1;
    moving_ = false;  // the retraction starts now
    last_message_ =
        "interlock: channel " + std::to_string(channel) + " obstructed; source retracted";
  }
  return Status::accepted();
}

std::vector<int> Afterloader::obstructedChannels() const {
  std::vector<int> out;
  for (const auto& [c, o] : obstructed_)
    if (o)
      out.push_back(c);
  return out;
}

int Afterloader::sourceChannel() const {
  return channel_index_ >= 0 && schedule_ ? schedule_->channels[channel_index_].channel : 0;
}

int Afterloader::sourceDwell() const {
  return dwell_k_ >= 0 && channel_index_ >= 0
             ? schedule_->channels[channel_index_].dwell_index[dwell_k_]
             : -1;
}

bool Afterloader::sourceInPatient() const {
  return channel_index_ >= 0 && schedule_->channels[channel_index_].inPatient(distance_m_);
}

Point3 Afterloader::sourcePosition() const {
  return channel_index_ >= 0 ? schedule_->channels[channel_index_].sourcePosition(distance_m_)
                             : Point3::Zero();
}

double Afterloader::plannedTotal() const {
  return schedule_ ? schedule_->totalDwellTime() : 0.0;
}

double Afterloader::deliveredTotal() const {
  double t = 0.0;
  for (const auto& [key, d] : delivered_)
    t += d;
  return t;
}

double Afterloader::deliveredFraction() const {
  const double planned = plannedTotal();
  return planned > 0.0 ? std::min(1.0, deliveredTotal() / planned) : 0.0;
}

std::vector<DwellRecord> Afterloader::records() const {
  std::vector<DwellRecord> out;
  if (!schedule_)
    return out;
  for (const auto& c : schedule_->channels) {
    for (std::size_t k = 0; k < c.time_s.size(); ++k) {
      const auto it = committed_.find({c.channel, c.dwell_index[k]});
      out.push_back(
          {c.channel, c.dwell_index[k], c.time_s[k], it == committed_.end() ? 0.0 : it->second});
    }
  }
  return out;
}

Ledger Afterloader::ledger() const {
  return journal_ ? replay(journal_->records(), schedule_.get(), config_.source_speed_m_s)
                  : Ledger{};
}

std::vector<std::string> Afterloader::takeJournalLines() {
  std::vector<std::string> out;
  out.swap(new_lines_);
  return out;
}

bool Afterloader::nextDwell(Dwell& next) const {
  const auto& channels = schedule_->channels;
  const int n = static_cast<int>(channels.size());
  // The channel the source is in first (never leave a channel half done), then schedule order.
  for (int pass = -1; pass < n; ++pass) {
    const int ci = pass < 0 ? channel_index_ : pass;
    if (ci < 0 || skipped_.count(channels[ci].channel))
      continue;
    const auto& c = channels[ci];
    for (std::size_t k = 0; k < c.time_s.size(); ++k) {
      const auto it = delivered_.find({c.channel, c.dwell_index[k]});
      if ((it == delivered_.end() ? 0.0 : it->second) < c.time_s[k] - kTimeEps) {
        next = {ci, static_cast<int>(k)};
        return true;
      }
    }
  }
  return false;
}

void Afterloader::beginMove(int channel_index, double target_m) {
  char from[32];
  std::snprintf(from, sizeof from, "%.9f", distance_m_);
  write({0, 0.0, "move", schedule_->channels[channel_index].channel, -1, target_m, from});
  moving_ = true;
  move_target_m_ = target_m;
  dwell_k_ = -1;
}

void Afterloader::moveToward(double target_m, double& dt_s) {
  const double gap = target_m - distance_m_;
  const double reach = config_.source_speed_m_s * dt_s;
  if (std::abs(gap) <= reach) {
    dt_s -= std::abs(gap) / config_.source_speed_m_s;
    distance_m_ = target_m;
    moving_ = false;
  } else {
    distance_m_ += gap > 0.0 ? reach : -reach;
    dt_s = 0.0;
  }
}

void Afterloader::finish() {
  double undelivered = 0.0;
  std::ostringstream skipped;
  for (const auto& [channel, s] : skipped_) {
    const auto& c = schedule_->channels[schedule_->channelIndex(channel)];
    for (std::size_t k = 0; k < c.time_s.size(); ++k)
      undelivered += c.time_s[k] - delivered_[{channel, c.dwell_index[k]}];
    skipped << " " << channel;
  }
  if (skipped_.empty()) {
    write({0, 0.0, "end", 0, -1, deliveredTotal(), "completed"});
    state_ = DeliveryState::kCompleted;
    last_message_ = "completed plan '" + schedule_->plan_id + "'";
  } else {
    write({0, 0.0, "end", 0, -1, deliveredTotal(), "stopped"});
    state_ = DeliveryState::kStopped;
    std::ostringstream msg;
    msg << "stopped: obstructed channel(s)" << skipped.str() << " skipped, " << undelivered
        << " s undelivered; clear the obstruction and deliver the plan again to finish it";
    last_message_ = msg.str();
  }
}

void Afterloader::step(double dt_s) {
  if (!std::isfinite(dt_s) || dt_s < 0.0)
    throw std::invalid_argument("afterloader: step dt must be finite and >= 0");
  time_s_ += dt_s;
  try {
    while (dt_s > 0.0) {
      Dwell next{-1, -1};
      const bool delivering = state_ == DeliveryState::kDelivering;
      const bool more = delivering && nextDwell(next);
      if (channel_index_ >= 0 && (!more || next.channel_index != channel_index_)) {
        // Retract: paused, stopped, done, interlocked or off to another channel.
        if (!moving_ || move_target_m_ != 0.0)
          beginMove(channel_index_, 0.0);
        moveToward(0.0, dt_s);
        if (distance_m_ <= 0.0) {
          distance_m_ = 0.0;
          channel_index_ = -1;
        }
        continue;
      }
      if (!delivering)
        break;
      if (!more) {
        finish();
        break;
      }
      const auto& c = schedule_->channels[next.channel_index];
      if (channel_index_ < 0) {
        if (obstructed_[c.channel]) {
          write({0, 0.0, "interlock", c.channel, -1, 0.0, "obstruction"});
          skipped_[c.channel] = true;
          last_message_ =
              "interlock: channel " + std::to_string(c.channel) + " obstructed; skipped";
          continue;
        }
        channel_index_ = next.channel_index;
      }
      const double target = c.distance_m[next.k];
      if (distance_m_ != target) {
        if (!moving_ || move_target_m_ != target)
          beginMove(channel_index_, target);
        moveToward(target, dt_s);
        continue;
      }
      // Dwell: expose only what the journal already covers; commit the next quantum first.
      dwell_k_ = next.k;
      const std::pair<int, int> key{c.channel, c.dwell_index[next.k]};
      double& del = delivered_[key];
      double& com = committed_[key];
      if (com <= del + kTimeEps) {
        const double upto = std::min(c.time_s[next.k], del + config_.commit_quantum_s);
        write({0, 0.0, "commit", key.first, key.second, upto, ""});
        com = upto;
      }
      if (com - del <= dt_s) {
        dt_s -= com - del;
        del = com;
      } else {
        del += dt_s;
        dt_s = 0.0;
      }
    }
  } catch (const std::runtime_error& e) {
    // The record cannot be kept: stop at once, source to the safe (hardware retraction).
    state_ = DeliveryState::kStopped;
    channel_index_ = -1;
    distance_m_ = 0.0;
    moving_ = false;
    dwell_k_ = -1;
    last_message_ = std::string("stopped: ") + e.what();
    throw;
  }
}

}  // namespace needle_guidance::delivery
