// CSV reading and writing with one-line, located error messages.
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <charconv>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <fstream>
#include <memory>
#include <sstream>
#include <string_view>

#include "piezo_compensation/io/axes.h"
#include "piezo_compensation/io/dataset.h"
#include "piezo_compensation/io/durable.h"

namespace piezo::io {

namespace {


std::string trim(std::string_view s) {
  while (!s.empty() && (s.front() == ' ' || s.front() == '\t')) s.remove_prefix(1);
  while (!s.empty() && (s.back() == ' ' || s.back() == '\t' || s.back() == '\r')) s.remove_suffix(1);
  return std::string(s);
}

// Where each CSV column goes.
enum class Target { kTime, kVoltage, kPosition, kTruth, kSegment, kPhase, kAux };
struct ColumnSlot {
  Target target;
  int index;  // axis index or aux index
  std::string name;
};

// The lines of a file's text, without their line ends.
struct CsvLines {
  std::string text;
  std::size_t pos = 0;
  bool next(std::string_view& line) {
    if (pos >= text.size()) return false;
    std::size_t end = text.find('\n', pos);
    if (end == std::string::npos) end = text.size();
    line = std::string_view(text).substr(pos, end - pos);
    if (!line.empty() && line.back() == '\r') line.remove_suffix(1);
    pos = end + 1;
    return true;
  }
  bool at_end() const { return pos >= text.size(); }
};

// `# origin: simulated` (Dataset::origin) before the column names; no other comment lines. Returns the column
// names; header_row is the header's row number.
std::vector<std::string> csv_header(CsvLines& lines, const std::string& path, Dataset& d, std::size_t& header_row) {
  std::string_view header;
  lines.next(header);
  header_row = 1;
  while (!header.empty() && header.front() == '#') {
    const std::string c = trim(header.substr(1));
    const std::string key = "origin:";
    const std::string value = c.rfind(key, 0) == 0 ? trim(std::string_view(c).substr(key.size())) : std::string();
    if (value != kOriginSimulated && value != kOriginRecorded)
      throw DataError(path + ": row " + std::to_string(header_row) + ": expected '# origin: simulated' or '# origin: "
                      "recorded' (the only comment line a data file may have, before the column names)");
    d.origin = value;
    if (!lines.next(header)) throw DataError(path + ": no header row after row " + std::to_string(header_row));
    ++header_row;
  }
  std::vector<std::string> names;
  std::size_t start = 0;
  while (true) {
    std::size_t comma = header.find(',', start);
    names.push_back(trim(header.substr(start, comma == std::string_view::npos ? std::string_view::npos : comma - start)));
    if (comma == std::string_view::npos) break;
    start = comma + 1;
  }
  return names;
}

// Where each named column goes; adds the data set's axes (each needs voltage and position) and aux columns.
std::vector<ColumnSlot> csv_slots(const std::vector<std::string>& names, const std::string& path, std::size_t header_row,
                                  Dataset& d) {
  std::vector<ColumnSlot> slots;
  bool have_time = false;
  bool have_v[3] = {false, false, false}, have_p[3] = {false, false, false};
  for (std::size_t c = 0; c < names.size(); ++c) {
    const std::string& n = names[c];
    const std::string at = path + ": row " + std::to_string(header_row) + ", column ";
    if (n.empty()) throw DataError(at + std::to_string(c + 1) + ": empty column name");
    for (std::size_t k = 0; k < c; ++k)
      if (names[k] == n) throw DataError(at + n + ": duplicate column name");
    ColumnSlot s{Target::kAux, -1, n};
    if (n == "time_s") {
      s.target = Target::kTime;
      have_time = true;
    } else if (n == "segment") {
      s.target = Target::kSegment;
    } else if (n == "phase") {
      s.target = Target::kPhase;
    } else {
      for (int a = 0; a < 3; ++a) {
        if (n == voltage_column(kAxisNames[a])) { s = {Target::kVoltage, a, n}; have_v[a] = true; }
        else if (n == position_column(kAxisNames[a])) { s = {Target::kPosition, a, n}; have_p[a] = true; }
        else if (n == true_position_column(kAxisNames[a])) { s = {Target::kTruth, a, n}; }
      }
    }
    if (s.target == Target::kAux) {
      s.index = static_cast<int>(d.aux.size());
      d.aux.push_back({n, {}});
    }
    slots.push_back(s);
  }
  if (!have_time) throw DataError(path + ": missing column time_s");
  int axis_of[3] = {-1, -1, -1};
  for (int a = 0; a < 3; ++a) {
    if (have_v[a] != have_p[a])
      throw DataError(path + ": missing column " +
                      (have_v[a] ? position_column(kAxisNames[a]) : voltage_column(kAxisNames[a])) + " (axis '" + kAxisNames[a] +
                      "' needs both voltage and position)");
    if (have_v[a]) {
      AxisSeries s;
      s.name = kAxisNames[a];
      axis_of[a] = static_cast<int>(d.axes.size());
      d.axes.push_back(std::move(s));
    }
  }
  if (d.axes.empty())
    throw DataError(path + ": missing axis columns: need <axis>_voltage_v and <axis>_position_nm for an axis a, b or c");
  for (auto& s : slots)
    if (s.target == Target::kVoltage || s.target == Target::kPosition || s.target == Target::kTruth) {
      if (axis_of[s.index] < 0)
        throw DataError(path + ": row 1, column " + s.name + ": ground truth for an axis without voltage/position");
      s.index = axis_of[s.index];
    }
  return slots;
}

// One data row's cells into their columns (time must increase).
void csv_row(std::string_view line, std::size_t row, const std::string& path, const std::vector<ColumnSlot>& slots,
             const std::vector<std::vector<double>*>& dest, const std::vector<double>& time_s) {
  std::size_t start = 0;
  for (std::size_t c = 0; c < slots.size(); ++c) {
    if (start > line.size())
      throw DataError(path + ": row " + std::to_string(row) + ", column " + slots[c].name + ": missing value (row has " +
                      std::to_string(c) + " of " + std::to_string(slots.size()) + " columns)");
    std::size_t comma = line.find(',', start);
    std::string_view cell = line.substr(start, comma == std::string_view::npos ? std::string_view::npos : comma - start);
    while (!cell.empty() && (cell.front() == ' ' || cell.front() == '\t')) cell.remove_prefix(1);
    while (!cell.empty() && (cell.back() == ' ' || cell.back() == '\t')) cell.remove_suffix(1);
    double v = 0.0;
    if (cell.empty())
      throw DataError(path + ": row " + std::to_string(row) + ", column " + slots[c].name + ": empty cell");
    const char* b = cell.data();
    if (*b == '+') ++b;
    auto [ptr, ec] = std::from_chars(b, cell.data() + cell.size(), v);
    if (ec != std::errc() || ptr != cell.data() + cell.size())
      throw DataError(path + ": row " + std::to_string(row) + ", column " + slots[c].name + ": not a number: '" +
                      std::string(cell) + "'");
    if (!std::isfinite(v))
      throw DataError(path + ": row " + std::to_string(row) + ", column " + slots[c].name + ": " + std::string(cell) +
                      " is not a finite number");
    if (slots[c].target == Target::kTime && !time_s.empty() && !(v > time_s.back()))
      throw DataError(path + ": row " + std::to_string(row) + ", column time_s: time does not increase (" +
                      std::to_string(time_s.back()) + " then " + std::string(cell) + ")");
    dest[c]->push_back(v);
    start = (comma == std::string_view::npos) ? line.size() + 1 : comma + 1;
  }
  if (start <= line.size())
    throw DataError(path + ": row " + std::to_string(row) + ": more cells than the " + std::to_string(slots.size()) +
                    " header columns");
}

}  // namespace

Dataset read_csv(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) throw DataError(path + ": cannot open file");
  CsvLines lines;
  lines.text.assign((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  if (lines.text.empty()) throw DataError(path + ": file is empty (expected a header row)");
  Dataset d;
  std::size_t header_row = 1;
  const std::vector<std::string> names = csv_header(lines, path, d, header_row);
  d.source = path;
  const std::vector<ColumnSlot> slots = csv_slots(names, path, header_row, d);

  // Reserve from a cheap line count to avoid reallocations on million-row files.
  const std::string& text = lines.text;
  const std::size_t approx_rows =
      static_cast<std::size_t>(std::count(text.begin() + std::min(lines.pos, text.size()), text.end(), '\n')) + 1;
  std::vector<std::vector<double>*> dest(slots.size(), nullptr);
  std::vector<double> seg_tmp, phase_tmp;
  for (std::size_t c = 0; c < slots.size(); ++c) {
    const auto& s = slots[c];
    switch (s.target) {
      case Target::kTime: dest[c] = &d.time_s; break;
      case Target::kVoltage: dest[c] = &d.axes[s.index].voltage_v; break;
      case Target::kPosition: dest[c] = &d.axes[s.index].position_nm; break;
      case Target::kTruth: dest[c] = &d.axes[s.index].true_position_nm; break;
      case Target::kSegment: dest[c] = &seg_tmp; break;
      case Target::kPhase: dest[c] = &phase_tmp; break;
      case Target::kAux: dest[c] = &d.aux[s.index].values; break;
    }
    dest[c]->reserve(approx_rows);
  }

  std::string_view line;
  std::size_t row = header_row;
  while (lines.next(line)) {
    ++row;
    if (trim(line).empty()) {
      if (lines.at_end()) break;  // trailing newline
      throw DataError(path + ": row " + std::to_string(row) + ": empty line");
    }
    csv_row(line, row, path, slots, dest, d.time_s);
  }
  if (d.time_s.empty()) throw DataError(path + ": no data rows after the header");
  for (double v : seg_tmp) d.segment.push_back(static_cast<int>(std::lround(v)));
  for (double v : phase_tmp) d.phase.push_back(static_cast<int>(std::lround(v)));
  for (auto& a : d.axes)
    if (a.true_position_nm.size() != d.time_s.size()) a.true_position_nm.clear();
  return d;
}

void write_csv(const std::string& path, const Dataset& d) {
  d.validate();
  const std::string tmp = path + ".partial";
  {
    std::unique_ptr<FILE, int (*)(FILE*)> f(std::fopen(tmp.c_str(), "w"), &std::fclose);
    if (!f) throw DataError(path + ": cannot open for writing");
    std::string line = d.origin.empty() ? std::string() : "# origin: " + d.origin + "\n";
    line += "time_s";
    for (const auto& a : d.axes) {
      line += "," + voltage_column(a.name) + "," + position_column(a.name);
      if (a.has_truth()) line += "," + true_position_column(a.name);
    }
    if (!d.segment.empty()) line += ",segment";
    if (!d.phase.empty()) line += ",phase";
    for (const auto& x : d.aux) line += "," + x.name;
    line += "\n";
    std::fputs(line.c_str(), f.get());
    char buf[64];
    for (std::size_t i = 0; i < d.size(); ++i) {
      line.clear();
      auto put = [&](double v, bool first = false) {
        if (!first) line += ',';
        auto [p, ec] = std::to_chars(buf, buf + sizeof buf, v);
        (void)ec;
        line.append(buf, p);
      };
      put(d.time_s[i], true);
      for (const auto& a : d.axes) {
        put(a.voltage_v[i]);
        put(a.position_nm[i]);
        if (a.has_truth()) put(a.true_position_nm[i]);
      }
      if (!d.segment.empty()) line += "," + std::to_string(d.segment[i]);
      if (!d.phase.empty()) line += "," + std::to_string(d.phase[i]);
      for (const auto& x : d.aux) put(x.values[i]);
      line += '\n';
      if (std::fputs(line.c_str(), f.get()) < 0) throw DataError(path + ": write failed (disk full?)");
    }
    if (std::fflush(f.get()) != 0) throw DataError(path + ": write failed (disk full?)");
    // The data must be on the disk before the rename makes it the real file (a power cut after a rename of
    // unsynced data can leave an empty file under the real name).
    if (::fsync(::fileno(f.get())) != 0) throw DataError(path + ": fsync failed: " + std::strerror(errno));
  }
  // Rename only when complete, so a crash never leaves a half-written data file under the real name.
  if (std::rename(tmp.c_str(), path.c_str()) != 0) throw DataError(path + ": cannot rename " + tmp);
  // Then the directory entry that names it.
  if (const std::string e = fsync_parent(path); !e.empty()) throw DataError(path + ": directory " + e);
}

}  // namespace piezo::io
