// The afterloader's dose record: an append-only journal, one file per plan, every record written
// and fdatasync'ed before the action it describes (write-ahead), each line carrying a sequence
// number and a CRC-32 so that a torn last line (the process killed mid-write) is told apart from
// a damaged record. Replaying it gives the time delivered at every dwell position. No ROS here.
#pragma once

#include <cstdint>
#include <map>
#include <optional>
#include <string>
#include <utility>
#include <vector>

namespace needle_guidance::delivery {

struct Schedule;

/// One record. Kinds (value meaning):
///   begin     first record; text "<plan_id> <content hash hex> <dwells> <total dwell s>"
///   session   a deliver command started or resumed the plan
///   recover   the journal was reopened after its last session ended without "end" (a crash)
///   move      the source starts moving in `channel` to `value` m from the indexer; text: from [m]
///   commit    the source may dwell at (channel, dwell) up to `value` s in total (written first)
///   settle    it dwelt exactly `value` s in total there (after a pause, abort or interlock)
///   pause / resume / abort / interlock   operator and interlock events; text: reason
///   end       the session ended; text: completed | stopped | aborted
struct JournalRecord {
  long seq = 0;
  double wall_time_s = 0.0;  ///< seconds since the epoch when written
  std::string kind;
  int channel = 0;
  int dwell = -1;  ///< DwellPosition::index, -1 if none
  double value = 0.0;
  std::string text;
};

/// The line of a record (without newline): seq,wall_time,kind,channel,dwell,value,text,crc32.
std::string formatRecord(const JournalRecord& r);
/// The record of a line, or nullopt for a malformed line or a wrong CRC.
std::optional<JournalRecord> parseRecord(const std::string& line);

/// An open journal file. Throws std::runtime_error naming the file when it cannot be opened or
/// written, or when a record other than the last is damaged (the journal is then not trusted).
class Journal {
public:
  /// Opens or creates `path` for appending and reads what it holds. A damaged last line is cut
  /// off (it was never acknowledged: the write-ahead order makes nothing depend on it).
  explicit Journal(std::string path);
  ~Journal();
  Journal(const Journal&) = delete;
  Journal& operator=(const Journal&) = delete;

  /// Appends the record (sequence number and time assigned here), fdatasync's the file and
  /// returns the line written. Throws std::runtime_error if writing or syncing fails.
  std::string append(JournalRecord record);

  const std::vector<JournalRecord>& records() const { return records_; }
  const std::string& path() const { return path_; }
  /// Bytes of a damaged last line that were cut off when the journal was opened.
  std::size_t tornTailBytes() const { return torn_tail_bytes_; }

private:
  std::string path_;
  int fd_ = -1;
  std::vector<JournalRecord> records_;
  std::size_t torn_tail_bytes_ = 0;
};

/// What a journal says was delivered.
struct Ledger {
  std::string plan_id;
  std::uint64_t content_hash = 0;
  bool begun = false;
  bool completed = false;     ///< an "end completed" record
  bool open_session = false;  ///< the last session has no "end" (crash, or still running)
  std::map<std::pair<int, int>, double> delivered_s;  ///< (channel, dwell) -> delivered [s]
  /// (channel, dwell) -> the most the source may have been short of `delivered_s` there
  /// because a crash cut a committed quantum (0 unless a session ended without settling).
  std::map<std::pair<int, int>, double> uncertainty_s;
  std::map<int, int> trips;  ///< channel -> times the source entered it from the safe
  double transit_in_patient_s = 0.0;
  int interruptions = 0;  ///< pause, abort, interlock and recover records
  int sessions = 0;
  /// Records that contradict the write-ahead rules: a commit below what was already committed
  /// (a quantum delivered twice), a commit or settle above the planned time.
  std::vector<std::string> anomalies;
  long last_seq = 0;
  long seq_gaps = 0;  ///< missing sequence numbers
};

/// Replays records. `schedule` (optional) gives planned times, transfer lengths and the source
/// speed needs `speed_m_s` for the transit in the patient.
Ledger replay(const std::vector<JournalRecord>& records, const Schedule* schedule,
              double speed_m_s);

}  // namespace needle_guidance::delivery
