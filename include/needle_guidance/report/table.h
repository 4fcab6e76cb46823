// A table of figures written as CSV, markdown and an aligned console table (docs/architecture.md,
// "Reports").
#pragma once

#include <string>
#include <variant>
#include <vector>

namespace needle_guidance::report {

/// A cell: text or a number printed with the column's precision.
using Cell = std::variant<std::string, double>;

/// Columns with names (units in the name, e.g. "depth_error_mm") and rows of cells.
class Table {
public:
  /// @param[in] columns column names; @param[in] precision significant digits for numbers
  explicit Table(std::vector<std::string> columns, int precision = 6);
  /// Appends a row; throws std::invalid_argument if its size differs from the column count.
  void addRow(std::vector<Cell> row);
  std::size_t rowCount() const { return rows_.size(); }
  const std::vector<std::string>& columns() const { return columns_; }
  /// The number in (row, column name); throws std::out_of_range / std::invalid_argument.
  double number(std::size_t row, const std::string& column) const;

  std::string toCsv() const;
  std::string toMarkdown() const;
  /// Fixed-width text for a terminal.
  std::string toText() const;
  /// Writes toCsv() to path; throws std::runtime_error if it cannot.
  void writeCsv(const std::string& path) const;

private:
  std::string format(const Cell& cell) const;
  std::vector<std::string> columns_;
  std::vector<std::vector<Cell>> rows_;
  int precision_;
};

/// A number for a JSON report: `precision` significant digits, "null" if not finite (JSON has
/// no NaN or infinity).
std::string jsonNumber(double v, int precision = 6);

/// Writes text to path (through path + ".partial", renamed into place), creating parent
/// folders; throws std::runtime_error on failure.
void writeTextFile(const std::string& path, const std::string& text);

}  // namespace needle_guidance::report
