#include "needle_guidance/report/table.h"

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <stdexcept>

namespace needle_guidance::report {

Table::Table(std::vector<std::string> columns, int precision)
    : columns_(std::move(columns)), precision_(precision) {
  if (columns_.empty()) {
    throw std::invalid_argument("Table: at least one column is needed");
  }
}

void Table::addRow(std::vector<Cell> row) {
  if (row.size() != columns_.size()) {
    throw std::invalid_argument("Table::addRow: row has " + std::to_string(row.size()) +
                                " cells for " + std::to_string(columns_.size()) + " columns");
  }
  rows_.push_back(std::move(row));
}

double Table::number(std::size_t row, const std::string& column) const {
  const auto it = std::find(columns_.begin(), columns_.end(), column);
  if (it == columns_.end()) {
    throw std::invalid_argument("Table::number: no column '" + column + "'");
  }
  const Cell& cell = rows_.at(row)[static_cast<std::size_t>(it - columns_.begin())];
  if (!std::holds_alternative<double>(cell)) {
    throw std::invalid_argument("Table::number: column '" + column + "' holds text");
  }
  return std::get<double>(cell);
}

std::string Table::format(const Cell& cell) const {
  if (std::holds_alternative<std::string>(cell)) {
    return std::get<std::string>(cell);
  }
  const double value = std::get<double>(cell);
  if (std::isnan(value)) {
    return "nan";
  }
  std::ostringstream out;
  out.precision(precision_);
  out << value;
  return out.str();
}

std::string Table::toCsv() const {
  std::ostringstream out;
  for (std::size_t c = 0; c < columns_.size(); ++c) {
    out << (c ? "," : "") << columns_[c];
  }
  out << '\n';
  for (const auto& row : rows_) {
    for (std::size_t c = 0; c < row.size(); ++c) {
      std::string text = format(row[c]);
      if (text.find_first_of(",\"\n") != std::string::npos) {
        std::string quoted = "\"";
        for (char ch : text) {
          quoted += ch == '"' ? std::string("\"\"") : std::string(1, ch);
        }
        text = quoted + "\"";
      }
      out << (c ? "," : "") << text;
    }
    out << '\n';
  }
  return out.str();
}

std::string Table::toMarkdown() const {
  std::ostringstream out;
  out << '|';
  for (const auto& c : columns_) {
    out << ' ' << c << " |";
  }
  out << "\n|";
  for (std::size_t c = 0; c < columns_.size(); ++c) {
    out << " --- |";
  }
  out << '\n';
  for (const auto& row : rows_) {
    out << '|';
    for (const auto& cell : row) {
      out << ' ' << format(cell) << " |";
    }
    out << '\n';
  }
  return out.str();
}

std::string Table::toText() const {
  std::vector<std::size_t> width(columns_.size());
  for (std::size_t c = 0; c < columns_.size(); ++c) {
    width[c] = columns_[c].size();
    for (const auto& row : rows_) {
      width[c] = std::max(width[c], format(row[c]).size());
    }
  }
  std::ostringstream out;
  auto line = [&](const std::vector<std::string>& cells) {
    for (std::size_t c = 0; c < cells.size(); ++c) {
      out << (c ? "  " : "") << std::string(width[c] - cells[c].size(), ' ') << cells[c];
    }
    out << '\n';
  };
  line(columns_);
  for (const auto& row : rows_) {
    std::vector<std::string> cells;
    for (const auto& cell : row) {
      cells.push_back(format(cell));
    }
    line(cells);
  }
  return out.str();
}

void Table::writeCsv(const std::string& path) const {
  writeTextFile(path, toCsv());
}

std::string jsonNumber(double v, int precision) {
  if (!std::isfinite(v)) {
    return "null";
  }
  std::ostringstream out;
  out.precision(precision);
  out << v;
  return out.str();
}

void writeTextFile(const std::string& path, const std::string& text) {
  const std::filesystem::path p(path);
  if (p.has_parent_path()) {
    std::filesystem::create_directories(p.parent_path());
  }
  // Written beside and renamed into place, so a reader waiting for the file never sees it
  // half written.
  const std::string partial = path + ".partial";
  {
    std::ofstream out(partial);
    if (!out) {
      throw std::runtime_error("writeTextFile: cannot write '" + path + "'");
    }
    out << text;
    out.close();
    if (!out) {
      throw std::runtime_error("writeTextFile: write to '" + path + "' failed");
    }
  }
  std::filesystem::rename(partial, path);
}

}  // namespace needle_guidance::report
