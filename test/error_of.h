// For tests: the message of the exception a call throws, for tests that check a refusal names
// what and where.
#pragma once

#include <exception>
#include <string>

/// What f() threw (std::exception::what), or "" if it did not throw.
template <typename F>
std::string errorOf(F&& f) {
  try {
    f();
  } catch (const std::exception& e) {
    return e.what();
  }
  return "";
}
