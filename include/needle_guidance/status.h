// One outcome shape for every module: an expected failure comes back as a
// status with a code, a one-line message, `operator bool` and `toString()`; a broken
// precondition throws std::invalid_argument instead.
#pragma once

#include <optional>
#include <string>
#include <utility>

namespace needle_guidance {

/// Outcome of an operation: a code from the caller's enum and a one-line message.
/// `Code` is an enum class; `kSuccess` is the value that means it worked (true).
template <typename Code, Code kSuccess>
class Status {
public:
  Status(Code code, std::string message) : code_(code), message_(std::move(message)) {}
  /// The success status with an optional message.
  static Status success(std::string message = "ok") { return Status(kSuccess, std::move(message)); }

  explicit operator bool() const { return code_ == kSuccess; }
  bool ok() const { return code_ == kSuccess; }
  Code code() const { return code_; }
  const std::string& toString() const { return message_; }
  const std::string& message() const { return message_; }

private:
  Code code_;
  std::string message_;
};

/// The general codes most operations need; a module with a richer outcome declares its own
/// enum and uses Status<ItsCode, ItsCode::kOk>.
enum class StatusCode {
  kOk,
  kRefused,  ///< the request was refused; nothing changed
  kFailed,   ///< ran, but the outcome was not met (missed target, no plan, not found)
  kError,    ///< could not run (a fault: a dead node, an I/O error)
};
const char* toString(StatusCode code);

using GeneralStatus = Status<StatusCode, StatusCode::kOk>;

/// A command's outcome: accepted, or refused with the reason (nothing changed).
enum class CommandCode { kAccepted, kRefused };
class CommandStatus : public Status<CommandCode, CommandCode::kAccepted> {
public:
  using Status::Status;
  static CommandStatus accepted() { return {CommandCode::kAccepted, "accepted"}; }
  static CommandStatus refused(std::string reason) {
    return {CommandCode::kRefused, std::move(reason)};
  }
};

/// A value or the status that says why there is none.
template <typename T, typename S = GeneralStatus>
class Result {
public:
  Result(T value)
      : status_(S::success()), value_(std::move(value)) {}  // NOLINT: implicit on purpose
  Result(S status) : status_(std::move(status)) {}          // NOLINT: implicit on purpose

  explicit operator bool() const { return value_.has_value(); }
  const S& status() const { return status_; }
  /// The value; throws std::logic_error (via std::optional) when there is none.
  const T& value() const { return value_.value(); }
  T& value() { return value_.value(); }

private:
  S status_;
  std::optional<T> value_;
};

inline const char* toString(StatusCode code) {
  switch (code) {
    case StatusCode::kOk:
      return "ok";
    case StatusCode::kRefused:
      return "refused";
    case StatusCode::kFailed:
      return "failed";
    case StatusCode::kError:
      return "error";
  }
  return "unknown";
}

}  // namespace needle_guidance
