#include "needle_guidance/delivery/journal.h"

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cerrno>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <fstream>
#include <sstream>
#include <stdexcept>

#include "needle_guidance/delivery/schedule.h"

namespace needle_guidance::delivery {

namespace {

std::uint32_t crc32(const std::string& text) {
  std::uint32_t crc = 0xffffffffu;
  for (unsigned char byte : text) {
    crc ^= byte;
    for (int k = 0; k < 8; ++k)
      crc = (crc >> 1) ^ (0xedb88320u & (0u - (crc & 1u)));
  }
  return ~crc;
}

std::string body(const JournalRecord& r) {
  char head[160];
  std::snprintf(head, sizeof head, "%ld,%.6f,%s,%d,%d,%.9f,", r.seq, r.wall_time_s, r.kind.c_str(),
                r.channel, r.dwell, r.value);
  return head + r.text;
}

std::runtime_error ioError(const std::string& what, const std::string& path) {
  return std::runtime_error("journal " + path + ": " + what + ": " + std::strerror(errno));
}

}  // namespace

std::string formatRecord(const JournalRecord& r) {
  if (r.text.find_first_of(",\n\r") != std::string::npos) {
    throw std::invalid_argument("journal record text must not contain ',' or a line break: '" +
                                r.text + "'");
  }
  const std::string b = body(r);
  char crc[16];
  std::snprintf(crc, sizeof crc, ",%08x", crc32(b));
  return b + crc;
}

std::optional<JournalRecord> parseRecord(const std::string& line) {
  const auto last = line.rfind(',');
  if (last == std::string::npos || line.size() - last != 9)
    return std::nullopt;
  const std::string b = line.substr(0, last);
  char* end = nullptr;
  const unsigned long crc = std::strtoul(line.c_str() + last + 1, &end, 16);
  if (end != line.c_str() + line.size() || crc != crc32(b))
    return std::nullopt;
  JournalRecord r;
  std::stringstream in(b);
  std::string field;
  std::vector<std::string> fields;
  while (std::getline(in, field, ','))
    fields.push_back(field);
  if (b.back() == ',')
    fields.emplace_back();
  if (fields.size() != 7)
    return std::nullopt;
  try {
    r.seq = std::stol(fields[0]);
    r.wall_time_s = std::stod(fields[1]);
    r.kind = fields[2];
    r.channel = std::stoi(fields[3]);
    r.dwell = std::stoi(fields[4]);
    r.value = std::stod(fields[5]);
    r.text = fields[6];
  } catch (const std::exception&) {
    return std::nullopt;
  }
  return r;
}

Journal::Journal(std::string path) : path_(std::move(path)) {
  std::string content;
  {
    std::ifstream in(path_, std::ios::binary);
    if (in)
      content.assign(std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>());
  }
  std::size_t start = 0, good_end = 0;
  while (start < content.size()) {
    const auto nl = content.find('\n', start);
    const bool complete = nl != std::string::npos;
    const std::string line = content.substr(start, complete ? nl - start : std::string::npos);
    const auto record = complete ? parseRecord(line) : std::nullopt;
    const std::size_t next = complete ? nl + 1 : content.size();
    if (!record) {
      if (next < content.size()) {
        throw std::runtime_error("journal " + path_ + ": damaged record at byte " +
                                 std::to_string(start) + " followed by more records; not trusted");
      }
      torn_tail_bytes_ = content.size() - start;
      break;
    }
    records_.push_back(*record);
    good_end = next;
    start = next;
  }
  fd_ = ::open(path_.c_str(), O_WRONLY | O_CREAT | O_CLOEXEC, 0644);
  if (fd_ < 0)
    throw ioError("cannot open", path_);
  if (torn_tail_bytes_ > 0 && ::ftruncate(fd_, static_cast<off_t>(good_end)) != 0) {
    const auto e = ioError("cannot cut the damaged last line", path_);
    ::close(fd_);
    throw e;
  }
  if (::lseek(fd_, 0, SEEK_END) < 0) {
    const auto e = ioError("cannot seek", path_);
    ::close(fd_);
    throw e;
  }
}

Journal::~Journal() {
  if (fd_ >= 0)
    ::close(fd_);
}

std::string Journal::append(JournalRecord record) {
  record.seq = records_.empty() ? 1 : records_.back().seq + 1;
  record.wall_time_s =
      std::chrono::duration<double>(std::chrono::system_clock::now().time_since_epoch()).count();
  const std::string line = formatRecord(record);
  const std::string out = line + "\n";
  std::size_t written = 0;
  while (written < out.size()) {
    const ssize_t n = ::write(fd_, out.data() + written, out.size() - written);
    if (n < 0) {
      if (errno == EINTR)
        continue;
      throw ioError("write failed", path_);
    }
    written += static_cast<std::size_t>(n);
  }
  if (::fdatasync(fd_) != 0)
    throw ioError("fdatasync failed", path_);
  records_.push_back(record);
  return line;
}

Ledger replay(const std::vector<JournalRecord>& records, const Schedule* schedule,
              double speed_m_s) {
  Ledger l;
  std::map<std::pair<int, int>, double> planned;
  std::map<int, double> transfer;
  if (schedule) {
    for (const auto& c : schedule->channels) {
      transfer[c.channel] = c.transfer_length_m;
      for (std::size_t k = 0; k < c.time_s.size() && k < c.dwell_index.size(); ++k) {
        planned[{c.channel, c.dwell_index[k]}] = c.time_s[k];
      }
    }
  }
  // The last commit of the running session that no later record shows finished.
  std::optional<std::pair<std::pair<int, int>, double>> open_quantum;
  // The last move: the source travels from `from` towards `to` until the next move starts.
  struct Move {
    bool active = false;
    int channel = 0;
    double from = 0.0, to = 0.0;
  } move;
  // Seconds inside the patient of a travel in `channel` from `from` to `end` [m from the indexer].
  auto travelled = [&](int channel, double from, double end) {
    const auto t = transfer.find(channel);
    const double skin = t != transfer.end() ? t->second : 0.0;
    return speed_m_s > 0.0 ? std::abs(std::max(end, skin) - std::max(from, skin)) / speed_m_s : 0.0;
  };
  for (const auto& r : records) {
    if (l.last_seq != 0 && r.seq != l.last_seq + 1)
      l.seq_gaps += std::labs(r.seq - l.last_seq - 1);
    l.last_seq = r.seq;
    const std::pair<int, int> key{r.channel, r.dwell};
    if (r.kind == "begin") {
      std::istringstream in(r.text);
      std::string hash;
      in >> l.plan_id >> hash;
      l.content_hash = std::strtoull(hash.c_str(), nullptr, 16);
      l.begun = true;
    } else if (r.kind == "session") {
      ++l.sessions;
      l.open_session = true;
      open_quantum.reset();
    } else if (r.kind == "recover") {
      ++l.interruptions;
      // The crash stopped the last move somewhere; count it to its end and the hardware's
      // retraction from there.
      if (move.active) {
        l.transit_in_patient_s +=
            travelled(move.channel, move.from, move.to) + travelled(move.channel, move.to, 0.0);
      }
      move.active = false;
      if (open_quantum)
        l.uncertainty_s[open_quantum->first] += open_quantum->second;
      open_quantum.reset();
    } else if (r.kind == "move") {
      open_quantum.reset();
      const double from = std::atof(r.text.c_str());
      if (move.active) {
        const double end = move.channel == r.channel ? from : move.to;
        l.transit_in_patient_s += travelled(move.channel, move.from, end);
      }
      move = Move{true, r.channel, from, r.value};
      if (from <= 0.0 && r.value > 0.0)
        ++l.trips[r.channel];
    } else if (r.kind == "commit" || r.kind == "settle") {
      double& d = l.delivered_s[key];
      if (r.kind == "commit") {
        if (r.value < d - 1e-9) {
          l.anomalies.push_back("seq " + std::to_string(r.seq) + ": commit " +
                                std::to_string(r.value) + " s below the " + std::to_string(d) +
                                " s already committed at channel " + std::to_string(r.channel) +
                                " dwell " + std::to_string(r.dwell));
        }
        open_quantum = std::make_pair(key, r.value - d);
      } else {
        open_quantum.reset();
      }
      const auto p = planned.find(key);
      if (p != planned.end() && r.value > p->second + 1e-6) {
        l.anomalies.push_back("seq " + std::to_string(r.seq) + ": " + r.kind + " " +
                              std::to_string(r.value) + " s above the planned " +
                              std::to_string(p->second) + " s at channel " +
                              std::to_string(r.channel) + " dwell " + std::to_string(r.dwell));
      }
      d = r.value;
    } else if (r.kind == "pause" || r.kind == "abort" || r.kind == "interlock") {
      ++l.interruptions;
    } else if (r.kind == "end") {
      l.open_session = false;
      open_quantum.reset();
      if (r.text == "completed")
        l.completed = true;
    }
  }
  if (move.active)
    l.transit_in_patient_s += travelled(move.channel, move.from, move.to);
  // A session still open (running, or crashed and not reopened yet): its last quantum is open.
  if (l.open_session && open_quantum)
    l.uncertainty_s[open_quantum->first] += open_quantum->second;
  return l;
}

}  // namespace needle_guidance::delivery
